"""A CiA 402 axis through the whole stack (issue 37): a device map with ``profile = "cia402"``,
a System on a virtual clock, a task commanding ``ctx.axis("x")``, the CANopen driver hosting the
engine, against the independent durand drive (vcan_tests/peers/durand_cia402.py) and the
simulated one. Every assertion is about what the DRIVE received and the state it is in, or what
Devtab reports (the axis's health, its sensors, the safe outcomes at shutdown)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.cia402_drive import Cia402Drive
from chcos.errors import ChcosError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from drivers.codecs.cia402 import AxisCommandFailed
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_cia402 import (
    ENABLED,
    FAULT,
    QUICK_STOP,
    SOD,
    DurandCia402Drive,
)
from vcan_tests.support_cia402 import drive_eds

M = "vcan_tests.test_cia402_axis_stack"
NODE = 5
STEP = 0.02
WALL = 20.0     # wall-clock seconds a condition may take on a loaded machine


# ---- the task -------------------------------------------------------------------------------
async def axis_task(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Runs ``cmd["steps"]`` on axis ``x``: ``(op, *args)`` for an axis command, ``("estop",)``
    or ``("raise",)``; each outcome goes to ``cmd["log"]`` as (op, "ok" or the error)."""
    x = ctx.axis("x")
    log: list[tuple[str, Any]] = cmd["log"]
    for op, *args in cmd["steps"]:
        if op == "estop":
            ctx.estop("test")
            continue
        if op == "raise":
            raise RuntimeError("the task's own error")
        try:
            await getattr(x, op)(*args)
        except ChcosError as exc:
            log.append((op, exc))
            continue
        log.append((op, "ok"))


async def mover(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Moves axis ``x`` to ``cmd["to"]``; a failure ends the task abnormally."""
    await ctx.axis("x").move_to(cmd["to"])


# ---- the rig --------------------------------------------------------------------------------
def axis_map(channel: str, eds: Path, node_extra: str = "", **axis: str) -> str:
    keys = {"mode": '"PP"', "quick_stop_option": "2", "counts_per_unit": "1000.0",
            "timeouts": "{ enable = 5.0, disable = 5.0, quick_stop = 10.0, fault_reset = 5.0, "
                        "set_mode = 2.0, move = 60.0, velocity = 10.0, safe_stop = 10.0 }",
            **axis}
    extra = "\n".join(f"{k} = {v}" for k, v in keys.items())
    return f"""
[[bus]]
name = "drives"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
nodes = [{{ id = {NODE}, eds = "{eds}"{node_extra} }}]

[[device]]
name = "x"
profile = "cia402"
bus = "drives"
units = "mm"
address = {{ node = {NODE} }}
{extra}
"""


@dataclass
class Rig:
    """The system, the drive, and the task's log."""

    s: System
    drive: Any
    log: list[tuple[str, Any]] = field(default_factory=list)

    def run(self, pred: Callable[[], bool], wall: float = WALL) -> bool:
        """Step the drive and the system's virtual clock together until ``pred()``; before
        virtual time goes on, chcos has seen what the drive last published (the drive answers
        on its own thread, in real time: a loaded machine must not make a timeout of virtual
        time expire while its answer is on the way)."""
        deadline = time.monotonic() + wall
        while not pred():
            if time.monotonic() > deadline:
                return False
            self.drive.step(STEP)
            self.caught_up()
            self.s.run_for(STEP)
        return True

    def hold(self, pred: Callable[[], bool], wall: float = WALL) -> bool:
        """Run the system without advancing its clock until ``pred()`` (what is judged on
        real time, a heartbeat's loss, happens meanwhile)."""
        deadline = time.monotonic() + wall
        while not pred():
            if time.monotonic() > deadline:
                return False
            self.s.run_for(0.0)
        return True

    def caught_up(self, wall: float = 2.0) -> None:
        """Run the system without advancing its clock until its ``x.statusword`` is the
        drive's (or ``wall`` seconds passed: a drive that is not heard, e.g. rebooting)."""
        deadline = time.monotonic() + wall
        while (self.value("x.statusword") != self.drive.published()[0]
               and time.monotonic() < deadline):
            self.s.run_for(0.0)

    def do(self, *steps: tuple[Any, ...]) -> list[tuple[str, Any]]:
        """Invoke the task with ``steps`` and run until it reported each of them."""
        start = len(self.log)
        want = start + sum(1 for s in steps if s[0] not in ("estop", "raise"))
        self.s.invoke("T", {"steps": list(steps), "log": self.log})
        assert self.run(lambda: len(self.log) >= want), self.log
        return self.log[start:]

    def value(self, name: str) -> Any:
        return self.s.devtab.get(name).value

    def status(self, name: str) -> str:
        return self.s.devtab.get(name).status.value


def make_system(tmp_path: Path, channel: str, node_extra: str = "", **axis: str) -> System:
    eds = tmp_path / "drive.eds"
    eds.write_text(drive_eds(), encoding="utf-8")
    path = tmp_path / "axis.toml"
    path.write_text(axis_map(channel, eds, node_extra, **axis), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    s.execute(f"install -m0o1 --code={M}:axis_task T x")
    return s


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    channel = unique_channel("axis")
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    s = make_system(tmp_path, channel)
    r = Rig(s, drive)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        yield r
    finally:
        s.shutdown()
        drive.close()


def after(seq: list[int], start: int) -> list[int]:
    return seq[start:]


# ---- commands that complete -----------------------------------------------------------------
def test_mode_enable_move_disable_as_the_drive_saw_them(rig: Rig) -> None:
    d = rig.drive
    assert rig.do(("set_mode",)) == [("set_mode", "ok")]
    # RPDO2 carries 0x6060 with the controlword of the image: the node's own 0, not stale
    assert d.read(0x6061) == 1 and d.received == [0x00] and d.state == SOD
    assert rig.do(("enable",)) == [("enable", "ok")]
    assert d.received[1:] == [0x06, 0x07, 0x0F] and d.state == ENABLED  # 2, 3, 4
    assert rig.value("x.state") == "OPERATION_ENABLED" and rig.value("x.mode") == 1
    n = len(d.received)
    assert rig.do(("move_to", 0.5)) == [("move_to", "ok")]
    assert 0x1F in after(d.received, n)                   # the new set-point's edge
    assert d.read(0x607A) == 500 and round(d.position) == 500
    assert rig.run(lambda: rig.value("x.position") == pytest.approx(0.5))
    n = len(d.received)
    assert rig.do(("disable",)) == [("disable", "ok")]
    assert after(d.received, n) == [0x00] and d.state == SOD
    assert rig.status("x") == "OK"


def test_quick_stop_then_enable_again(rig: Rig) -> None:
    d = rig.drive
    rig.do(("set_mode", 3), ("enable",))
    assert rig.do(("at_velocity", 2.0)) == [("at_velocity", "ok")]
    assert d.velocity == 2000
    n = len(d.received)
    assert rig.do(("quick_stop",)) == [("quick_stop", "ok")]
    assert after(d.received, n)[:1] == [0x02]
    assert QUICK_STOP in d.history and d.state == SOD and d.velocity == 0
    assert rig.do(("enable",)) == [("enable", "ok")] and d.state == ENABLED


def test_a_mode_the_drive_refuses_names_what_0x6061_shows(rig: Rig) -> None:
    (op, err), = rig.do(("set_mode", 6))                  # the durand drive refuses homing
    assert op == "set_mode" and isinstance(err, AxisCommandFailed)
    text = str(err)
    assert "0x6061 shows 0 (NONE), not 6 (HM)" in text and "statusword 0x" in text
    assert "0x603F" in text and "SWITCH_ON_DISABLED" in text
    assert rig.drive.read(0x6061) == 0


def test_enable_from_a_fault_fails_naming_the_fault(rig: Rig,
                                                   caplog: pytest.LogCaptureFixture) -> None:
    rig.drive.inject_fault(0x2310)
    assert rig.run(lambda: rig.value("x.state") == "FAULT")
    (_op, err), = rig.do(("enable",))
    assert isinstance(err, AxisCommandFailed) and "FAULT" in str(err)
    assert "0x603F 0x2310" in str(err)
    # a drive in FAULT has its power stage off: shutdown's safe stop is reached as it is,
    # and nothing is sent to it (no reset, no enable)
    n = len(rig.drive.received)
    rig.s.devtab.shutdown_window = 1.0
    rig.s.shutdown()
    outcome = rig.s.devtab.safe_outcomes["x"]
    assert outcome.written, outcome
    assert rig.drive.received[n:] == [] and rig.drive.state == FAULT
    # the reason it is safe, in the log: the fault, no torque
    assert "axis x: safe stop done: the drive is in FAULT (0x603F 0x2310)" in caplog.text
    assert "no torque" in caplog.text


def test_a_safe_stop_of_a_faulted_drive_is_reached_and_says_why(rig: Rig) -> None:
    d = rig.drive
    rig.do(("set_mode", 3), ("enable",), ("at_velocity", 2.0))
    d.inject_fault(0x2310)
    assert rig.run(lambda: rig.value("x.state") == "FAULT" and rig.value("x.fault") == 0x2310)
    n = len(d.received)
    got = rig.do(("safe_stop",))
    assert got == [("safe_stop", "ok")]
    assert d.received[n:] == [] and d.state == FAULT and d.velocity == 0
    rig.run(lambda: False, wall=0.5)                      # time passes: nothing re-enables
    assert d.received[n:] == [] and d.state == FAULT


async def safe_stopper(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Runs axis ``x``'s safe stop and logs its result (or its failure)."""
    try:
        cmd["log"].append(await ctx.axis("x").safe_stop())
    except ChcosError as exc:
        cmd["log"].append(exc)


def test_a_safe_stop_waits_for_the_fault_reaction_to_end(rig: Rig) -> None:
    from drivers.codecs.cia402 import Result
    d, s = rig.drive, rig.s
    s.execute(f"install -m0o1 --code={M}:safe_stopper Q x")
    rig.do(("set_mode", 3), ("enable",), ("at_velocity", 2.0))
    d.inject_fault(0x2310)                    # FAULT REACTION ACTIVE until the drive steps
    assert rig.hold(lambda: rig.value("x.state") == "FAULT_REACTION_ACTIVE")
    got: list[Any] = []
    n = len(d.received)
    s.invoke("Q", {"log": got})
    s.run_for(0.5)                            # virtual time, the drive still reacting
    assert got == [] and d.state != FAULT
    assert rig.run(lambda: bool(got))         # the drive steps: its reaction ends in FAULT
    (result,) = got
    assert isinstance(result, Result) and result.ok, result
    assert "FAULT" in result.reason and "0x2310" in result.reason
    assert "no torque" in str(result)
    assert d.received[n:] == [] and d.state == FAULT


# ---- the fault that used to deadlock --------------------------------------------------------
def test_drive_fault_fails_the_axis_alone_and_the_fault_reset_goes_through(rig: Rig) -> None:
    d = rig.drive
    rig.do(("set_mode",), ("enable",))
    d.inject_fault(0x2310)                                # over-current: EMCY 0x2310
    assert rig.run(lambda: rig.status("x") == "failed")
    assert "0x2310" in rig.s.devtab.get("x").reason and d.state == FAULT
    # the statusword stays readable: the sensors are not failed and show the fault
    assert rig.run(lambda: rig.value("x.fault") == 0x2310)
    for sensor in ("x.state", "x.statusword", "x.fault", "x.position"):
        assert rig.status(sensor) == "OK", sensor
    assert rig.value("x.state") == "FAULT" and int(rig.value("x.statusword")) & 0x4F == 0x08
    n = len(d.received)
    assert rig.do(("fault_reset",)) == [("fault_reset", "ok")]
    assert after(d.received, n) == [0x00, 0x80]           # the edge, as two frames
    assert d.state == SOD and d.emcys[-1] == 0            # the drive's error-reset EMCY
    assert rig.run(lambda: rig.status("x") == "OK")
    rig.run(lambda: False, wall=0.5)                      # time passes: nothing re-enables
    assert d.state == SOD and all(cw in (0x00, 0x80) for cw in after(d.received, n))
    assert rig.do(("enable",)) == [("enable", "ok")] and d.state == ENABLED


def test_a_fault_that_stays_fails_the_reset_and_holds_the_axis(rig: Rig) -> None:
    d = rig.drive
    d.inject_fault(0x4310, persistent=True)               # over-temperature
    assert rig.run(lambda: rig.status("x") == "failed")
    (_op, err), = rig.do(("fault_reset",))
    assert isinstance(err, AxisCommandFailed) and "FAULT" in str(err)
    assert rig.status("x") == "failed" and d.state == FAULT
    d.clear_cause()
    assert rig.do(("fault_reset",)) == [("fault_reset", "ok")]
    assert rig.run(lambda: rig.status("x") == "OK") and d.state == SOD


# ---- safe stop sequences --------------------------------------------------------------------
def stopped_before_disable(d: DurandCia402Drive, n: int) -> None:
    """Quick stop while moving, disable voltage only once stopped, as the drive logged it."""
    log = d.log[n:]
    assert log[0][0] == 0x02 and log[0][1] == ENABLED and log[0][2] > 0
    assert all(speed == 0 for cw, _state, speed in log if cw == 0x00)


@pytest.mark.parametrize("safe_stop", ["quick_stop_then_disable", "halt_then_disable"])
def test_estop_runs_the_safe_stop_sequence_on_the_drive(tmp_path: Path, safe_stop: str) -> None:
    channel = unique_channel("axis")
    d = DurandCia402Drive(channel, NODE, quick_stop_option=6)  # stays in quick stop active
    s = make_system(tmp_path, channel, quick_stop_option="6", safe_stop=f'"{safe_stop}"')
    r = Rig(s, d)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        r.do(("set_mode", 3), ("enable",), ("at_velocity", 5.0))
        n = len(d.log)
        r.do(("estop",))
        assert r.run(lambda: d.state == SOD)
        if safe_stop == "halt_then_disable":     # halt (bit 8): enabled until stopped
            first = d.log[n]
            assert first[0] == 0x10F and first[1] == ENABLED and first[2] > 0
            assert QUICK_STOP not in d.history[-3:]
            assert all(speed == 0 for cw, _s, speed in d.log[n:] if cw == 0x00)
        else:
            stopped_before_disable(d, n)
            assert QUICK_STOP in d.history
        assert [cw for cw, *_ in d.log[n:]][-1] == 0x00
        assert r.run(lambda: r.s.devtab.get("x").pending is None)
        assert r.s.devtab.safe_failures == []
    finally:
        s.shutdown()
        d.close()


def test_abnormal_completion_of_the_owner_stops_the_axis(rig: Rig) -> None:
    d = rig.drive
    rig.do(("set_mode", 3), ("enable",), ("at_velocity", 5.0))
    n = len(d.log)
    rig.s.invoke("T", {"steps": [("raise",)], "log": rig.log})
    assert rig.run(lambda: d.state == SOD)
    stopped_before_disable(d, n)


def test_an_estop_during_a_move_is_one_safe_stop_with_the_abnormal_end_it_causes(
        rig: Rig) -> None:
    d, s = rig.drive, rig.s
    s.execute(f"install -m0o1 --code={M}:mover V x")
    rig.do(("set_mode",), ("enable",))
    s.invoke("V", {"to": 50.0})
    assert rig.run(lambda: d.velocity > 0 and d.received[-1] == 0x0F and not d.ack)
    n = len(d.log)
    s.devtab.estop("test")
    assert rig.run(lambda: d.state == SOD and s.devtab.get("x").pending is None)
    v = s.tsktab.get("V")
    assert v.abnormal == 1 and "superseded by safe stop" in (v.last_error or "")
    stopped_before_disable(d, n)
    sent = [cw for cw, *_ in d.log[n:]]
    assert sent.count(0x02) == 1 and sent[-1] == 0x00      # one sequence
    assert s.devtab.safe_failures == []


def test_shutdown_reports_the_safe_stop_the_drive_confirmed(tmp_path: Path) -> None:
    channel = unique_channel("axis")
    d = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    s = make_system(tmp_path, channel)
    r = Rig(s, d)
    stop = threading.Event()

    def motor() -> None:           # the drive's own time goes on while chcos shuts down
        while not stop.wait(0.005):
            d.step(STEP)

    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        r.do(("set_mode", 3), ("enable",), ("at_velocity", 5.0))
        n = len(d.log)
        stepper = threading.Thread(target=motor, daemon=True)
        stepper.start()
        s.shutdown()
        stop.set()
        stepper.join(5)
        outcome = s.devtab.safe_outcomes["x"]
        assert outcome.written, outcome
        assert d.state == SOD
        stopped_before_disable(d, n)
    finally:
        stop.set()
        s.shutdown()
        d.close()


def test_shutdown_says_so_when_the_drive_does_not_stop(tmp_path: Path) -> None:
    channel = unique_channel("axis")
    d = DurandCia402Drive(channel, NODE, quick_stop_option=6)
    s = make_system(tmp_path, channel, quick_stop_option="6")
    r = Rig(s, d)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        r.do(("set_mode", 3), ("enable",), ("at_velocity", 5.0))
        s.devtab.shutdown_window = 1.0
        s.shutdown()               # nobody steps the drive: it never decelerates
        outcome = s.devtab.safe_outcomes["x"]
        assert not outcome.written and "not confirmed" in outcome.reason
        assert d.state == QUICK_STOP and 0x00 not in [cw for cw, *_ in d.log[-1:]]
    finally:
        s.shutdown()
        d.close()


# ---- the simulated drive --------------------------------------------------------------------
def test_the_simulated_drive_as_an_axis(tmp_path: Path) -> None:
    channel = unique_channel("axissim")
    d = Cia402Drive(NODE, channel=channel, heartbeat_period=0, quick_stop_option=2,
                    refused_modes=(6,))
    d.start()
    s = make_system(tmp_path, channel)
    r = Rig(s, d)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        assert r.do(("set_mode",), ("enable",), ("move_to", 0.2)) == [
            ("set_mode", "ok"), ("enable", "ok"), ("move_to", "ok")]
        assert [cw for cw in d.received if cw][:3] == [0x06, 0x07, 0x0F]
        assert 0x1F in d.received
        assert d.published()[2] == 200
        assert r.run(lambda: d.received[-1] == 0x0F)      # the set-point handshake's end
        n = len(d.received)
        assert r.do(("disable",)) == [("disable", "ok")] and d.received[n:] == [0x00]
        assert d.published()[0] & 0x4F == 0x40
    finally:
        s.shutdown()
        d.stop()


# ---- node failure, device commands ----------------------------------------------------------
def test_a_node_reboot_fails_the_command_stops_the_axis_and_never_re_enables(
        tmp_path: Path) -> None:
    import can
    channel = unique_channel("axis")
    d = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    s = make_system(tmp_path, channel)
    r = Rig(s, d)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        r.do(("set_mode",), ("enable",))
        r.s.invoke("T", {"steps": [("move_to", 50.0)], "log": r.log})   # 50 s at 1 mm/s
        # moving, and the set-point handshake over (0x1F acknowledged, 0x0F back)
        assert r.run(lambda: d.velocity > 0 and d.received[-1] == 0x0F and not d.ack)
        n, start = len(d.log), len(r.log)
        bus.send(can.Message(arbitration_id=0x700 + NODE, data=b"\x00", is_extended_id=False))
        assert r.run(lambda: len(r.log) > start)
        (op, err), = r.log[start:]
        assert op == "move_to" and isinstance(err, AxisCommandFailed)
        assert "drive lost" in str(err) and "rebooted" in str(err)
        assert r.run(lambda: d.state == SOD and r.status("x") == "OK")
        stopped_before_disable(d, n)
        r.run(lambda: False, wall=0.5)
        assert d.state == SOD and not {0x06, 0x07, 0x0F} & {cw for cw, *_ in d.log[n:]}
    finally:
        bus.shutdown()
        s.shutdown()
        d.close()


async def stranger(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Tries to command axis ``x`` without a port to it."""
    try:
        ctx.axis("x")
    except ChcosError as exc:
        cmd["log"].append(str(exc))


def test_only_a_task_with_a_port_to_the_axis_commands_it(rig: Rig) -> None:
    rig.s.execute(f"install -m0 --code={M}:stranger S")
    got: list[str] = []
    rig.s.invoke("S", {"log": got})
    assert rig.run(lambda: bool(got))
    assert "task S has no output port to axis x" in got[0]
    assert rig.drive.received == []


def test_device_commands_complete_on_the_drive(rig: Rig) -> None:
    from drivers.canopen_axis import AxisCode
    d, dt = rig.drive, rig.s.devtab
    dt.write("x", int(AxisCode.SET_MODE))
    dt.write("x", int(AxisCode.ENABLE))
    assert rig.run(lambda: dt.get("x").pending is None and d.state == ENABLED)
    assert dt.get("x").value == int(AxisCode.ENABLE) and d.read(0x6061) == 1
    dt.write("x", int(AxisCode.DISABLE))
    dt.write("x", int(AxisCode.HOME))           # not enabled any more: refused by the drive
    assert rig.run(lambda: dt.get("x").pending is None)
    assert "needs OPERATION_ENABLED" in (dt.get("x").last_write_error or "")
    assert d.state == SOD
    with pytest.raises(ChcosError, match="outside its limits"):
        dt.write("x", 9)
    with pytest.raises(ChcosError, match="command code of the axis"):
        dt.write("x", 2.5)


def test_a_lost_heartbeat_fails_the_command_and_stops_the_axis_each_time(
        tmp_path: Path) -> None:
    import can
    channel = unique_channel("axis")
    d = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    bus = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    beating = threading.Event()
    done = threading.Event()

    def heartbeat() -> None:       # the drive's heartbeat, OPERATIONAL, while ``beating``
        while not done.wait(0.05):
            if beating.is_set():
                bus.send(can.Message(arbitration_id=0x700 + NODE, data=b"\x05",
                                     is_extended_id=False))

    beating.set()
    beater = threading.Thread(target=heartbeat, daemon=True)
    beater.start()
    s = make_system(tmp_path, channel, node_extra=", heartbeat_timeout = 0.3")
    r = Rig(s, d)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED" and r.status("x") == "OK")
        r.do(("set_mode",), ("enable",))
        for _ in range(2):          # the second loss is seen as well as the first
            r.s.invoke("T", {"steps": [("move_to", 50.0)], "log": r.log})
            assert r.run(lambda: d.velocity > 0 and d.received[-1] == 0x0F and not d.ack)
            n, start = len(d.log), len(r.log)
            beating.clear()
            # the loss is judged on real time: virtual time (and the move) wait for it
            assert r.hold(lambda: r.status("x") == "failed")
            assert r.run(lambda k=start: len(r.log) > k)
            (op, err), = r.log[start:]
            assert op == "move_to" and "drive lost" in str(err) and "heartbeat" in str(err)
            assert r.run(lambda: d.state == SOD)
            stopped_before_disable(d, n)
            beating.set()
            assert r.run(lambda: r.status("x") == "OK")
            assert d.state == SOD                      # back: nothing enabled it again
            r.do(("enable",))
    finally:
        done.set()
        beater.join(2)
        bus.shutdown()
        s.shutdown()
        d.close()
