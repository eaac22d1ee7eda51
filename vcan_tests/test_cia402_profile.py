"""test_cia402_profile - the CiA 402 profile's pure logic (drivers/codecs/cia402.py): the statusword
decoding, every state x command of the state table against the standard's diagram written out
here, the planner from every state to every target, and the Axis engine on scripted readings."""

from __future__ import annotations

import re

import pytest

from drivers.codecs.cia402 import (
    AUTOMATIC,
    CONTROLWORDS,
    Axis,
    AxisBusy,
    AxisConfig,
    AxisLimitError,
    Cia402Error,
    Command,
    Mode,
    Obj,
    Op,
    Plan,
    Reading,
    SafeStop,
    State,
    StatuswordError,
    Target,
    Timeouts,
    Unreachable,
    config_from_table,
    decode_command,
    decode_state,
    next_controlwords,
    next_state,
    plan,
)

S = State
C = Command

#: A statusword for each state, as drives send them (remote bit 9 and voltage bit 4 as usual).
STATUSWORDS = {
    S.NOT_READY_TO_SWITCH_ON: 0x0200,
    S.SWITCH_ON_DISABLED: 0x0250,
    S.READY_TO_SWITCH_ON: 0x0231,
    S.SWITCHED_ON: 0x0233,
    S.OPERATION_ENABLED: 0x0637,
    S.QUICK_STOP_ACTIVE: 0x0217,
    S.FAULT_REACTION_ACTIVE: 0x021F,
    S.FAULT: 0x0218,
}

#: The CiA 402 device control diagram, one row per state, one column per command, in the order
#: shutdown, switch on, enable operation, disable voltage, quick stop, disable operation, fault
#: reset ("." = no transition). Quick stop active -> enable is transition 16 (option codes 5..8).
_ = None
DIAGRAM: dict[State, tuple[State | None, ...]] = {
    S.NOT_READY_TO_SWITCH_ON: (_, _, _, _, _, _, _),
    S.SWITCH_ON_DISABLED: (S.READY_TO_SWITCH_ON, _, _, _, _, _, _),
    S.READY_TO_SWITCH_ON: (_, S.SWITCHED_ON, S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED,
                           S.SWITCH_ON_DISABLED, S.SWITCHED_ON, _),
    S.SWITCHED_ON: (S.READY_TO_SWITCH_ON, _, S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED,
                    S.SWITCH_ON_DISABLED, _, _),
    S.OPERATION_ENABLED: (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, _, S.SWITCH_ON_DISABLED,
                          S.QUICK_STOP_ACTIVE, S.SWITCHED_ON, _),
    S.QUICK_STOP_ACTIVE: (_, _, S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED, _, _, _),
    S.FAULT_REACTION_ACTIVE: (_, _, _, _, _, _, _),
    S.FAULT: (_, _, _, _, _, _, S.SWITCH_ON_DISABLED),
}
COLUMNS = (C.SHUTDOWN, C.SWITCH_ON, C.ENABLE_OPERATION, C.DISABLE_VOLTAGE, C.QUICK_STOP,
           C.DISABLE_OPERATION, C.FAULT_RESET)


@pytest.mark.parametrize("state", list(State))
@pytest.mark.parametrize("command", list(Command))
def test_every_state_and_command_follows_the_diagram(state: State, command: Command) -> None:
    expected = DIAGRAM[state][COLUMNS.index(command)]
    assert next_state(state, command, quick_stop_option=6) == (expected or state)


def test_quick_stop_active_is_left_for_enable_only_on_option_codes_5_to_8() -> None:
    for option in range(-2, 9):
        got = next_state(S.QUICK_STOP_ACTIVE, C.ENABLE_OPERATION, option)
        assert got == (S.OPERATION_ENABLED if 5 <= option <= 8 else S.QUICK_STOP_ACTIVE)


def expected_state(sw: int) -> State | None:
    """The state of a statusword read bit by bit from the standard's table (x: any bit):
    bits 6 5 4 3 2 1 0 = 0 x x 0 0 0 0 not ready, 1 x x 0 0 0 0 switch on disabled,
    0 1 x 0 0 0 1 ready, 0 1 x 0 0 1 1 switched on, 0 1 x 0 1 1 1 enabled,
    0 0 x 0 1 1 1 quick stop, 0 x x 1 1 1 1 fault reaction, 0 x x 1 0 0 0 fault."""
    b = [bool(sw >> i & 1) for i in range(7)]
    low = (b[3], b[2], b[1], b[0])
    if low == (False, False, False, False):
        return S.SWITCH_ON_DISABLED if b[6] else S.NOT_READY_TO_SWITCH_ON
    if b[6]:
        return None
    if low == (True, True, True, True):
        return S.FAULT_REACTION_ACTIVE
    if low == (True, False, False, False):
        return S.FAULT
    by_low = {(False, False, False, True): S.READY_TO_SWITCH_ON,
              (False, False, True, True): S.SWITCHED_ON,
              (False, True, True, True): S.OPERATION_ENABLED}
    if b[5]:
        return by_low.get(low)
    return S.QUICK_STOP_ACTIVE if low == (False, True, True, True) else None


def test_every_statusword_decodes_to_the_state_its_bits_show() -> None:
    # every pattern of bits 0-6 (the state bits), under several patterns of the others
    for sw in (low | high for low in range(0x80) for high in (0x0000, 0xFF80, 0x0280, 0x5500)):
        expected = expected_state(sw)
        if expected is None:
            with pytest.raises(StatuswordError, match=f"0x{sw:04X}"):
                decode_state(sw)
        else:
            assert decode_state(sw) is expected, hex(sw)
    for state, sw in STATUSWORDS.items():
        assert decode_state(sw) is state


def test_controlwords_decode_to_their_commands() -> None:
    for command, seq in CONTROLWORDS.items():
        previous = seq[0] if len(seq) > 1 else None
        got = decode_command(seq[-1], previous)
        assert got == (C.SWITCH_ON if command is C.DISABLE_OPERATION else command)
    assert decode_command(0x80, previous=0x80) is C.DISABLE_VOLTAGE   # no edge
    assert decode_command(0x8F, previous=0x0F) is C.FAULT_RESET
    assert decode_command(0x0B) is C.QUICK_STOP
    assert decode_command(0x0D) is C.DISABLE_VOLTAGE
    assert decode_command(0x0E) is None or decode_command(0x0E) is C.SHUTDOWN
    assert C.FAULT_RESET.sequence == (0x00, 0x80)


@pytest.mark.parametrize("state", list(State))
@pytest.mark.parametrize("target", list(Target))
def test_the_planner_reaches_every_target_or_names_the_state(state: State,
                                                             target: Target) -> None:
    """Applying the planner's commands to the diagram (with the drive's own transitions)
    reaches the target in a few steps, or the planner refuses naming the fault state."""
    done = {Target.ENABLED: {S.OPERATION_ENABLED}, Target.DISABLED: {S.SWITCH_ON_DISABLED},
            Target.QUICK_STOP: {S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED},
            Target.FAULT_CLEARED: set(State) - {S.FAULT, S.FAULT_REACTION_ACTIVE}}[target]
    current = state
    for _step in range(6):
        try:
            step = plan(current, target)
        except Unreachable as exc:
            assert current in (S.FAULT, S.FAULT_REACTION_ACTIVE)
            assert target is not Target.FAULT_CLEARED
            assert current.name in str(exc) and exc.state is current
            return
        if step is Plan.DONE:
            assert current in done
            return
        if step is Plan.WAIT:
            current = AUTOMATIC[current]
            continue
        assert isinstance(step, Command)
        after = next_state(current, step)
        assert after is not current, f"{step} leaves {current} where it is"
        current = after
    pytest.fail(f"{target} not reached from {state} in 6 steps")


# -- the Axis engine on scripted readings -------------------------------------------------------


def cws(actions: object) -> list[int]:
    return [w.value for w in actions.writes if w.obj is Obj.CONTROLWORD]  # type: ignore[attr-defined]


def test_enable_walks_the_states_and_completes_on_the_statusword() -> None:
    axis = Axis(AxisConfig("x"))
    out = axis.enable(0.0)
    assert out.reads == (Obj.STATUSWORD,) and not out.writes
    assert cws(axis.update(Reading(statusword=0x0250), 0.01)) == [0x06]
    assert cws(axis.update(Reading(statusword=0x0231), 0.02)) == [0x07]
    assert cws(axis.update(Reading(statusword=0x0233), 0.03)) == [0x0F]
    done = axis.update(Reading(statusword=0x0637), 0.04)
    assert [r.ok for r in done.results] == [True] and done.results[0].op is Op.ENABLE
    assert axis.busy is None and axis.state is S.OPERATION_ENABLED


def test_a_timeout_names_the_state_reached_and_the_statusword() -> None:
    axis = Axis(AxisConfig("x", timeouts=Timeouts(enable=0.5)))
    axis.update(Reading(statusword=0x0250), 0.0)
    axis.enable(0.0)
    axis.update(Reading(statusword=0x0231), 0.1)
    out = axis.poll(0.6)
    (result,) = out.results
    assert not result.ok and result.state is S.READY_TO_SWITCH_ON
    assert "0x0231" in str(result) and "READY_TO_SWITCH_ON" in str(result)


def test_a_fault_fails_the_command_with_the_error_code_and_is_reported_once() -> None:
    axis = Axis(AxisConfig("x"))
    axis.update(Reading(statusword=0x0250), 0.0)
    axis.enable(0.0)
    out = axis.update(Reading(statusword=0x0218), 0.1)
    assert Obj.ERROR_CODE in out.reads and not out.results      # waits for 0x603F
    out = axis.update(Reading(error_code=0x2310), 0.15)
    (result,) = out.results
    assert not result.ok and result.error_code == 0x2310 and result.state is S.FAULT
    assert [f.error_code for f in out.faults if f] == [0x2310]
    assert not axis.update(Reading(statusword=0x0218), 0.2).faults
    # nothing is written by the engine on its own: no re-enable, no reset
    assert not axis.poll(5.0).writes


def test_a_fault_without_readable_error_code_is_reported_after_the_wait() -> None:
    axis = Axis(AxisConfig("x", timeouts=Timeouts(error_code=0.3)))
    axis.update(Reading(statusword=0x0250), 0.0)
    axis.enable(0.0)
    assert not axis.update(Reading(statusword=0x0218), 0.1).results
    (result,) = axis.poll(0.45).results
    assert result.error_code is None and "unknown" in str(result)


def test_fault_reset_is_a_rising_edge_in_two_writes_and_retried() -> None:
    axis = Axis(AxisConfig("x", edge_gap=0.01, resend=0.2, timeouts=Timeouts(fault_reset=1.0)))
    axis.update(Reading(statusword=0x0218, error_code=0x8611), 0.0)
    assert cws(axis.fault_reset(0.0)) == [0x00]
    assert cws(axis.poll(0.005)) == []
    assert cws(axis.poll(0.011)) == [0x80]
    assert cws(axis.poll(0.25)) == [0x00]           # still in FAULT: a new edge
    assert cws(axis.poll(0.27)) == [0x80]
    out = axis.update(Reading(statusword=0x0250), 0.3)
    # out of FAULT: done once the drive's new 0x603F is read (the result shows it)
    assert out.results == () and out.faults == (None,) and Obj.ERROR_CODE in out.reads
    (result,) = axis.update(Reading(error_code=0x0000, answer=True), 0.31).results
    assert result.ok and result.error_code == 0 and "0x603F 0x0000" in str(result)
    assert axis.fault is None


def test_a_fault_reset_whose_new_error_code_is_not_answered_is_done_saying_so() -> None:
    axis = Axis(AxisConfig("x", edge_gap=0.01, timeouts=Timeouts(error_code=0.2)))
    axis.update(Reading(statusword=0x0218, error_code=0x8611), 0.0)
    axis.fault_reset(0.0)
    axis.poll(0.011)
    assert not axis.update(Reading(statusword=0x0250), 0.05).results
    (result,) = axis.poll(0.3).results
    assert result.ok and result.error_code is None and "not read" in result.reason


def test_fault_reset_that_the_drive_refuses_fails_naming_the_code() -> None:
    axis = Axis(AxisConfig("x", timeouts=Timeouts(fault_reset=0.5)))
    axis.update(Reading(statusword=0x0218, error_code=0x4310), 0.0)
    axis.fault_reset(0.0)
    t, results = 0.0, []
    while not results:
        t += 0.01
        results = list(axis.poll(t).results)
    assert not results[0].ok and results[0].error_code == 0x4310 and t >= 0.5


def test_set_mode_fails_naming_what_0x6061_shows() -> None:
    axis = Axis(AxisConfig("x", timeouts=Timeouts(set_mode=0.3)))
    axis.update(Reading(statusword=0x0637, mode_display=1), 0.0)
    out = axis.set_mode(Mode.HM, 0.0)
    assert [(w.obj, w.value) for w in out.writes] == [(Obj.MODES, 6)]
    assert out.reads == (Obj.MODES_DISPLAY,)
    (result,) = axis.poll(0.31).results
    assert not result.ok and "0x6061 shows 1 (PP), not 6 (HM)" in result.reason


def test_move_to_uses_the_set_point_handshake_and_units() -> None:
    axis = Axis(AxisConfig("x", counts_per_unit=100.0, position_limits=(-5.0, 5.0),
                           position_window=2))
    axis.update(Reading(statusword=0x0637, mode_display=1, position=0), 0.0)
    out = axis.move_to(2.5, 0.0)
    # controlword unknown so far: bit 4 is written low first, so that 0x1F is an edge
    assert [(w.obj, w.value) for w in out.writes] == [(Obj.TARGET_POSITION, 250),
                                                      (Obj.CONTROLWORD, 0x0F),
                                                      (Obj.CONTROLWORD, 0x1F)]
    assert not axis.update(Reading(statusword=0x0237, position=10), 0.1).results
    assert cws(axis.update(Reading(statusword=0x1237), 0.2)) == [0x0F]   # acked: bit 4 off
    assert not axis.update(Reading(statusword=0x0237, position=200), 0.3).results
    (done,) = axis.update(Reading(statusword=0x0637, position=249), 0.4).results
    assert done.ok and axis.position == pytest.approx(2.49)
    with pytest.raises(AxisLimitError, match="outside the limits"):
        axis.move_to(6.0, 1.0)
    with pytest.raises(AxisLimitError, match="finite"):
        axis.move_to(float("nan"), 1.0)
    assert axis.busy is None


def test_one_command_at_a_time_but_safe_stop_supersedes() -> None:
    axis = Axis(AxisConfig("x"))
    axis.update(Reading(statusword=0x0250), 0.0)
    axis.enable(0.0)
    with pytest.raises(AxisBusy, match="enable is running"):
        axis.set_mode(Mode.PP, 0.1)
    out = axis.safe_stop(0.1)
    assert [(r.op, r.ok, r.reason) for r in out.results] == \
        [(Op.ENABLE, False, "superseded by safe stop")]
    # switch on disabled was read before the enable's shutdown went out: it proves nothing
    # (the drive may be ready to switch on now), so the safe stop sends a quick stop, safe in
    # any state, and is done on the statusword that follows it
    assert cws(out) == [0x02]
    (done,) = axis.update(Reading(statusword=0x0250), 0.2).results
    assert (done.op, done.ok, done.reason) == (Op.SAFE_STOP, True, "")


@pytest.mark.parametrize("option,ends", [(2, [0x02]), (6, [0x02, 0x00])])
def test_safe_stop_waits_for_standstill_and_respects_the_option_code(option: int,
                                                                     ends: list[int]) -> None:
    axis = Axis(AxisConfig("x", quick_stop_option=option, standstill=5))
    axis.update(Reading(statusword=0x0637, velocity=1000), 0.0)
    sent = cws(axis.safe_stop(0.0))
    sent += cws(axis.update(Reading(statusword=0x0217, velocity=400), 0.1))
    assert sent == [0x02]                        # no disable voltage while moving
    if option == 2:     # the drive goes to switch on disabled by itself
        out = axis.update(Reading(statusword=0x0250, velocity=0), 0.2)
    else:               # it stays in quick stop active: the engine removes the power
        sent += cws(axis.update(Reading(statusword=0x0217, velocity=0), 0.2))
        out = axis.update(Reading(statusword=0x0250), 0.3)
    sent += cws(out)
    assert sent == ends and [r.ok for r in out.results] == [True]
    assert axis.state is S.SWITCH_ON_DISABLED


def test_safe_stop_not_stopped_in_time_disables_voltage_and_fails() -> None:
    axis = Axis(AxisConfig("x", safe_stop=SafeStop.QUICK_STOP_THEN_DISABLE,
                           quick_stop_option=6, timeouts=Timeouts(safe_stop=1.0)))
    axis.update(Reading(statusword=0x0637, velocity=1000), 0.0)
    axis.safe_stop(0.0)
    axis.update(Reading(statusword=0x0217, velocity=900), 0.5)
    out = axis.poll(1.0)
    assert cws(out) == [0x00]
    (result,) = out.results
    assert not result.ok and "voltage disabled while moving" in result.reason


def test_multi_axis_objects_are_offset() -> None:
    cfg = AxisConfig("b", axis=1)
    assert cfg.index(Obj.CONTROLWORD) == 0x6840
    axis = Axis(cfg)
    axis.update(Reading(statusword=0x0250), 0.0)
    (w,) = axis.enable(0.0).writes
    assert (w.index, w.value) == (0x6840, 0x06)
    with pytest.raises(ValueError, match="counts_per_unit"):
        AxisConfig("c", counts_per_unit=0.0)


def test_an_axis_configuration_from_a_map_table_and_its_errors() -> None:
    cfg = config_from_table("x", {"axis": 1, "counts_per_unit": 1000, "position_limits": [0, 2],
                                  "safe_stop": "halt_then_disable", "quick_stop_option": 6,
                                  "timeouts": {"enable": 3.5}}, "cell.toml: device[3]")
    assert cfg.axis == 1 and cfg.counts_per_unit == 1000.0 and cfg.position_limits == (0, 2)
    assert cfg.safe_stop is SafeStop.HALT_THEN_DISABLE and cfg.timeouts.enable == 3.5
    assert cfg.timeouts.disable == Timeouts().disable
    bad = [({"axis": 9}, "device[3].axis: expected an axis number 0..7"),
           ({"counts_per_unit": 0}, "device[3].counts_per_unit: expected a finite positive"),
           ({"position_limits": [2, 1]}, "device[3].position_limits: low 2.0 is not below"),
           ({"safe_stop": "brake"}, "device[3].safe_stop: expected one of quick_stop_then"),
           ({"timeouts": {"enabel": 1}}, "device[3].timeouts.enabel: unknown timeout"),
           ({"timeouts": {"enable": -1}}, "device[3].timeouts.enable: expected a finite"),
           ({"speed": 1}, "device[3].speed: unknown key for a cia402 axis")]
    for table, message in bad:
        with pytest.raises(Cia402Error, match=re.escape(message)):
            config_from_table("x", table, "cell.toml: device[3]")


def test_next_controlwords_from_the_planner() -> None:
    assert next_controlwords(S.SWITCH_ON_DISABLED, Target.ENABLED) == (0x06,)
    assert next_controlwords(S.SWITCHED_ON, Target.ENABLED) == (0x0F,)
    assert next_controlwords(S.OPERATION_ENABLED, Target.QUICK_STOP) == (0x02,)
    assert next_controlwords(S.FAULT, Target.FAULT_CLEARED) == (0x00, 0x80)
    assert next_controlwords(S.OPERATION_ENABLED, Target.ENABLED) == ()
    with pytest.raises(Unreachable, match="ENABLED cannot be reached from FAULT"):
        next_controlwords(S.FAULT, Target.ENABLED)


def test_a_lost_drive_fails_the_command_and_forgets_its_state() -> None:
    axis = Axis(AxisConfig("x"))
    axis.update(Reading(statusword=0x0250, position=10), 0.0)
    axis.enable(0.0)
    out = axis.lost("heartbeat lost", 0.1)
    (result,) = out.results
    assert not result.ok and result.reason == "drive lost: heartbeat lost"
    assert axis.state is None and axis.position is None and axis.busy is None
    # after a reboot the drive shows switch on disabled; nothing is sent without a command
    assert not axis.update(Reading(statusword=0x0250), 0.2).writes
    assert cws(axis.enable(0.3)) == [0x06]


def test_a_safe_stop_in_a_fault_is_reached_and_a_fault_reaction_is_waited_for() -> None:
    axis = Axis(AxisConfig("x", timeouts=Timeouts(safe_stop=1.0)))
    axis.update(Reading(statusword=0x0637, error_code=0x2310), 0.0)
    axis.update(Reading(statusword=0x021F, error_code=0x2310), 0.1)   # fault reaction
    out = axis.safe_stop(0.2)
    assert not out.writes and not out.results
    out = axis.poll(1.1)                                              # reaction still on
    assert not out.writes and not out.results
    out = axis.update(Reading(statusword=0x0218), 1.15)               # FAULT: power off
    (result,) = out.results
    assert result.ok and result.state is S.FAULT and not out.writes
    assert "0x603F 0x2310" in str(result) and "no torque" in str(result)
    # a reaction that never ends fails at the timeout, still sending nothing
    axis = Axis(AxisConfig("x", timeouts=Timeouts(safe_stop=1.0)))
    axis.update(Reading(statusword=0x021F, error_code=0x2310), 0.0)
    axis.safe_stop(0.0)
    assert not axis.poll(0.9).results
    out = axis.poll(1.0)
    (result,) = out.results
    assert not result.ok and "FAULT_REACTION_ACTIVE" in result.reason and not out.writes



# -- readings older than the command (issue 37: "a reading older than the command is trusted") --


def enabled_axis(mode: int, **config: object) -> Axis:
    """An axis confirmed in OPERATION_ENABLED and ``mode``, standing at 0 (readings after every
    write so far)."""
    axis = Axis(AxisConfig("x", **config))  # type: ignore[arg-type]
    axis.update(Reading(statusword=0x0250, mode_display=mode, position=0, velocity=0), 0.0)
    axis.enable(0.0)
    for sw in (0x0231, 0x0233, 0x0637):
        axis.update(Reading(statusword=sw, velocity=0), 0.01)
    assert axis.state is S.OPERATION_ENABLED and axis.busy is None
    return axis


@pytest.mark.parametrize("option", [2, 6])
def test_a_safe_stop_right_after_a_move_starts_waits_for_a_reading_after_the_quick_stop(
        option: int) -> None:
    """The velocity the engine holds (0) was read before the move started: it proves nothing
    about standstill. Disable voltage goes out only once a reading taken after the quick stop
    shows standstill (option 2: the drive gets there by itself)."""
    axis = enabled_axis(3, quick_stop_option=option, standstill=5)
    assert Obj.TARGET_VELOCITY in [w.obj for w in axis.at_velocity(5000, 1.0).writes]
    # a TPDO from before the quick stop: it arrives, then waits in the host's queue
    queued = axis.order.pdo_received((Obj.STATUSWORD, Obj.VELOCITY_ACTUAL))
    out = axis.safe_stop(1.0)
    assert cws(out) == [0x02] and not out.results[1:]
    sent = cws(axis.update(Reading(statusword=0x0637, velocity=0, received=queued), 1.01))
    sent += cws(axis.poll(1.2))
    assert sent == []                                 # no disable voltage behind the quick stop
    assert cws(axis.update(Reading(statusword=0x0217, velocity=4000), 1.3)) == []
    if option == 6:
        assert cws(axis.update(Reading(statusword=0x0217, velocity=0), 1.4)) == [0x00]
        out = axis.update(Reading(statusword=0x0250, velocity=0), 1.5)
    else:
        out = axis.update(Reading(statusword=0x0250, velocity=0), 1.4)
        assert cws(out) == []
    (result,) = out.results
    assert result.op is Op.SAFE_STOP and result.ok and result.state is S.SWITCH_ON_DISABLED


def test_a_stale_statusword_after_a_newer_one_does_not_fail_a_running_move() -> None:
    """The two-process run's failure: move to failed at once with 'left OPERATION_ENABLED for
    SWITCHED_ON (0x0233)', a statusword older than the one that confirmed the enable."""
    axis = enabled_axis(1, position_window=2)
    # the TPDO showing switched on arrived during the enable but waited in the queue
    old = axis.order.pdo_received((Obj.STATUSWORD,))
    newer = axis.order.pdo_received((Obj.STATUSWORD,))
    axis.update(Reading(statusword=0x0637, received=newer), 0.02)
    assert cws(axis.move_to(100, 0.03)) == [0x1F]
    out = axis.update(Reading(statusword=0x0233, received=old), 0.031)
    assert not out.results and axis.busy is Op.MOVE_TO
    assert axis.state is S.OPERATION_ENABLED and axis.stale_readings == 1
    # the move goes on: acknowledge, then target reached at the position
    assert cws(axis.update(Reading(statusword=0x1237, position=10), 0.1)) == [0x0F]
    (done,) = axis.update(Reading(statusword=0x0637, position=99), 0.2).results
    assert done.op is Op.MOVE_TO and done.ok


def test_a_reading_queued_before_the_write_confirms_nothing() -> None:
    """A TPDO received before the command's write, fed after it: neither completes nor fails
    the command; the next one does."""
    axis = enabled_axis(8, position_window=2)                 # CSP: the target alone
    before = axis.order.pdo_received((Obj.STATUSWORD, Obj.POSITION_ACTUAL))
    assert [w.obj for w in axis.move_to(0, 0.1).writes] == [Obj.TARGET_POSITION]
    out = axis.update(Reading(statusword=0x0233, position=0, received=before), 0.11)
    assert not out.results and axis.busy is Op.MOVE_TO
    assert Obj.STATUSWORD in out.reads                       # a fresh one is asked for
    (done,) = axis.update(Reading(statusword=0x0637, position=1), 0.2).results
    assert done.ok
    # and a failure, too, needs a statusword taken after the write
    before = axis.order.pdo_received((Obj.STATUSWORD,))
    axis.move_to(0.5, 0.3)
    assert not axis.update(Reading(statusword=0x0233, received=before), 0.31).results
    (failed,) = axis.update(Reading(statusword=0x0233), 0.32).results
    assert not failed.ok and "left OPERATION_ENABLED for SWITCHED_ON" in failed.reason


def test_an_sdo_answer_asked_before_a_tpdo_arrived_is_dropped_for_that_object() -> None:
    axis = Axis(AxisConfig("x"))
    axis.update(Reading(statusword=0x0233), 0.0)
    asked = axis.order.mark()
    tpdo = axis.order.pdo_received((Obj.STATUSWORD,))        # arrives during the SDO read
    axis.update(Reading(statusword=0x0637, position=7, received=asked, answer=True), 0.01)
    assert axis.state is S.SWITCHED_ON and axis.position == 7  # position: no newer PDO
    axis.update(Reading(statusword=0x0250, received=tpdo), 0.02)
    assert axis.state is S.SWITCH_ON_DISABLED and axis.stale_readings == 1
