"""The good-gap welding job over real SocketCAN (vcan0: the CANopen servos, vcan1: the raw CAN
sensors) inside User-Mode Linux; skipped where no SocketCAN channel is up. The host-side round trip
in test_uml_socketcan.py runs every `socketcan` test inside UML."""

from __future__ import annotations

from pathlib import Path

import pytest

from chcos.weldrun import open_cell

pytestmark = pytest.mark.socketcan


def test_good_gap_over_socketcan(tmp_path: Path) -> None:
    from vcan_tests.uml import socketcan_channel

    if socketcan_channel() is None:
        pytest.skip("no SocketCAN channel (vcan0): runs inside User-Mode Linux")
    with open_cell("buses", workdir=tmp_path, interface="socketcan",
                   channels=("vcan0", "vcan1")) as cell:
        cell.start_job(None)
        cell.run(200.0)
        outcome = cell.outcome()
        summary = cell.summary()
    assert outcome is not None and outcome["outcome"] == "welded", outcome
    assert summary["welded_mm"] >= 0.99 * summary["seam_mm"], summary
    assert summary["in_band_pct"] >= 95.0, summary
