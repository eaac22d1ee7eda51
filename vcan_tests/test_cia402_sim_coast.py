"""test_cia402_sim_coast - the simulated drive's motor once its power stage is off
(chcos/apps/sim/cia402_drive.py, DriveModel): it coasts down by friction, slower than a quick stop
brakes it, so that tests see a braked stop and a coasting one apart (issue 37: "disable voltage"
from QUICK_STOP_ACTIVE used to leave the velocity as it was, forever)."""

from __future__ import annotations

import pytest

from chcos.apps.sim.cia402_drive import PV, DriveModel, Power

OPTION = 6          # quick stop active is kept once stopped: the master removes the power
DECELERATION = 50_000


def step(model: DriveModel, dt: float = 0.01, velocity: int = 5000) -> None:
    model.step(dt, target_position=0, target_velocity=velocity, profile_velocity=10_000,
               quick_stop_deceleration=DECELERATION, following_window=5000,
               quick_stop_option=OPTION)


def running(velocity: int = 5000) -> DriveModel:
    """A model enabled in profile velocity, running at ``velocity`` counts/s."""
    model = DriveModel()
    step(model)                                    # self test: switch on disabled
    model.mode(PV)
    for cw in (0x06, 0x07, 0x0F):
        model.controlword(cw, OPTION)
    step(model, velocity=velocity)
    assert model.power is Power.ENABLED and model.velocity == velocity
    return model


def seconds_to_stop(model: DriveModel, limit: float = 10.0) -> float:
    t = 0.0
    while model.velocity and t < limit:
        step(model)
        t += 0.01
    return t


def test_disable_voltage_during_a_quick_stop_coasts_down_instead_of_keeping_the_speed() -> None:
    model = running()
    model.controlword(0x02, OPTION)
    step(model)                                     # braking: 5000 - 500
    assert model.power is Power.QUICK_STOP and model.velocity == pytest.approx(4500)
    model.controlword(0x00, OPTION)                 # the power removed while moving
    assert model.power is Power.SWITCH_ON_DISABLED
    step(model)
    assert 4400 < model.velocity < 4500            # friction alone: 20 counts/s per step
    t = seconds_to_stop(model)
    assert model.velocity == 0 and t == pytest.approx(4480 / model.coast_deceleration, abs=0.02)


def test_a_braked_stop_is_shorter_than_a_coasting_one() -> None:
    braked, coasting = running(), running()
    start = braked.position
    braked.controlword(0x02, OPTION)
    coasting.controlword(0x00, OPTION)
    t_braked, t_coast = seconds_to_stop(braked), seconds_to_stop(coasting)
    assert braked.power is Power.QUICK_STOP and coasting.power is Power.SWITCH_ON_DISABLED
    assert t_braked == pytest.approx(0.1, abs=0.02) and t_coast > 10 * t_braked
    assert coasting.position - start > 10 * (braked.position - start)
    # stopped, the power off stays stopped
    braked.controlword(0x00, OPTION)
    step(braked)
    assert braked.velocity == 0 and coasting.velocity == 0
