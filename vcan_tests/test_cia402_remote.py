"""``ctx.axis`` on an axis hosted by another satellite (issue 37): two satellites' Systems joined
by the in-memory stand-in for the Zenoh transport (vcan_tests/test_sat_comm.py), on virtual
time; the axis is on machine 1's CANopen bus, against the independent durand drive; the task
commanding it runs on machine 0. Its commands travel over the satellite link, run on machine 1's
driver, and complete with what the DRIVE confirmed; an unknown axis, a satellite that is down
and one that dies before answering give the task a clear error."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from chcos.comm.codec import MessageKind, decode_batch
from chcos.errors import ChcosError, MessageError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from drivers.codecs.cia402 import AxisCommandFailed, State
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_cia402 import ENABLED, FAULT, SOD, DurandCia402Drive
from vcan_tests.support_cia402 import drive_eds, remote_axis_map
from vcan_tests.test_sat_comm import LoopNet, LoopTransport

M = "vcan_tests.test_cia402_remote"
NODE = 5
STEP = 0.02
WALL = 20.0


async def remote_steps(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Runs ``cmd["steps"]`` on axis ``cmd.get("axis", "x")``: ``(op, *args)``, or
    ``("raise",)``; logs (op, "ok" or the error), and after each the state the handle shows."""
    log: list[tuple[str, Any]] = cmd["log"]
    try:
        axis = ctx.axis(cmd.get("axis", "x"))
    except ChcosError as exc:
        log.append(("axis", exc))
        return
    for op, *args in cmd["steps"]:
        if op == "raise":
            raise RuntimeError("the task's own error")
        try:
            await getattr(axis, op)(*args)
        except ChcosError as exc:
            log.append((op, exc))
            continue
        log.append((op, "ok"))
        cmd.setdefault("states", []).append(axis.state)


def axis_map(channel: str, eds: Path) -> str:
    return remote_axis_map(channel, eds, NODE) + f"""
[[device]]
name = "lamp"
direction = "actuator"
machine = 1
bus = "drives"
safe_value = 0
address = {{ node = {NODE}, index = 0x6081 }}
"""


@dataclass
class Pair:
    """Machine 0 (the task) and machine 1 (the axis's bus), the link between them, the drive."""

    m0: System
    m1: System
    net: LoopNet
    drive: DurandCia402Drive
    log: list[tuple[str, Any]] = field(default_factory=list)
    states: list[Any] = field(default_factory=list)

    def cycle(self, advance: bool = True) -> None:
        if advance:
            self.drive.step(STEP)
        for s in (self.m0, self.m1):
            s.run_for(STEP if advance else 0.0)
        self.net.deliver()

    def run(self, pred: Callable[[], bool], wall: float = WALL) -> bool:
        """Step the drive, both satellites and the link until ``pred()``; virtual time goes on
        only once machine 1 has seen the drive's last statusword."""
        deadline = time.monotonic() + wall
        while not pred():
            if time.monotonic() > deadline:
                return False
            self.cycle(advance=self.caught_up())
        return True

    def caught_up(self) -> bool:
        return bool(self.m1.devtab.get("x.statusword").value == self.drive.published()[0])

    def do(self, *steps: tuple[Any, ...], axis: str = "x") -> list[tuple[str, Any]]:
        start = len(self.log)
        cmd = {"steps": list(steps), "log": self.log, "axis": axis}
        self.m0.invoke("T", cmd)
        assert self.run(lambda: len(self.log) >= start + max(1, len(steps))), self.log
        self.states = cmd.get("states", [])
        return self.log[start:]


@pytest.fixture
def pair(tmp_path: Path) -> Iterator[Pair]:
    channel = unique_channel("axrem")
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    eds = tmp_path / "drive.eds"
    eds.write_text(drive_eds(), encoding="utf-8")
    path = tmp_path / "axis.toml"
    path.write_text(axis_map(channel, eds), encoding="utf-8")
    net = LoopNet()
    systems = []
    for m in (0, 1):
        s = System([path], clock=VirtualClock(), machines=(0, 1), base_dir=tmp_path,
                   map_path=tmp_path / f"sysfile{m}.map", local_machines={m},
                   transport=LoopTransport(net), prefix="chcos/t")
        assert s.comm is not None
        s.comm.start()
        systems.append(s)
    for s in systems:   # the same install log on both satellites
        s.execute(f"install -m0o1 --code={M}:remote_steps T x")
        s.execute(f"install -m0o1 --code={M}:remote_steps L lamp")
    p = Pair(systems[0], systems[1], net, drive)
    try:
        assert p.run(lambda: all(s.comm is not None and s.comm.is_up(1 - s.comm.machine)
                                 for s in systems))
        assert p.run(lambda: p.m1.devtab.get("x.state").value == "SWITCH_ON_DISABLED")
        yield p
    finally:
        for s in systems:
            s.shutdown()
        drive.close()


def axis_requests(net: LoopNet) -> list[dict[str, Any]]:
    """The axis requests waiting on the link now."""
    return [m.value for _k, payload, kind in net.held if kind is MessageKind.COMMAND
            for m in decode_batch(payload) if isinstance(m.value, dict)
            and m.value.get("op") == "axis"]


def test_a_task_commands_an_axis_on_another_satellite(pair: Pair) -> None:
    d = pair.drive
    assert pair.do(("set_mode",), ("enable",), ("at_velocity", 2.0)) == [
        ("set_mode", "ok"), ("enable", "ok"), ("at_velocity", "ok")]
    # what the drive received and where it is: the commands ran on machine 1's driver
    assert d.received[:4] == [0x00, 0x06, 0x07, 0x0F] and d.state == ENABLED
    assert d.read(0x6061) == 3 and d.velocity == 2000
    assert pair.states[1] is State.OPERATION_ENABLED       # what the result confirmed
    # a fault: the remote command fails naming the state, statusword and 0x603F
    d.inject_fault(0x2310)
    assert pair.run(lambda: pair.m1.devtab.get("x").status.value == "failed")
    n = len(d.received)
    (op, err), = pair.do(("enable",))
    assert op == "enable" and isinstance(err, AxisCommandFailed)
    assert "FAULT" in str(err) and "0x603F 0x2310" in str(err) and "statusword 0x" in str(err)
    assert d.received[n:] == []
    assert pair.do(("fault_reset",)) == [("fault_reset", "ok")]
    assert d.received[n:] == [0x00, 0x80] and d.state == SOD and d.emcys[-1] == 0
    assert pair.states == [State.SWITCH_ON_DISABLED]
    assert pair.do(("enable",)) == [("enable", "ok")] and d.state == ENABLED
    assert pair.do(("disable",)) == [("disable", "ok")] and d.state == SOD


def test_an_unknown_or_plain_device_is_a_clear_error(pair: Pair) -> None:
    (op, err), = pair.do(("enable",), axis="nope")
    assert op == "axis" and "no device 'nope'" in str(err)
    pair.log.clear()
    pair.m0.execute(f"install -m0o1 --code={M}:remote_steps U lamp")
    pair.m1.execute(f"install -m0o1 --code={M}:remote_steps U lamp")
    got: list[tuple[str, Any]] = []
    pair.m0.invoke("U", {"steps": [("enable",)], "log": got, "axis": "lamp"})
    assert pair.run(lambda: bool(got))
    (op, err), = got
    assert op == "axis" and "lamp is not a CiA 402 axis" in str(err)
    assert pair.drive.received == []


def test_a_satellite_that_is_down_refuses_the_command_at_once(pair: Pair) -> None:
    pair.net.kill(1)
    assert pair.run(lambda: pair.m0.comm is not None and not pair.m0.comm.is_up(1))
    (op, err), = pair.do(("enable",))
    assert op == "enable" and isinstance(err, MessageError)
    assert "satellite 1, which is not up" in str(err) and "enable not sent" in str(err)
    assert axis_requests(pair.net) == [] and pair.drive.received == []


def test_a_satellite_that_dies_before_answering_fails_the_command(pair: Pair) -> None:
    start = len(pair.log)
    pair.m0.invoke("T", {"steps": [("enable",)], "log": pair.log})
    pair.m0.run_for(0.0)
    (request,) = axis_requests(pair.net)           # on its way: nobody answers it
    assert request["call"] == "enable" and request["device"] == "x"
    pair.net.held.clear()
    pair.net.kill(1)
    assert pair.run(lambda: len(pair.log) > start)
    (op, err), = pair.log[start:]
    assert op == "enable" and isinstance(err, MessageError)
    assert "satellite 1 died before confirming enable" in str(err)
    assert pair.drive.received == [] and pair.drive.state == SOD


def test_the_hosting_satellite_refuses_a_task_without_a_port_to_the_axis(pair: Pair) -> None:
    """A request naming a task that has no output link to the axis (forged, or tables out of
    step) is refused there, and nothing reaches the drive."""
    from drivers.canopen_axis import AxisCall
    from drivers.codecs.cia402 import Op
    assert pair.m0.comm is not None
    answers: list[Any] = []
    pair.m0.comm.axis_call("x", 1, "L", AxisCall(Op.ENABLE), answers.append)
    assert pair.run(lambda: bool(answers))
    (err,) = answers
    assert isinstance(err, MessageError) and "task L has no output port to axis x" in str(err)
    assert pair.drive.received == [] and pair.drive.state != FAULT


def test_the_abnormal_end_of_the_owner_stops_the_remote_axis(pair: Pair) -> None:
    d = pair.drive
    pair.do(("set_mode",), ("enable",), ("at_velocity", 5.0))
    assert d.state == ENABLED and d.velocity == 5000
    n = len(d.log)
    pair.m0.invoke("T", {"steps": [("raise",)], "log": pair.log})
    # the safe value travels to machine 1 as an actuator command: the safe stop sequence
    assert pair.run(lambda: d.state == SOD)
    log = d.log[n:]
    assert log[0][0] == 0x02 and log[0][1] == ENABLED and log[0][2] > 0, log
    assert all(speed == 0 for cw, _state, speed in log if cw == 0x00) and log[-1][0] == 0x00
    assert pair.m0.tsktab.get("T").abnormal == 1

