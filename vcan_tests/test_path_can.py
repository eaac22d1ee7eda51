"""Full path through the kernel on python-can's virtual bus: a sensor frame on the bus reaches
Devtab, readies the driver task at its link's priority, and the task's actuator command goes out
as a frame; limits, staleness and safe values on the same path."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.can_device import CanDeviceSim
from chcos.errors import DeviceError, SensorFailure
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from vcan_tests.netutil import unique_channel

M = "vcan_tests.test_path_can"

DBC = """VERSION ""
NS_ :
BS_:
BU_: Node Chcos
BO_ 256 Temps: 2 Node
 SG_ T1 : 0|16@1+ (0.1,0) [0|1000] "degC" Chcos
BO_ 512 Heater: 2 Chcos
 SG_ Power : 0|16@1+ (0.1,0) [0|100] "%" Node
"""


def devmap(tmp: Path, channel: str) -> Path:
    (tmp / "cell.dbc").write_text(DBC)
    path = tmp / "cell.toml"
    path.write_text(f"""
[[bus]]
name = "can0"
kind = "can"
interface = "virtual"
channel = "{channel}"
dbc = "cell.dbc"

[[device]]
name = "T1"
direction = "sensor"
bus = "can0"
address = {{ message = "Temps", signal = "T1" }}
priority = 30
stale_after = 0.5
units = "degC"

[[device]]
name = "H1"
direction = "actuator"
bus = "can0"
address = {{ message = "Heater", signal = "Power" }}
limits = [0, 80]
safe_value = 0
units = "%"
""")
    return path


async def thermostat(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Heater power proportional to the error; logs every reading and failure."""
    while True:
        try:
            t = await ctx.read("T1")
        except SensorFailure as exc:
            cmd["log"].append(("failure", exc.device))
            ctx.write("H1", 0.0)
            return
        cmd["log"].append((t, ctx.priority))
        power = 2.0 * (cmd["setpoint"] - t)
        try:
            ctx.write("H1", max(0.0, power))
        except DeviceError as exc:
            cmd["log"].append(("refused", str(exc)))


@pytest.fixture
def cell(tmp_path: Path) -> Any:
    channel = unique_channel("path")
    mapfile = devmap(tmp_path, channel)
    sim = CanDeviceSim(tmp_path / "cell.dbc", interface="virtual", channel=channel)
    s = System([mapfile], clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    s.execute(f"install -m0i1o1 --code={M}:thermostat TH T1 H1")
    yield s, sim
    s.shutdown()
    sim.close()


def test_frame_in_task_frame_out(cell: Any) -> None:
    s, sim = cell
    log: list[Any] = []
    s.invoke("TH", {"log": log, "setpoint": 50.0})
    s.run_for(0.05)
    sim.set("Temps", T1=40.0)
    sim.send("Temps")
    s.run_for(0.05)
    assert log == [(40.0, 30)]  # read at the sensor link's priority
    assert sim.wait_for("Heater", "Power", lambda v: abs(v - 20.0) < 0.05, timeout=5)
    assert s.devtab.get("T1").readings == 1


def test_out_of_limits_command_is_refused_not_clamped(cell: Any) -> None:
    s, sim = cell
    log: list[Any] = []
    s.invoke("TH", {"log": log, "setpoint": 100.0})
    s.run_for(0.05)
    sim.set("Temps", T1=10.0)
    sim.send("Temps")
    s.run_for(0.05)
    refused = [e for e in log if e[0] == "refused"]
    assert refused and "180.0" in refused[0][1] and "outside its limits [0.0, 80.0]" in \
        refused[0][1]
    assert s.devtab.get("H1").rejected == 1


def test_silence_makes_the_sensor_stale_and_the_actuator_safe(cell: Any) -> None:
    s, sim = cell
    log: list[Any] = []
    s.invoke("TH", {"log": log, "setpoint": 50.0})
    sim.set("Temps", T1=45.0)
    sim.send("Temps")
    s.run_for(0.1)
    s.run_for(1.0)  # no frame for 1 s: stale after 0.5 s
    assert ("failure", "T1") in log
    assert s.devtab.get("T1").status.value == "stale"
    assert sim.wait_for("Heater", "Power", lambda v: v == 0.0, timeout=5)
