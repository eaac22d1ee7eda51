"""Two CiA 402 axes on one node through the whole stack (issue 37): a device map with two axis
tables on node 5 (axis 0 and axis 1, objects 0x800 apart), a System on a virtual clock, one task
per axis commanding ``ctx.axis``, the CANopen driver hosting both engines, against the
independent two-axis durand drive (vcan_tests/peers/durand_cia402_multi.py). Both axes are
enabled and moved; one faults and is reset while the other keeps moving; both are safely
stopped at shutdown. Every assertion is about what each AXIS of the drive received and the state
it is in, or what Devtab reports."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from chcos.errors import ChcosError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_cia402 import ENABLED, FAULT, SOD, DurandCia402Drive
from vcan_tests.peers.durand_cia402_multi import TwoAxisDrive, two_axis_eds

M = "vcan_tests.test_cia402_multi_axis"
NODE = 5
STEP = 0.02
WALL = 20.0     # wall-clock seconds a condition may take on a loaded machine
AXES = ("x", "y")


async def axis_steps(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Runs ``cmd["steps"]`` on axis ``cmd["axis"]``: ``(op, *args)``; each outcome goes to
    ``cmd["log"]`` as (axis, op, "ok" or the error)."""
    name = cmd["axis"]
    axis = ctx.axis(name)
    for op, *args in cmd["steps"]:
        try:
            await getattr(axis, op)(*args)
        except ChcosError as exc:
            cmd["log"].append((name, op, exc))
            continue
        cmd["log"].append((name, op, "ok"))


def two_axis_map(channel: str, eds: Path) -> str:
    keys = ('mode = "PV"\nquick_stop_option = 2\ncounts_per_unit = 1000.0\n'
            "timeouts = { enable = 5.0, disable = 5.0, quick_stop = 10.0, fault_reset = 5.0, "
            "set_mode = 2.0, move = 60.0, velocity = 10.0, safe_stop = 10.0 }")
    return f"""
[[bus]]
name = "drives"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
nodes = [{{ id = {NODE}, eds = "{eds}" }}]

[[device]]
name = "x"
profile = "cia402"
bus = "drives"
units = "mm"
address = {{ node = {NODE} }}
{keys}

[[device]]
name = "y"
profile = "cia402"
bus = "drives"
units = "mm"
address = {{ node = {NODE}, axis = 1 }}
{keys}
"""


@dataclass
class Rig:
    """The system, the two-axis drive, and the tasks' log."""

    s: System
    drive: TwoAxisDrive
    log: list[tuple[str, str, Any]] = field(default_factory=list)

    def axis(self, name: str) -> DurandCia402Drive:
        return self.drive.axes[AXES.index(name)]

    def run(self, pred: Callable[[], bool], wall: float = WALL) -> bool:
        """Step the drive and the virtual clock together until ``pred()``; before virtual
        time goes on, chcos has seen both statuswords the drive last published."""
        deadline = time.monotonic() + wall
        while not pred():
            if time.monotonic() > deadline:
                return False
            self.drive.step(STEP)
            self.caught_up()
            self.s.run_for(STEP)
        return True

    def caught_up(self, wall: float = 2.0) -> None:
        deadline = time.monotonic() + wall
        while (any(self.value(f"{n}.statusword") != self.axis(n).published()[0] for n in AXES)
               and time.monotonic() < deadline):
            self.s.run_for(0.0)

    def do(self, name: str, *steps: tuple[Any, ...]) -> list[tuple[str, str, Any]]:
        """Invoke axis ``name``'s task with ``steps`` and run until it reported each."""
        start = len(self.log)
        self.s.invoke(name.upper(), {"axis": name, "steps": list(steps), "log": self.log})
        assert self.run(lambda: len(self.log) >= start + len(steps)), self.log
        return self.log[start:]

    def value(self, name: str) -> Any:
        return self.s.devtab.get(name).value

    def status(self, name: str) -> str:
        return self.s.devtab.get(name).status.value


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    channel = unique_channel("axes2")
    drive = TwoAxisDrive(channel, NODE)
    eds = tmp_path / "two_axis.eds"
    eds.write_text(two_axis_eds(), encoding="utf-8")
    path = tmp_path / "axes.toml"
    path.write_text(two_axis_map(channel, eds), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    s.execute(f"install -m0o1 --code={M}:axis_steps X x")
    s.execute(f"install -m0o1 --code={M}:axis_steps Y y")
    r = Rig(s, drive)
    try:
        assert r.run(lambda: all(r.value(f"{n}.state") == "SWITCH_ON_DISABLED" for n in AXES))
        yield r
    finally:
        s.shutdown()
        drive.close()


def ok(name: str, *ops: str) -> list[tuple[str, str, str]]:
    return [(name, op, "ok") for op in ops]


def stopped_before_disable(axis: DurandCia402Drive, n: int) -> None:
    """Quick stop while moving, disable voltage only once stopped, as the axis logged it."""
    log = axis.log[n:]
    assert log and log[0][0] == 0x02 and log[0][1] == ENABLED and log[0][2] > 0, log
    assert all(speed == 0 for cw, _state, speed in log if cw == 0x00), log
    assert log[-1][0] == 0x00


def test_two_axes_move_one_faults_and_is_reset_while_the_other_moves_on(rig: Rig) -> None:
    x, y = rig.axis("x"), rig.axis("y")
    assert rig.do("x", ("set_mode",), ("enable",), ("at_velocity", 2.0)) == \
        ok("x", "set_mode", "enable", "at_velocity")
    assert rig.do("y", ("set_mode",), ("enable",), ("at_velocity", -3.0)) == \
        ok("y", "set_mode", "enable", "at_velocity")
    # each axis walked its own state machine; neither heard the other's commands
    assert x.received[:4] == [0x00, 0x06, 0x07, 0x0F] and y.received[:4] == [0x00, 0x06, 0x07,
                                                                             0x0F]
    assert x.state == ENABLED and y.state == ENABLED
    assert x.read(0x6061) == 3 and y.read(0x6061) == 3
    assert x.velocity == 2000 and y.velocity == -3000
    assert rig.run(lambda: rig.value("x.velocity") == pytest.approx(2.0)
                   and rig.value("y.velocity") == pytest.approx(-3.0))

    nx = len(x.received)
    y.inject_fault(0x2310)
    assert rig.run(lambda: rig.status("y") == "failed" and rig.value("y.fault") == 0x2310)
    assert "0x2310" in rig.s.devtab.get("y").reason and y.state == FAULT and y.velocity == 0
    # the other axis keeps moving, healthy, commanded by nobody
    assert rig.status("x") == "OK" and x.state == ENABLED and x.velocity == 2000
    assert rig.value("x.state") == "OPERATION_ENABLED" and rig.value("x.fault") == 0
    before = x.position
    assert rig.run(lambda: x.position > before + 100)

    ny = len(y.received)
    assert rig.do("y", ("fault_reset",)) == ok("y", "fault_reset")
    assert y.received[ny:] == [0x00, 0x80] and y.state == SOD
    assert rig.run(lambda: rig.status("y") == "OK")
    assert x.received[nx:] == [] and x.state == ENABLED and x.velocity == 2000
    assert rig.do("y", ("enable",), ("at_velocity", 1.0)) == ok("y", "enable", "at_velocity")
    assert y.state == ENABLED and y.velocity == 1000
    assert x.received[nx:] == [] and x.velocity == 2000


def test_shutdown_stops_both_axes_safely_on_the_drive(rig: Rig) -> None:
    x, y = rig.axis("x"), rig.axis("y")
    rig.do("x", ("set_mode",), ("enable",), ("at_velocity", 2.0))
    rig.do("y", ("set_mode",), ("enable",), ("at_velocity", 4.0))
    nx, ny = len(x.log), len(y.log)
    stop = threading.Event()

    def motor() -> None:           # the drive's own time goes on while chcos shuts down
        while not stop.wait(0.005):
            rig.drive.step(STEP)

    stepper = threading.Thread(target=motor, daemon=True)
    stepper.start()
    try:
        rig.s.shutdown()
    finally:
        stop.set()
        stepper.join(5)
    for name in AXES:
        outcome = rig.s.devtab.safe_outcomes[name]
        assert outcome.written, outcome
    assert x.state == SOD and y.state == SOD and x.velocity == 0 and y.velocity == 0
    stopped_before_disable(x, nx)
    stopped_before_disable(y, ny)
