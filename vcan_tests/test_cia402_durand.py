"""test_cia402_durand - the Axis engine (drivers/codecs/cia402.py) commanding an independent CiA 402
drive written on durand (vcan_tests/peers/durand_cia402.py) over a python-can virtual bus: RPDO
frames composed from an image, TPDOs, SDO reads, EMCY. Every test asserts what the DRIVE saw: the
controlwords it received, the states it went through, its objects."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from dataclasses import replace

import pytest

from drivers.codecs.cia402 import AxisConfig, Mode, Obj, Op, SafeStop, State, Timeouts
from vcan_tests.peers.durand_cia402 import (
    ENABLED,
    FAULT,
    FOLLOWING_ERROR,
    OVER_TEMPERATURE,
    QUICK_STOP,
    RTSO,
    SOD,
    SWITCHED_ON,
    DurandCia402Drive,
)
from vcan_tests.support_cia402 import Cia402Host

NODE = 5


def squeeze(seq: list[int]) -> list[int]:
    """``seq`` without consecutive repeats (the image resends an unchanged controlword)."""
    out: list[int] = []
    for x in seq:
        if not out or out[-1] != x:
            out.append(x)
    return out


def make(option: int = 2, **config: object) -> tuple[DurandCia402Drive, Cia402Host]:
    channel = f"cia402-{uuid.uuid4().hex}"
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=option)
    cfg = AxisConfig("x", quick_stop_option=option, position_window=1, velocity_window=1,
                     **config)  # type: ignore[arg-type]
    host = Cia402Host(channel, NODE, drive, cfg)
    host.start_node()
    return drive, host


@pytest.fixture
def rig() -> Iterator[tuple[DurandCia402Drive, Cia402Host]]:
    drive, host = make()
    yield drive, host
    host.close()
    drive.close()


def enabled_in(host: Cia402Host, mode: Mode) -> None:
    assert host.run(host.axis.enable).ok
    result = host.run(lambda now: host.axis.set_mode(mode, now))
    assert result.ok, result


def test_enable_and_disable_walk_the_drive_through_its_states(rig: tuple) -> None:
    drive, host = rig
    result = host.run(host.axis.enable)
    assert result.ok and result.state is State.OPERATION_ENABLED
    assert drive.received == [0x06, 0x07, 0x0F]
    assert drive.history[-4:] == [SOD, RTSO, SWITCHED_ON, ENABLED]
    result = host.run(host.axis.disable)
    assert result.ok and drive.state == SOD
    assert drive.received[-1] == 0x00


def test_a_mode_write_carries_the_current_controlword(rig: tuple) -> None:
    """RPDO2 maps the controlword with 0x6060: a stale 0 in it would disable the voltage."""
    drive, host = rig
    enabled_in(host, Mode.PV)
    assert drive.state == ENABLED and drive.read(0x6061) == 3
    assert 0x00 not in drive.received


def test_move_to_in_profile_position_reaches_the_target_on_the_drive(rig: tuple) -> None:
    drive, host = rig
    enabled_in(host, Mode.PP)
    result = host.run(lambda now: host.axis.move_to(300, now))
    assert result.ok, result
    assert drive.position == 300 and drive.read(0x607A) == 300
    # the new set-point handshake: bit 4 raised once, dropped after the acknowledge
    assert squeeze(drive.received)[-2:] == [0x1F, 0x0F]


def test_at_velocity_in_profile_velocity(rig: tuple) -> None:
    drive, host = rig
    enabled_in(host, Mode.PV)
    result = host.run(lambda now: host.axis.at_velocity(2000, now))
    assert result.ok and drive.velocity == 2000 and drive.read(0x60FF) == 2000


def test_a_mode_the_drive_refuses_fails_naming_0x6061(rig: tuple) -> None:
    drive, host = rig
    enabled_in(host, Mode.PP)
    result = host.run(lambda now: host.axis.set_mode(Mode.HM, now))
    assert not result.ok and result.mode_display == 1
    assert "0x6061 shows 1 (PP), not 6 (HM)" in str(result)
    assert drive.read(0x6061) == 1 and drive.read(0x6060) == 6   # received, refused
    # the axis is still usable in the mode it has
    assert host.run(lambda now: host.axis.move_to(10, now)).ok


@pytest.mark.parametrize("option,ends_in", [(2, SOD), (6, QUICK_STOP)])
def test_quick_stop_follows_the_option_code(option: int, ends_in: str) -> None:
    drive, host = make(option, standstill=0)
    try:
        enabled_in(host, Mode.PV)
        assert host.run(lambda now: host.axis.at_velocity(5000, now)).ok
        result = host.run(host.axis.quick_stop)
        assert result.ok, result
        assert drive.state == ends_in and drive.velocity == 0
        assert QUICK_STOP in drive.history
        assert squeeze(drive.received)[-1] == 0x02            # nothing after the quick stop
    finally:
        host.close()
        drive.close()


@pytest.mark.parametrize("option", [2, 6])
def test_safe_stop_disables_voltage_only_once_stopped(option: int) -> None:
    drive, host = make(option, standstill=0)
    try:
        enabled_in(host, Mode.PV)
        assert host.run(lambda now: host.axis.at_velocity(5000, now)).ok
        result = host.run(host.axis.safe_stop)
        assert result.ok and result.state is State.SWITCH_ON_DISABLED
        assert drive.state == SOD                            # the state the sequence promises
        stop_at = max(i for i, (cw, *_rest) in enumerate(drive.log) if cw == 0x02)
        assert drive.log[stop_at][1] == ENABLED and drive.log[stop_at][2] == 5000
        # disable voltage, if the drive needed it, reached it only at standstill
        assert all(speed == 0 for cw, _s, speed in drive.log[stop_at + 1:] if cw == 0x00)
        if option == 6:          # the drive stays in quick stop active: the axis removes power
            assert drive.received[-1] == 0x00
        assert drive.history[-2:] == [QUICK_STOP, SOD]
    finally:
        host.close()
        drive.close()


def test_safe_stop_halt_variant_keeps_the_drive_enabled_until_stopped() -> None:
    drive, host = make(2, standstill=0, safe_stop=SafeStop.HALT_THEN_DISABLE)
    try:
        enabled_in(host, Mode.PV)
        assert host.run(lambda now: host.axis.at_velocity(3000, now)).ok
        assert host.run(host.axis.safe_stop).ok
        assert squeeze(drive.received)[-2:] == [0x10F, 0x00]
        assert drive.state == SOD and QUICK_STOP not in drive.history
        assert [speed for cw, _s, speed in drive.log if cw == 0x00][-1] == 0
    finally:
        host.close()
        drive.close()


def test_a_fault_does_not_deadlock_and_nothing_re_enables_by_itself(rig: tuple) -> None:
    """The scenario that deadlocked: EMCY 0x2310 during operation -> FAULT; the axis stays
    readable, the fault reset (a rising edge of bit 7) is accepted, the drive goes to switch
    on disabled and is enabled again only when commanded."""
    drive, host = rig
    enabled_in(host, Mode.PP)
    host.perform(host.axis.move_to(50_000, host.now))
    host.idle(0.1)
    assert drive.velocity > 0
    drive.inject_fault(0x2310)
    host.idle(0.1)
    (failed,) = host.op_results(Op.MOVE_TO)
    assert not failed.ok and failed.error_code == 0x2310 and failed.state is State.FAULT
    assert "0x2310" in str(failed) and "FAULT" in str(failed)
    assert [f.error_code for f in host.faults if f] == [0x2310]
    assert host.emcys == [0x2310] and drive.state == FAULT
    before = len(drive.received)
    host.idle(1.0)                                    # a second of cycles: nothing is sent
    assert len(drive.received) == before and drive.state == FAULT
    assert host.axis.state is State.FAULT and host.axis.fault is not None

    result = host.run(host.axis.fault_reset)
    assert result.ok and result.state is State.SWITCH_ON_DISABLED
    assert drive.received[before:] == [0x00, 0x80]   # the edge, as two frames
    assert drive.state == SOD and drive.read(0x603F) == 0
    assert host.emcys[-1] == 0 and host.faults[-1] is None
    before = len(drive.received)
    host.idle(1.0)
    assert len(drive.received) == before and drive.state == SOD   # no re-enable by itself
    assert host.run(host.axis.enable).ok and drive.state == ENABLED


def test_a_persistent_fault_refuses_the_reset_and_the_failure_names_it(rig: tuple) -> None:
    drive, host = rig
    host.axis.config = AxisConfig("x", position_window=1,
                                  timeouts=Timeouts(fault_reset=0.3))
    enabled_in(host, Mode.PP)
    drive.inject_fault(OVER_TEMPERATURE, persistent=True)
    host.idle(0.05)
    result = host.run(host.axis.fault_reset)
    assert not result.ok and result.error_code == OVER_TEMPERATURE and drive.state == FAULT
    edges = [i for i in range(1, len(drive.received))
             if drive.received[i] & 0x80 and not drive.received[i - 1] & 0x80]
    assert len(edges) >= 1                             # it was asked, and refused
    drive.clear_cause()
    assert host.run(host.axis.fault_reset).ok and drive.state == SOD


def test_a_following_error_in_csp_fails_the_move_with_0x8611(rig: tuple) -> None:
    drive, host = rig
    enabled_in(host, Mode.CSP)
    result = host.run(lambda now: host.axis.move_to(1_000_000, now))
    assert not result.ok and result.error_code == FOLLOWING_ERROR
    assert result.state in (State.FAULT_REACTION_ACTIVE, State.FAULT)
    host.idle(0.02)
    assert drive.state == FAULT and drive.read(0x603F) == FOLLOWING_ERROR
    assert FOLLOWING_ERROR in host.emcys


def test_commands_refused_in_the_wrong_state_name_it(rig: tuple) -> None:
    drive, host = rig
    result = host.run(lambda now: host.axis.move_to(5, now))
    assert not result.ok and "needs OPERATION_ENABLED" in result.reason
    assert "SWITCH_ON_DISABLED" in result.reason and drive.received == []


def test_an_e_stop_during_a_move_stops_then_removes_the_power(rig: tuple) -> None:
    """The safe action superseding a running command (e-stop): the move fails as superseded,
    the drive gets the quick stop while moving and disable voltage only at standstill."""
    drive, host = rig
    enabled_in(host, Mode.PP)
    host.perform(host.axis.move_to(50_000, host.now))
    host.idle(0.2)
    assert drive.velocity > 0
    result = host.run(host.axis.safe_stop)
    assert result.ok and drive.state == SOD
    (move,) = host.op_results(Op.MOVE_TO)
    assert not move.ok and move.reason == "superseded by safe stop"
    assert 0 < drive.position < 50_000
    quick = [speed for cw, _s, speed in drive.log if cw == 0x02]
    assert quick and quick[0] > 0
    assert all(speed == 0 for cw, _s, speed in drive.log if cw == 0x00)


def test_a_safe_stop_of_a_faulted_drive_is_reached_naming_the_fault_and_sends_nothing(
        rig: tuple) -> None:
    drive, host = rig
    enabled_in(host, Mode.PP)
    drive.inject_fault(OVER_TEMPERATURE, persistent=True)
    host.idle(0.05)
    before = len(drive.received)
    result = host.run(host.axis.safe_stop)
    # FAULT: the drive function is disabled (no torque): the safe outcome, said as it is
    assert result.ok and result.state is State.FAULT and result.error_code == 0x4310
    assert "0x603F 0x4310" in result.reason and "no torque" in result.reason
    assert len(drive.received) == before and drive.state == FAULT
    host.idle(0.5)                                   # nothing re-enables it
    assert len(drive.received) == before and drive.state == FAULT


def test_a_safe_stop_during_the_fault_reaction_waits_for_fault(rig: tuple) -> None:
    drive, host = rig
    enabled_in(host, Mode.PP)
    drive.inject_fault(0x2310)                       # FAULT REACTION ACTIVE until it steps
    host.settle()
    host.perform(host.axis.update(host.reading(), host.now))
    assert host.axis.state is State.FAULT_REACTION_ACTIVE
    before = len(drive.received)
    host.perform(host.axis.safe_stop(host.now))
    host.now += 0.2                                  # time passes, the drive still reacting
    host.perform(host.axis.poll(host.now))
    assert host.op_results(Op.SAFE_STOP) == []
    result = host.run(lambda now: host.axis.poll(now))   # the drive steps: FAULT
    assert result.op is Op.SAFE_STOP and result.ok and result.state is State.FAULT
    assert result.error_code == 0x2310
    assert len(drive.received) == before and drive.state == FAULT


def test_the_error_code_is_read_by_sdo_when_no_pdo_brings_it() -> None:
    channel = f"cia402-{uuid.uuid4().hex}"
    drive = DurandCia402Drive(channel, NODE)
    host = Cia402Host(channel, NODE, drive, AxisConfig("x", position_window=1),
                      error_code_by_sdo=True)
    try:
        host.start_node()
        enabled_in(host, Mode.PP)
        host.perform(host.axis.move_to(50_000, host.now))
        host.idle(0.05)
        drive.inject_fault(FOLLOWING_ERROR)
        host.idle(0.05)
        (move,) = host.op_results(Op.MOVE_TO)
        assert not move.ok and move.error_code == FOLLOWING_ERROR
        assert Obj.ERROR_CODE in host.sdo_reads
    finally:
        host.close()
        drive.close()


def test_a_stale_controlword_in_a_shared_rpdo_disables_the_drive(rig: tuple) -> None:
    """Why RPDOs are composed from one image: the drive applies every object of a frame, so a
    mode write that carries a stale controlword 0 (issue 36) is a disable voltage."""
    drive, host = rig
    assert host.run(host.axis.enable).ok and drive.state == ENABLED
    before = drive.frames()
    host.network.send_message(0x300 + NODE, bytes([0x00, 0x00, 0x03]))   # RPDO2: cw 0, mode 3
    assert drive.wait(lambda: drive.frames() > before)
    assert drive.state == SOD and drive.received[-1] == 0x00 and drive.read(0x6061) == 3


@pytest.mark.parametrize("option", [2, 6])
def test_a_safe_stop_right_after_a_move_starts_brakes_before_it_removes_the_power(
        option: int) -> None:
    """E-stop while the drive already runs but before any TPDO showing it reached the axis (the
    last velocity it holds, 0, predates the move): the drive gets the quick stop, and disable
    voltage only once it reported standstill. Before issue 37's fix the engine sent disable
    voltage right behind the quick stop, on that old 0: the drive coasted at full speed."""
    drive, host = make(option, standstill=0)
    try:
        enabled_in(host, Mode.PV)
        host.perform(host.axis.at_velocity(5000, host.now))
        for _ in range(5):       # the drive runs; its TPDOs have not been fed to the axis yet
            drive.step(host.dt)
        assert drive.velocity == 5000 and host.axis.velocity == 0
        first = len(drive.log)
        host.perform(host.axis.safe_stop(host.now))
        assert [(cw, state, speed) for cw, state, speed in drive.log[first:]] == \
            [(0x02, ENABLED, 5000)]
        while not host.op_results(Op.SAFE_STOP):
            host.cycle()
        (result,) = host.op_results(Op.SAFE_STOP)
        assert result.ok and result.state is State.SWITCH_ON_DISABLED, result
        assert drive.state == SOD and drive.velocity == 0
        after = drive.log[first:]
        assert squeeze([cw for cw, *_rest in after])[0] == 0x02
        # disable voltage, if the drive needed it, reached it at standstill only
        assert all(speed == 0 for cw, _s, speed in after if cw == 0x00)
        if option == 6:
            assert squeeze([cw for cw, *_rest in after]) == [0x02, 0x00]
            assert after[-1][1] == QUICK_STOP
        assert drive.history[-2:] == [QUICK_STOP, SOD]
    finally:
        host.close()
        drive.close()


def test_a_statusword_older_than_the_one_held_does_not_fail_a_running_move(rig: tuple) -> None:
    """Issue 37's two-process failure, on the durand drive: a TPDO showing SWITCHED_ON, received
    during the enable but fed to the axis only after the move started (it waited in a queue),
    is older than the statusword that confirmed the enable: ignored, the move goes on."""
    drive, host = rig
    host.perform(host.axis.enable(host.now))
    stale = None
    while not host.op_results(Op.ENABLE):
        host.cycle()
        if host.axis.state is State.SWITCHED_ON and stale is None:
            # this TPDO's values, as the reader thread marks them on arrival
            stale = replace(host.reading(), received=host.axis.order.pdo_received(
                (Obj.STATUSWORD, Obj.MODES_DISPLAY, Obj.POSITION_ACTUAL,
                 Obj.VELOCITY_ACTUAL)))
    assert stale is not None and host.op_results(Op.ENABLE)[0].ok
    assert host.run(lambda now: host.axis.set_mode(Mode.PP, now)).ok
    host.perform(host.axis.move_to(300, host.now))
    host.perform(host.axis.update(stale, host.now))           # the queued, older TPDO
    assert host.axis.busy is Op.MOVE_TO and host.axis.state is State.OPERATION_ENABLED
    assert host.axis.stale_readings == 1
    while not host.op_results(Op.MOVE_TO):
        host.cycle()
    (move,) = host.op_results(Op.MOVE_TO)
    assert move.ok, move
    assert drive.state == ENABLED and drive.position == 300
    assert squeeze(drive.received) == [0x06, 0x07, 0x0F, 0x1F, 0x0F]
