"""The good-gap welding job over real SocketCAN (vcan0: the CANopen servos, vcan1: the raw CAN
sensors) inside User-Mode Linux; skipped where no SocketCAN channel is up.

UML's system calls are slow (its timer makes every short receive timeout cost milliseconds), so the
whole job takes about 20 minutes there: it runs only with CHCOS_UML_WELD=1, e.g.
``CHCOS_UML_WELD=1 tools/uml/run-in-uml --timeout 2400 -- .venv/bin/pytest -m socketcan
vcan_tests/test_weldcell_socketcan.py``. The host-side round trip in test_uml_socketcan.py runs
every other `socketcan` test inside UML on every CI run."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from chcos.weldrun import open_cell

pytestmark = pytest.mark.socketcan


def test_good_gap_over_socketcan(tmp_path: Path) -> None:
    from vcan_tests.uml import socketcan_channel

    if socketcan_channel() is None:
        pytest.skip("no SocketCAN channel (vcan0): runs inside User-Mode Linux")
    if os.environ.get("CHCOS_UML_WELD") != "1":
        pytest.skip("the whole welding job takes ~20 min inside UML: set CHCOS_UML_WELD=1")
    with open_cell("buses", workdir=tmp_path, interface="socketcan",
                   channels=("vcan0", "vcan1")) as cell:
        cell.start_job(None)
        cell.run(200.0)
        outcome = cell.outcome()
        summary = cell.summary()
    assert outcome is not None and outcome["outcome"] == "welded", outcome
    assert summary["welded_mm"] >= 0.99 * summary["seam_mm"], summary
    assert summary["in_band_pct"] >= 95.0, summary
