"""The operator's commands of a CiA 402 axis from the host shell (issue 37): ``axis x
fault-reset``, ``enable``, ``disable``, ``quick-stop``, ``set-mode``, ``safe-stop`` and ``axis x``
(its state, statusword, 0x603F), as ``chcos shell`` gives them to an in-process System, against the
independent durand drive (vcan_tests/peers/durand_cia402.py). Each assertion is about what the
DRIVE received and the state it is in, or the answer and error the operator gets."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.errors import ChcosError, CommandSyntaxError
from chcos.kernel.clock import RealClock
from chcos.system import cmdline
from chcos.system.embedded import System
from drivers.codecs.cia402 import AxisCommandFailed
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_cia402 import ENABLED, FAULT, QUICK_STOP, SOD, DurandCia402Drive
from vcan_tests.support_cia402 import drive_eds
from vcan_tests.support_faults import wait_until
from vcan_tests.test_cia402_axis_stack import NODE, STEP, Rig, axis_map, make_system


class Motor:
    """The drive's own time going on, on a thread of its own (its deceleration, its fault
    reaction), while the operator's command waits."""

    def __init__(self, drive: DurandCia402Drive) -> None:
        self.drive = drive
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stop.wait(0.005):
            self.drive.step(STEP)

    def close(self) -> None:
        self.stop.set()
        self.thread.join(5)


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[Rig]:
    channel = unique_channel("axsh")
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    s = make_system(tmp_path, channel)
    r = Rig(s, drive)
    try:
        assert r.run(lambda: r.value("x.state") == "SWITCH_ON_DISABLED")
        yield r
    finally:
        s.shutdown()
        drive.close()


def test_the_operator_resets_a_fault_and_the_drive_leaves_it(rig: Rig) -> None:
    d, s = rig.drive, rig.s
    motor = Motor(d)
    try:
        assert "set mode done" in s.execute("axis x set-mode PP")
        answer = s.execute("axis x enable")
        assert answer.startswith("axis x: enable done") and "OPERATION_ENABLED" in answer
        assert d.received == [0x00, 0x06, 0x07, 0x0F] and d.state == ENABLED
        d.inject_fault(0x2310)
        assert rig.hold(lambda: rig.status("x") == "failed")     # the drive-fault
        assert wait_until(lambda: "state FAULT," in s.execute("axis x")), s.execute("axis x")
        status = s.execute("axis x")
        assert "0x603F 0x2310" in status and "statusword 0x" in status and "1 (PP)" in status
        n = len(d.received)
        with pytest.raises(AxisCommandFailed, match="FAULT") as err:
            s.execute("axis x enable")                   # never out of a fault
        assert "0x603F 0x2310" in str(err.value) and d.received[n:] == []
        answer = s.execute("axis x fault-reset")
        assert answer.startswith("axis x: fault reset done"), answer
        assert d.received[n:] == [0x00, 0x80]           # the rising edge, two frames
        assert d.state == SOD and d.emcys[-1] == 0      # the drive's error-reset EMCY
        assert rig.hold(lambda: rig.status("x") == "OK")
        assert "state SWITCH_ON_DISABLED" in s.execute("axis x")
        assert "0x603F none" in s.execute("axis x")
        n = len(d.received)
        s.execute("axis x enable")
        assert d.state == ENABLED and d.received[n:] == [0x06, 0x07, 0x0F]
        n = len(d.history)
        assert "quick stop done" in s.execute("axis x quick-stop")
        assert QUICK_STOP in d.history[n:] and d.state == SOD
        s.execute("axis x enable")
        n = len(d.received)
        assert "disable done" in s.execute("axis x disable")
        assert d.received[n:] == [0x00] and d.state == SOD
    finally:
        motor.close()


def test_a_fault_the_reset_cannot_clear_is_reported_to_the_operator(rig: Rig) -> None:
    d, s = rig.drive, rig.s
    motor = Motor(d)
    try:
        d.inject_fault(0x4310, persistent=True)          # over-temperature: stays
        assert wait_until(lambda: "state FAULT," in s.execute("axis x"))
        with pytest.raises(AxisCommandFailed, match="fault reset failed") as err:
            s.execute("axis x fault-reset")
        assert "FAULT" in str(err.value) and "0x4310" in str(err.value)
        assert d.state == FAULT and 0x80 in d.received
        answer = s.execute("axis x safe-stop")          # power stage off: reached as it is
        assert "safe stop done" in answer and "no torque" in answer and d.state == FAULT
        d.clear_cause()
        assert "fault reset done" in s.execute("axis x fault-reset") and d.state == SOD
    finally:
        motor.close()


def test_bad_axis_commands_are_refused_naming_the_word_and_send_nothing(rig: Rig) -> None:
    d, s = rig.drive, rig.s
    with pytest.raises(CommandSyntaxError, match=r"axis x: unknown command 'jump'"):
        s.execute("axis x jump")
    with pytest.raises(CommandSyntaxError, match=r"axis x enable: takes no argument"):
        s.execute("axis x enable now")
    with pytest.raises(CommandSyntaxError, match=r"'warp' is no mode"):
        s.execute("axis x set-mode warp")
    with pytest.raises(CommandSyntaxError, match="no axis given"):
        s.execute("axis")
    with pytest.raises(ChcosError, match="no axis 'nope'"):
        s.execute("axis nope enable")
    with pytest.raises(ChcosError, match=r"x\.state is not a CiA 402 axis"):
        s.execute("axis x.state enable")
    assert d.received == []
    assert cmdline.parse("axis x set-mode 3") == cmdline.AxisCmd("x", "set-mode", "3")
    assert cmdline.parse("axis x") == cmdline.AxisCmd("x", "status")


def test_on_a_running_system_the_command_waits_for_the_drive(tmp_path: Path) -> None:
    """As ``chcos shell`` without --virtual: the kernel on its own thread, real time."""
    channel = unique_channel("axsh")
    d = DurandCia402Drive(channel, NODE, quick_stop_option=2)
    eds = tmp_path / "drive.eds"
    eds.write_text(drive_eds(), encoding="utf-8")
    path = tmp_path / "axis.toml"
    path.write_text(axis_map(channel, eds), encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0])
    motor = Motor(d)
    try:
        s.start()
        assert wait_until(lambda: "SWITCH_ON_DISABLED" in s.execute("axis x"))
        s.execute("axis x set-mode 3")
        assert "enable done" in s.execute("axis x enable") and d.state == ENABLED
        assert d.read(0x6061) == 3
        d.inject_fault(0x2310)
        assert wait_until(lambda: "state FAULT," in s.execute("axis x"))
        n = len(d.received)
        assert "fault reset done" in s.execute("axis x fault-reset")
        assert d.received[n:] == [0x00, 0x80] and d.state == SOD
    finally:
        motor.close()
        s.shutdown()
        d.close()
