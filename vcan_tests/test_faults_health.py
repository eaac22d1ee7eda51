"""The device health model in Devtab, on virtual time: a driver-reported failure is cleared only by
the driver's end event, staleness only by fresh data, safe values go out whatever the status, and
the map shows status, cause and time (issue 15, items 1, 4 and 10)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from chcos.devices.entry import DeviceEntry, DeviceStatus
from chcos.errors import DeviceError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.system.textview import render_text

MAP = """
[[bus]]
name = "mem"
kind = "memory"

[[device]]
name = "S"
direction = "sensor"
bus = "mem"
stale_after = 0.5

[[device]]
name = "M"
direction = "actuator"
bus = "mem"
limits = [0, 10]
safe_value = 1
"""


def status(e: DeviceEntry) -> DeviceStatus:
    """The entry's status, read fresh (keeps mypy from narrowing it across runs)."""
    return e.status


@pytest.fixture
def system(tmp_path: Path) -> System:
    path = tmp_path / "mem.toml"
    path.write_text(MAP, encoding="utf-8")
    return System([path], clock=VirtualClock(), machines=[0], map_path=tmp_path / "sysfile.map")


def test_a_reading_does_not_clear_a_failure_the_driver_reported(system: System) -> None:
    s, dt = system, system.devtab
    seen: list[tuple[str, bool, str]] = []
    dt.add_health_listener(lambda d, ok, cause: seen.append((d, ok, cause)))
    dt.inject("S", 1.0)
    s.run_for(0.1)
    dt.fail("S", "heartbeat lost")
    s.run_for(0.1)
    dt.inject("S", 2.0)                          # an unrelated reading
    s.run_for(0.1)
    e = dt.get("S")
    assert status(e) is DeviceStatus.FAILED and e.reason == "heartbeat lost"
    # a failed sensor delivers nothing until the failure ends (issue 48): dropped, counted
    assert e.value == 1.0 and e.dropped == 1 and e.since == pytest.approx(0.1)
    dt.recover("S", "heartbeat back")
    s.run_for(0.1)
    assert status(e) is DeviceStatus.OK
    assert seen == [("S", False, "heartbeat lost"), ("S", True, "heartbeat back")]


def test_a_link_back_does_not_make_a_stale_sensor_ok(system: System) -> None:
    s, dt = system, system.devtab
    s.run_for(1.0)                               # no data: stale
    e = dt.get("S")
    assert status(e) is DeviceStatus.STALE
    dt.fail("S", "link down")
    s.run_for(0.1)
    assert status(e) is DeviceStatus.FAILED
    dt.recover("S", "link up")
    s.run_for(0.1)
    assert status(e) is DeviceStatus.STALE        # still no data
    dt.inject("S", 3.0)
    s.run_for(0.01)
    assert status(e) is DeviceStatus.OK


def test_safe_values_reach_failed_and_suspended_actuators(system: System) -> None:
    s, dt = system, system.devtab
    dt.write("M", 7)
    s.run_for(0.1)
    dt.fail("M", "write refused")
    s.run_for(0.1)
    with pytest.raises(DeviceError, match="failed"):
        dt.write("M", 8)
    assert dt.estop("test") == 1
    assert dt.get("M").value == 1
    dt.set_status("M", DeviceStatus.SUSPENDED, "by the host")
    with pytest.raises(DeviceError, match="suspended"):
        dt.write("M", 8)
    assert dt.stop_drivers() == []
    assert dt.get("M").value == 1 and dt.safe_failures == []


def test_recovery_of_an_actuator_writes_its_safe_value_before_any_command(
        system: System) -> None:
    s, dt = system, system.devtab
    writes: list[tuple[str, object]] = []
    dt.on_write.append(lambda d, v: writes.append((d, v)))
    dt.write("M", 7)
    dt.fail("M", "link down")
    s.run_for(0.1)
    dt.recover("M", "link up")
    s.run_for(0.1)
    assert writes == [("M", 7), ("M", 1)]
    assert dt.get("M").value == 1


def test_nan_and_infinities_never_reach_an_actuator(system: System) -> None:
    dt = system.devtab
    for bad in (float("nan"), float("inf"), float("-inf")):
        with pytest.raises(DeviceError, match=r"M"):
            dt.write("M", bad)
    assert dt.get("M").commands == 0 and dt.get("M").rejected == 3


def test_the_map_shows_status_cause_and_time_of_change(system: System, tmp_path: Path) -> None:
    s, dt = system, system.devtab
    s.run_for(0.2)
    dt.fail("S", "canopen node 3: no heartbeat")
    s.run_for(0.1)
    doc = json.loads((tmp_path / "sysfile.map").read_text(encoding="utf-8"))
    dev = next(d for d in doc["devices"] if d["name"] == "S")
    assert dev["status"] == "failed" and dev["reason"] == "canopen node 3: no heartbeat"
    assert dev["since"] == pytest.approx(0.2)
    assert "since t=0.200: canopen node 3: no heartbeat" in render_text(doc)


def test_staleness_is_judged_from_the_drivers_receive_time(system: System) -> None:
    s, dt = system, system.devtab
    clock = s.kernel.clock
    assert isinstance(clock, VirtualClock)
    clock.advance(0.3)
    dt.deliver("S", 1.0)                         # received by the driver at t=0.3 ...
    clock.advance(0.05)                          # ... handled by the kernel at t=0.35
    s.run_for(0.01)
    e = dt.get("S")
    assert e.rx_at == pytest.approx(0.3) and e.updated_at == pytest.approx(0.35)
    s.run_for(0.44)                              # t=0.80: 0.5 s after it was received
    assert status(e) is DeviceStatus.STALE and e.since == pytest.approx(0.8)
