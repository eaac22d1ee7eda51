"""The pytest plugin as faithful as the device: a failed sensor delivers nothing until it
recovers, cell.set holds against a value script until cell.release, a reading outside the
sensor's limits is a failure with the reason ``limit`` (on Modbus and on CAN), and cell.set
reaches any raw value the wire carries (past a DBC's limits: raw is the value on the bus before
the device's own scale and offset, a DBC signal's physical value)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from chcos.cli import scaffold
from chcos.errors import DeviceError, SensorFailure
from chcos.testing import TestCell
from vcan_tests.test_can_restbus_cell import _project


@pytest.fixture
def project(tmp_path: Path) -> Path:
    scaffold.create(tmp_path / "cell", port=5020)
    return tmp_path / "cell"


def test_a_failed_sensor_delivers_nothing_until_recovered(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    cell.set("level", 90.0)
    cell.run_for(1.0)
    entry = cell.system.devtab.get("level")
    cell.fail("level", "float switch broken")
    before = entry.readings
    cell.set("level", 95.0)
    cell.run_for(1.0)                     # ten polls of the PLC meanwhile
    assert entry.readings == before and entry.dropped >= 5
    assert cell.status("level") == "failed" and cell.value("level") == pytest.approx(90.0)
    with pytest.raises(SensorFailure, match="float switch broken"):
        cell.system.devtab.check_readable("level")
    cell.recover("level")
    cell.run_for(0.3)
    assert cell.status("level") == "OK" and cell.value("level") == pytest.approx(95.0)


def test_set_wins_over_the_value_script_until_released(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml", values={"level": "ramp(0, 100, 10)"})
    cell.run_for(2.0)
    assert 15 < cell.value("level") < 25
    cell.set("level", 140.0)
    cell.run_for(2.0)                     # the script would be at 40 by now
    assert cell.value("level") == pytest.approx(140.0)
    cell.release("level")
    cell.run_for(0.5)
    assert 40 < cell.value("level") < 50  # the script again
    with pytest.raises(DeviceError, match="'level' is not held"):
        cell.release("level")


def test_a_reading_outside_the_limits_fails_the_sensor_with_the_reason_limit(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")   # level: limits [0, 200] cm on Modbus
    cell.set("level", 90.0)
    cell.run_for(1.0)
    cell.set("level", 250.0)
    cell.run_for(0.5)
    assert cell.status("level") == "failed"
    reason = cell.system.devtab.get("level").reason
    assert reason == "limit: reading 250 cm outside [0, 200]"
    assert cell.value("level") == pytest.approx(250.0)    # shown as the device sent it, ...
    with pytest.raises(SensorFailure, match="limit"):     # ... but no reader gets it
        cell.system.devtab.check_readable("level")
    assert cell.task("fill").abnormal == 1 and "limit" in cell.task("fill").last_error
    cell.set("level", 100.0)
    cell.run_for(0.5)
    assert cell.status("level") == "OK" and cell.value("level") == pytest.approx(100.0)


def test_set_raw_sends_what_the_dbc_forbids_and_the_limit_rule_catches_it_on_can(
        tmp_path: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(_project(tmp_path) / "system.toml")   # LEVEL: DBC [0, 200], map [0, 150]
    with pytest.raises(Exception, match="LEVEL"):
        cell.set("level", 600.0)          # the ECU encodes within the DBC's limits
    cell.set("level", raw=600.0)           # the 16 bits x 0.1 carry up to 6553.5
    cell.run_for(0.2)
    assert cell.status("level") == "failed"
    assert cell.system.devtab.get("level").reason.startswith("limit: reading 600 cm")
    with pytest.raises(DeviceError, match="outside what signal LEVEL carries"):
        cell.set("level", raw=7000.0)     # more than the 16 bits carry
    cell.set("level", raw=90.0)
    cell.run_for(0.2)
    assert cell.status("level") == "OK" and cell.value("level") == pytest.approx(90.0)


def test_a_simulated_sensor_starts_at_a_value_its_device_would_show() -> None:
    from chcos.apps.sim.from_map import within_limits
    from chcos.devices.spec import DeviceSpec

    def sensor(**kw: object) -> DeviceSpec:
        return DeviceSpec("s", "sensor", 0, "b", **kw)  # type: ignore[arg-type]

    assert within_limits(sensor()) is None                          # 0 is served
    assert within_limits(sensor(limits=(0.0, 60.0))) is None
    assert within_limits(sensor(limits=(103.0, 103.0))) == 103.0    # a SunSpec model id
    assert within_limits(sensor(limits=(-40.0, -5.0))) == -5.0
    assert within_limits(sensor(address={"unimplemented": 0}, scale=10.0)) == 10.0
    assert within_limits(sensor(address={"unimplemented": 0x8000})) is None
