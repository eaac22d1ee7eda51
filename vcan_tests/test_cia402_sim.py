"""test_cia402_sim - the simulated CiA 402 drive (chcos/apps/sim/cia402_drive.py) commanded by the
Axis engine over a virtual bus, and cross-checked against the independent durand drive: the same
command sequences must give the same results, states and received controlwords on both."""

from __future__ import annotations

import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from chcos.apps.sim.canopen_slave import Clock
from chcos.apps.sim.cia402_drive import (
    FOLLOWING_ERROR,
    OVER_TEMPERATURE,
    Cia402Drive,
    DriveModel,
    Power,
)
from chcos.errors import ConfigError
from drivers.codecs.cia402 import Actions, Axis, AxisConfig, Mode, State, Timeouts
from vcan_tests.peers.durand_cia402 import DurandCia402Drive
from vcan_tests.support_cia402 import Cia402Host, drive_eds

NODE = 7
Step = Callable[[Axis, float], Actions]


def config(option: int) -> AxisConfig:
    return AxisConfig("x", quick_stop_option=option, position_window=1, velocity_window=1,
                      standstill=0, timeouts=Timeouts(set_mode=0.3, fault_reset=0.3))


def sim_rig(option: int = 2) -> tuple[Cia402Drive, Cia402Host]:
    channel = f"cia402sim-{uuid.uuid4().hex}"
    drive = Cia402Drive(NODE, channel=channel, heartbeat_period=0, quick_stop_option=option,
                        refused_modes=(6,), clock=Clock.TICK)
    drive.start()
    host = Cia402Host(channel, NODE, drive, config(option))
    host.start_node()
    return drive, host


def durand_rig(option: int = 2) -> tuple[DurandCia402Drive, Cia402Host]:
    channel = f"cia402dur-{uuid.uuid4().hex}"
    drive = DurandCia402Drive(channel, NODE, quick_stop_option=option)
    host = Cia402Host(channel, NODE, drive, config(option))
    host.start_node()
    return drive, host


@pytest.fixture
def sim() -> Iterator[tuple[Cia402Drive, Cia402Host]]:
    drive, host = sim_rig()
    yield drive, host
    host.close()
    drive.stop()


#: command sequences run on both drives: (name, [(label, start)])
SEQUENCES: dict[str, list[tuple[str, Step]]] = {
    "enable, position move, disable": [
        ("enable", lambda a, t: a.enable(t)),
        ("mode PP", lambda a, t: a.set_mode(Mode.PP, t)),
        ("move", lambda a, t: a.move_to(400, t)),
        ("move back", lambda a, t: a.move_to(-100, t)),
        ("disable", lambda a, t: a.disable(t)),
    ],
    "velocity, quick stop, re-enable": [
        ("enable", lambda a, t: a.enable(t)),
        ("mode PV", lambda a, t: a.set_mode(Mode.PV, t)),
        ("run", lambda a, t: a.at_velocity(3000, t)),
        ("quick stop", lambda a, t: a.quick_stop(t)),
        ("enable", lambda a, t: a.enable(t)),
    ],
    "refused homing, safe stop": [
        ("enable", lambda a, t: a.enable(t)),
        ("mode PV", lambda a, t: a.set_mode(Mode.PV, t)),
        ("mode HM", lambda a, t: a.set_mode(Mode.HM, t)),
        ("run", lambda a, t: a.at_velocity(-2500, t)),
        ("safe stop", lambda a, t: a.safe_stop(t)),
        ("fault reset (none)", lambda a, t: a.fault_reset(t)),
    ],
}


def trace(host: Cia402Host, steps: list[tuple[str, Step]]) -> list[tuple[str, bool, str, str]]:
    out = []
    for label, start in steps:
        result = host.run(lambda now, s=start: s(host.axis, now))
        state = result.state.name if result.state else "none"
        out.append((label, result.ok, state, result.reason))
    return out


@pytest.mark.parametrize("option", [2, 6])
@pytest.mark.parametrize("name", list(SEQUENCES))
def test_the_simulated_drive_behaves_as_the_durand_drive(name: str, option: int) -> None:
    steps = SEQUENCES[name]
    sim_drive, sim_host = sim_rig(option)
    dur_drive, dur_host = durand_rig(option)
    try:
        on_sim = trace(sim_host, steps)
        on_durand = trace(dur_host, steps)
        assert on_sim == on_durand
        assert sim_drive.received == dur_drive.received
        assert sim_drive.published()[:2] == dur_drive.published()[:2]   # statusword, mode
        assert any(not ok for _l, ok, _s, _r in on_sim) == (name == "refused homing, safe stop")
    finally:
        sim_host.close()
        sim_drive.stop()
        dur_host.close()
        dur_drive.close()


def test_a_following_error_faults_with_emcy_and_needs_a_reset(sim: tuple) -> None:
    drive, host = sim
    assert host.run(host.axis.enable).ok
    assert host.run(lambda now: host.axis.set_mode(Mode.PP, now)).ok
    drive.block()
    result = host.run(lambda now: host.axis.move_to(100_000, now))
    assert not result.ok and result.error_code == FOLLOWING_ERROR
    assert FOLLOWING_ERROR in host.emcys and drive.get(0x603F) == FOLLOWING_ERROR
    host.idle(0.5)
    assert drive.model.power is Power.FAULT          # stays until reset
    drive.block(False)
    assert host.run(host.axis.fault_reset).ok
    assert drive.model.power is Power.SWITCH_ON_DISABLED and host.emcys[-1] == 0
    assert drive.received[-2:] == [0x00, 0x80]


def test_over_temperature_refuses_the_reset_until_cooled(sim: tuple) -> None:
    drive, host = sim
    assert host.run(host.axis.enable).ok
    drive.set_temperature(95.0)
    host.idle(0.05)
    assert host.axis.state is State.FAULT and host.axis.fault is not None
    assert host.axis.fault.error_code == OVER_TEMPERATURE
    result = host.run(host.axis.fault_reset)
    assert not result.ok and result.error_code == OVER_TEMPERATURE
    drive.set_temperature(40.0)
    assert host.run(host.axis.fault_reset).ok
    assert host.run(host.axis.enable).ok and drive.model.power is Power.ENABLED


def test_quick_stop_decelerates_on_the_quick_stop_ramp(sim: tuple) -> None:
    drive, host = sim
    assert host.run(host.axis.enable).ok
    assert host.run(lambda now: host.axis.set_mode(Mode.PV, now)).ok
    assert host.run(lambda now: host.axis.at_velocity(5000, now)).ok
    start = host.now
    assert host.run(host.axis.quick_stop).ok
    # 5000 counts/s at 50000 counts/s^2: a tenth of a second, not at once
    assert host.now - start >= 0.09
    assert drive.model.power is Power.SWITCH_ON_DISABLED and drive.model.velocity == 0


def test_the_model_reacts_to_every_command_from_every_state() -> None:
    """The model's own table against the diagram, on the controlword values masters send."""
    cws = {"shutdown": 0x06, "switch on": 0x07, "enable": 0x0F, "disable voltage": 0x00,
           "quick stop": 0x02}
    expect = {
        Power.SWITCH_ON_DISABLED: {"shutdown": Power.READY},
        Power.READY: {"switch on": Power.SWITCHED_ON, "enable": Power.ENABLED,
                      "disable voltage": Power.SWITCH_ON_DISABLED,
                      "quick stop": Power.SWITCH_ON_DISABLED},
        Power.SWITCHED_ON: {"shutdown": Power.READY, "enable": Power.ENABLED,
                            "disable voltage": Power.SWITCH_ON_DISABLED,
                            "quick stop": Power.SWITCH_ON_DISABLED},
        Power.ENABLED: {"shutdown": Power.READY, "switch on": Power.SWITCHED_ON,
                        "disable voltage": Power.SWITCH_ON_DISABLED,
                        "quick stop": Power.QUICK_STOP},
        Power.QUICK_STOP: {"disable voltage": Power.SWITCH_ON_DISABLED},
        Power.FAULT: {},
    }
    for state, moves in expect.items():
        for name, cw in cws.items():
            model = DriveModel()
            model.power, model.last_cw = state, 0
            model.controlword(cw, quick_stop_option=2)
            assert model.power is moves.get(name, state), (state, name)
    stuck = DriveModel(power=Power.FAULT, last_cw=0x80)
    stuck.controlword(0x80, 2)                       # bit 7 set, but no edge: no reset
    assert stuck.power is Power.FAULT
    stuck.controlword(0x00, 2)
    stuck.controlword(0x80, 2)                       # the rising edge
    assert stuck.power is Power.SWITCH_ON_DISABLED


def test_an_eds_without_the_cia402_objects_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "half.eds"
    path.write_text(drive_eds(rpdos=(), tpdos=((0x6064,),), without=(0x6060,)))
    with pytest.raises(ConfigError, match="0x6060"):
        Cia402Drive(3, path, channel="unused")
    # a vendor drive without the optional objects (0x6061, 0x603F) still runs its state machine
    path.write_text(drive_eds(rpdos=(), tpdos=((0x6064,),), without=(0x6061, 0x603F)))
    drive = Cia402Drive(3, path, channel="unused")
    drive.step(0.01)
    statusword, mode, _position, _velocity, error = drive.published()
    assert statusword & 0x4F == 0x40 and mode == 0 and error == 0


def test_homing_on_a_drive_that_accepts_it() -> None:
    channel = f"cia402sim-{uuid.uuid4().hex}"
    drive = Cia402Drive(NODE, channel=channel, heartbeat_period=0, clock=Clock.TICK)
    drive.start()
    host = Cia402Host(channel, NODE, drive, config(2))
    try:
        host.start_node()
        assert host.run(host.axis.enable).ok
        assert host.run(lambda now: host.axis.set_mode(Mode.PV, now)).ok
        assert host.run(lambda now: host.axis.at_velocity(4000, now)).ok
        host.idle(0.2)
        assert drive.model.position > 0
        assert host.run(lambda now: host.axis.set_mode(Mode.HM, now)).ok
        result = host.run(host.axis.home)
        assert result.ok, result
        assert drive.model.position == 0 and drive.model.homed
        assert 0x1F in drive.received and drive.received[-1] == 0x0F
    finally:
        host.close()
        drive.stop()


def test_the_command_line_runs_the_drive_for_a_duration() -> None:
    from chcos.apps.sim.cia402_drive import main

    channel = f"cia402cli-{uuid.uuid4().hex}"
    assert main(["--node", "3", "--channel", channel, "--duration", "0.05"]) == 0
    assert main(["--node", "300", "--channel", channel]) == 2
