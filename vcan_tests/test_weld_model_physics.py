"""Physics of the welding cell: servos, arc, temperature, tip sticking, gas, wire, weld record."""

from __future__ import annotations

import itertools
import math
import re
from typing import Any

import pytest

from chcos.apps.weld.kinematics import UnreachableError
from chcos.apps.weld.model import CellConfig, Flaw, SimulationError, WeldCell
from chcos.errors import ConfigError, DeviceError

DT = 0.02


def settle(cell: WeldCell, limit: float = 20.0) -> None:
    """Step until every joint has reached its target (at most ``limit`` s)."""
    end = cell.t + limit
    while max(abs(a - b) for a, b in zip(cell.joints, cell.targets, strict=True)) > 1e-12:
        assert cell.t < end, "joints did not reach their targets"
        cell.step(DT)


def go_to(cell: WeldCell, s: float, standoff: float = 10.0) -> None:
    """Put the tip over the seam at arc length ``s`` (mm), ``standoff`` mm above the plate."""
    x, y = cell.seam.centre(s)
    cell.move_tip((x, y, cell.seam.plate_z + standoff), cell.seam.heading(s))
    settle(cell)


def track(
    cell: WeldCell, s_from: float, s_to: float, speed: float = 5.0, standoff: float = 10.0
) -> None:
    """Move the tip along the seam from ``s_from`` to ``s_to`` (mm) at ``speed`` mm/s."""
    s = s_from
    while s < s_to:
        s = min(s_to, s + speed * DT)
        x, y = cell.seam.centre(s)
        cell.move_tip((x, y, cell.seam.plate_z + standoff), cell.seam.heading(s))
        cell.step(DT)


def weld_on(cell: WeldCell, volts: float = 24.0, wire: float = 100.0) -> None:
    cell.set_gas_valve(True)
    cell.set_voltage(volts)
    cell.set_wire_speed(wire)


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"heat_tau": 0.0}, "heat_tau=0.0"),
        ({"noise_temp": -1.0}, "noise_temp"),
        ({"ambient": math.nan}, "ambient=nan"),
        ({"weld_band": (1600.0, 1450.0)}, "weld_band"),
        ({"joint_max_speed": (1.0, 1.0, 1.0, 1.0, 0.0)}, "joint_max_speed"),
        ({"nominal_voltage": 50.0}, "max_voltage"),
    ],
)
def test_bad_cell_config_is_a_config_error(kwargs: dict[str, Any], fragment: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(fragment)):
        CellConfig(**kwargs)


def test_unreachable_home_is_refused() -> None:
    with pytest.raises(UnreachableError, match="beyond the reach"):
        WeldCell(CellConfig(home_position=(1500.0, 0.0, 250.0)))


def test_starts_at_home_cold_and_off() -> None:
    cell = WeldCell()
    r = cell.readings()
    assert cell.pose.position == pytest.approx(CellConfig().home_position, abs=1e-6)
    assert r.t == 0.0 and r.arc_voltage == 0.0 and r.arc_current == 0.0
    assert r.arc_temperature == pytest.approx(20.0, abs=15.0)
    assert r.gas_flow == 0.0 and r.gas_line_pressure == 0.0
    assert r.gas_bottle_pressure == pytest.approx(200.0, abs=0.5)
    assert r.servo_ok == (True,) * 5 and not r.intruder and r.silent == frozenset()
    assert r.range_mm is None  # 250 mm above the plate is out of the sensor's range


def test_joints_move_at_their_commanded_speed_and_stop_on_target() -> None:
    cell = WeldCell()
    start = list(cell.joints)
    cell.set_joint_target(1, start[0] + 0.5)
    for _ in range(5):
        cell.step(0.02)
    assert cell.joints[0] - start[0] == pytest.approx(0.1)  # 1.0 rad/s for 0.1 s
    cell.set_joint_speed(1, 0.25)
    for _ in range(10):
        cell.step(0.02)
    assert cell.joints[0] - start[0] == pytest.approx(0.15)
    settle(cell)
    assert cell.joints[0] == pytest.approx(start[0] + 0.5, abs=1e-12)
    assert cell.joints[1:] == start[1:]
    assert cell.readings().joints[0] == pytest.approx(start[0] + 0.5, abs=1e-3)


def test_actuator_limits_are_device_errors() -> None:
    cell = WeldCell()
    with pytest.raises(DeviceError, match="joint1 speed"):
        cell.set_joint_speed(1, 5.0)
    with pytest.raises(DeviceError, match="joint 6"):
        cell.set_joint_target(6, 0.0)
    with pytest.raises(DeviceError, match="joint2 target"):
        cell.set_joint_target(2, 3.0)
    with pytest.raises(DeviceError, match="5 angles"):
        cell.set_joint_targets([0.0] * 4)
    with pytest.raises(DeviceError, match="voltage"):
        cell.set_voltage(55.0)
    with pytest.raises(DeviceError, match="wire speed"):
        cell.set_wire_speed(-1.0)
    with pytest.raises(UnreachableError):
        cell.move_tip((2000.0, 0.0, 0.0), 0.0)
    for dt in (0.0, -0.1, math.nan, 2.0):
        with pytest.raises(SimulationError, match="dt"):
            cell.step(dt)


def test_temperature_in_band_at_nominal_settings() -> None:
    cell = WeldCell(seed=3)
    go_to(cell, 0.0)
    weld_on(cell)
    track(cell, 0.0, 60.0)
    temps = []
    for s in (60.0, 70.0, 80.0, 90.0):
        track(cell, s, s + 10.0)
        temps.append(cell.readings().arc_temperature)
    assert all(1450.0 <= t <= 1600.0 for t in temps), temps
    r = cell.readings()
    assert cell.arc_burning
    assert r.arc_voltage == pytest.approx(24.0, abs=0.5)
    assert r.arc_current == pytest.approx(200.0, abs=10.0)
    assert r.wire_speed == pytest.approx(100.0, abs=2.0)
    assert r.gas_flow == pytest.approx(15.0, abs=0.5)
    assert r.gas_line_pressure == pytest.approx(2.5, abs=0.1)


def _steady_temperature(volts: float, standoff: float, speed: float) -> float:
    cell = WeldCell(seed=0)
    go_to(cell, 20.0, standoff)
    weld_on(cell, volts)
    track(cell, 20.0, 20.0 + 8.0 * speed, speed, standoff)
    return cell.temperature


def test_temperature_rises_with_voltage_and_falls_with_standoff_and_speed() -> None:
    nominal = _steady_temperature(24.0, 10.0, 5.0)
    assert 1450.0 <= nominal <= 1600.0
    assert _steady_temperature(28.0, 10.0, 5.0) > nominal + 100.0
    too_far = _steady_temperature(24.0, 16.0, 5.0)
    assert too_far < 1450.0  # too far: not enough heat for a pool
    assert _steady_temperature(24.0, 6.0, 5.0) > 1600.0  # too close: too hot
    assert _steady_temperature(24.0, 10.0, 10.0) < nominal - 300.0


def test_arc_goes_out_when_too_far_and_temperature_drops() -> None:
    cell = WeldCell()
    go_to(cell, 50.0)
    weld_on(cell)
    track(cell, 50.0, 70.0)
    hot = cell.temperature
    x, y = cell.seam.centre(70.0)
    cell.move_tip((x, y, 25.0), cell.seam.heading(70.0))  # 25 mm > 0.75 mm/V * 24 V
    settle(cell)
    assert not cell.arc_burning
    r = cell.readings()
    assert r.arc_current == 0.0
    assert r.arc_voltage > 40.0  # open-circuit voltage
    for _ in range(250):
        cell.step(DT)
    assert cell.temperature < hot - 1000.0


def test_tip_sticks_on_touch_and_is_freed_by_pulling_up_with_the_arc_off() -> None:
    cell = WeldCell(seed=5)
    go_to(cell, 100.0)
    weld_on(cell)
    track(cell, 100.0, 110.0)
    hot = cell.temperature
    x, y = cell.seam.centre(110.0)
    yaw = cell.seam.heading(110.0)
    cell.move_tip((x, y, -3.0), yaw)  # plunge into the plate
    settle_limit = cell.t + 2.0
    while not cell.tip_stuck:
        assert cell.t < settle_limit
        cell.step(DT)
    held = list(cell.joints)
    assert 0.0 <= cell.standoff <= 0.05
    r = cell.readings()
    assert r.arc_voltage == 0.0 and r.arc_current > 400.0
    # sideways does not free it, nor does pulling up with the power on
    cell.move_tip((x + 10.0, y, cell.standoff), yaw)
    for _ in range(20):
        cell.step(DT)
    cell.move_tip((x, y, 30.0), yaw)
    for _ in range(20):
        cell.step(DT)
    assert cell.tip_stuck and cell.joints == held
    assert cell.temperature < hot - 300.0  # the arc is out: temperature dips
    cell.set_voltage(0.0)
    cell.move_tip((x + 10.0, y, 0.5), yaw)
    for _ in range(20):
        cell.step(DT)
    assert cell.tip_stuck
    cell.move_tip((x, y, 30.0), yaw)
    cell.step(DT)
    assert not cell.tip_stuck
    settle(cell)
    assert cell.standoff == pytest.approx(30.0, abs=1e-6)


def test_touching_with_the_power_off_does_not_stick() -> None:
    cell = WeldCell()
    go_to(cell, 100.0, 5.0)
    x, y = cell.seam.centre(100.0)
    cell.move_tip((x, y, -2.0), cell.seam.heading(100.0))
    for _ in range(100):
        cell.step(DT)
    assert not cell.tip_stuck
    assert 0.0 <= cell.standoff <= 0.05  # the plate stops the torch
    cell.set_voltage(20.0)  # switching on while touching: the electrode freezes
    cell.step(DT)
    assert cell.tip_stuck and cell.readings().arc_voltage == 0.0


def test_gas_drains_while_the_valve_is_open() -> None:
    cfg = CellConfig()
    cell = WeldCell(cfg)
    for _ in range(100):
        cell.step(0.1)
    assert cell.bottle_pressure == cfg.bottle_pressure
    cell.set_gas_valve(True)
    for _ in range(100):
        cell.step(0.1)
    # 15 L/min for 10 s out of a 10 L bottle: 0.25 bar
    assert cfg.bottle_pressure - cell.bottle_pressure == pytest.approx(0.25, rel=1e-6)
    cell.set_gas_valve(False)
    cell.step(0.1)
    assert cell.readings().gas_flow == 0.0 and cell.readings().gas_line_pressure == 0.0


def test_flow_falls_off_as_the_bottle_runs_dry() -> None:
    cell = WeldCell(CellConfig(bottle_pressure=3.0, bottle_volume=2.0))
    cell.set_gas_valve(True)
    flows = []
    for _ in range(60):
        for _ in range(10):
            cell.step(0.1)
        flows.append(cell.gas_flow)
    assert flows[0] == pytest.approx(15.0)  # regulated while the bottle is above 2.5 bar
    assert all(a > b for a, b in itertools.pairwise(flows[5:]))
    # below the regulator pressure it decays with tau = V * p_reg / flow = 20 s
    assert flows[-1] == pytest.approx(15.0 * math.exp(-56.0 / 20.0), rel=0.05)
    assert cell.bottle_pressure < 0.2


def test_wire_feed_ramps_and_unwinds_the_spool() -> None:
    cell = WeldCell()
    cell.set_wire_speed(200.0)
    cell.step(0.1)
    assert cell.wire_speed == pytest.approx(100.0)  # 1000 mm/s^2
    for _ in range(99):
        cell.step(0.1)
    assert cell.wire_speed == pytest.approx(200.0)
    used = CellConfig().wire_spool - cell.readings().wire_remaining
    assert used == pytest.approx(0.1 * 0.1 + 0.2 * 9.9, rel=1e-9)  # m


def test_weld_record_and_quality_flags() -> None:
    cell = WeldCell()
    go_to(cell, 0.0)
    weld_on(cell)
    track(cell, 0.0, 100.0)
    cell.set_gas_valve(False)
    track(cell, 100.0, 130.0)
    cell.set_gas_valve(True)
    track(cell, 130.0, 160.0, speed=1.0)  # slow: too hot
    cell.set_voltage(0.0)
    track(cell, 160.0, 200.0)
    bins = cell.weld_bins()
    assert all(b & Flaw.WELDED for b in bins[:160])
    assert not any(b & Flaw.WELDED for b in bins[162:])
    assert bins[0] & Flaw.TOO_COLD  # the pool takes a moment to heat up
    assert bins[50] == Flaw.WELDED
    assert all(b & Flaw.NO_GAS for b in bins[102:129])
    assert not bins[50] & Flaw.NO_GAS
    assert any(b & Flaw.TOO_HOT for b in bins[135:160])
    p = cell.progress()
    assert p.welded == pytest.approx(160.0, abs=2.0)
    assert p.fraction == pytest.approx(160.0 / 300.0, abs=0.01)
    assert p.no_gas == pytest.approx(30.0, abs=2.0)
    assert p.good + p.flawed == p.welded and p.too_hot > 5.0


def test_linear_sensor_follows_the_tool() -> None:
    cell = WeldCell()
    go_to(cell, 0.0)
    r = cell.readings()
    assert r.start_marker and not r.end_marker
    assert r.range_mm == pytest.approx(10.0, abs=1e-6)
    go_to(cell, 150.0)
    r = cell.readings()
    assert not r.start_marker and sum(r.linear_pixels) in (3, 4, 5)
    go_to(cell, cell.seam.length - 3.0)
    assert cell.readings().end_marker


def test_deterministic_given_a_seed() -> None:
    def run(seed: int) -> list[tuple[float, ...]]:
        cell = WeldCell(seed=seed)
        go_to(cell, 10.0)
        weld_on(cell)
        out = []
        s = 10.0
        for _ in range(5):
            track(cell, s, s + 5.0)
            s += 5.0
            r = cell.readings()
            out.append((r.arc_temperature, r.arc_voltage, r.gas_flow, *r.joints))
        return out

    assert run(7) == run(7)
    assert run(7) != run(8)


def test_a_spiral_search_from_the_probable_start_finds_the_start_marker() -> None:
    cell = WeldCell()
    px, py = cell.seam.probable_start
    yaw = cell.seam.heading(0.0)  # the expected direction of the seam
    cell.move_tip((px, py, 10.0), yaw)
    settle(cell)
    assert not cell.readings().start_marker  # not visible from the probable start
    theta, found = 0.0, None
    while theta < 12 * math.pi:
        r = 5.0 * theta / (2 * math.pi)  # Archimedean spiral, 5 mm between turns
        theta += 2.5 / max(r, 2.5)  # about 2.5 mm of path per move
        x, y = px + r * math.cos(theta), py + r * math.sin(theta)
        cell.move_tip((x, y, 10.0), yaw)
        settle(cell)
        if cell.readings().start_marker:
            found = (x, y)
            break
    assert found is not None, "spiral search did not find the start marker"
    sx, sy = cell.seam.start
    # the detector (5 mm ahead of the tip) is over the 12 x 16 mm marker plate
    assert math.dist(found, (sx, sy)) < 16.0
    assert theta > 2 * math.pi  # it took more than one turn
