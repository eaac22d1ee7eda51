"""The bus option ``sync_priority`` (the SYNC producer process's SCHED_FIFO priority) offline:
``chcos check`` refuses a value out of 0..99, or one without ``sync_period``, naming the key,
and passes the same map with a valid value. The producer running at that priority is tested on
real SocketCAN (vcan_tests/test_canopen_sync_socketcan.py)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver

ROOT = Path(__file__).resolve().parent.parent

MAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "sync-priority"
{options}

[[bus.nodes]]
id = 5
eds = "{eds}"
nmt_start = false
"""


def chcos_check(tmp_path: Path, options: str) -> subprocess.CompletedProcess[str]:
    path = tmp_path / "cell.toml"
    path.write_text(MAP.format(options=options, eds=SERVO_EDS.as_posix()), encoding="utf-8")
    return subprocess.run([sys.executable, "-m", "chcos.cli.main", "check", str(path)],
                          capture_output=True, text=True, timeout=120, check=False,
                          cwd=ROOT)


def errors(**opts: Any) -> list[str]:
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "virtual", "channel": "x", **opts,
        "nodes": [{"id": 5, "eds": str(SERVO_EDS), "nmt_start": False}]})
    return [e for e in CanopenDriver.check_bus(bus) if "sync_priority" in e]


def test_chcos_check_refuses_an_out_of_range_sync_priority_naming_the_key(
        tmp_path: Path) -> None:
    out = chcos_check(tmp_path, "sync_period = 0.004\nsync_priority = 100")
    assert out.returncode == 1, out.stdout + out.stderr
    assert "bus[0].sync_priority" in out.stdout + out.stderr
    assert "1..99, or 0" in out.stdout + out.stderr
    good = chcos_check(tmp_path, "sync_period = 0.004\nsync_priority = 99")
    assert good.returncode == 0, good.stdout + good.stderr


@pytest.mark.parametrize("value", [-1, 100, 80.0, True, "80"])
def test_a_sync_priority_not_an_integer_0_to_99_is_refused(value: object) -> None:
    errs = errors(sync_period=0.004, sync_priority=value)
    assert len(errs) == 1 and errs[0].startswith("bus[0].sync_priority: expected"), errs


@pytest.mark.parametrize("value", [0, 1, 80, 99])
def test_a_sync_priority_0_to_99_passes(value: int) -> None:
    assert errors(sync_period=0.004, sync_priority=value) == []


def test_a_sync_priority_without_sync_period_is_refused() -> None:
    errs = errors(sync_priority=80)
    assert len(errs) == 1 and "no sync_period" in errs[0], errs
