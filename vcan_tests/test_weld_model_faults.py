"""Fault injection: scenario parsing (string and TOML), and faults firing at their time/position."""

from __future__ import annotations

import pytest

from chcos.apps.weld.faults import (
    AtSeam,
    AtTime,
    Fault,
    Immediate,
    Scenario,
    parse_fault,
    parse_scenario,
    parse_scenario_toml,
    scenario_from_table,
)
from chcos.apps.weld.model import WeldCell
from chcos.errors import ConfigError

DT = 0.05


def go_to(cell: WeldCell, s: float, standoff: float = 10.0) -> None:
    x, y = cell.seam.centre(s)
    cell.move_tip((x, y, cell.seam.plate_z + standoff), cell.seam.heading(s))
    end = cell.t + 20.0
    while max(abs(a - b) for a, b in zip(cell.joints, cell.targets, strict=True)) > 1e-12:
        assert cell.t < end
        cell.step(DT)


def run_until(cell: WeldCell, t: float) -> None:
    while cell.t < t - 1e-9:
        cell.step(DT)


# --- parsing ------------------------------------------------------------------------------------


def test_parse_the_example_scenario() -> None:
    sc = parse_scenario("tip-stuck@s=120mm,intruder@t=8s")
    assert sc.faults == (
        Fault("tip-stuck", AtSeam(120.0)),
        Fault("intruder", AtTime(8.0)),
    )


@pytest.mark.parametrize(
    ("text", "fault"),
    [
        ("gas-empty", Fault("gas-empty", Immediate())),
        ("gas-empty@now", Fault("gas-empty", Immediate())),
        ("intruder(for=2s)@t=1500ms", Fault("intruder", AtTime(1.5), duration=2.0)),
        (
            "sensor-dropout(arc_temperature;for=1.5s)@t=3",
            Fault("sensor-dropout", AtTime(3.0), duration=1.5, sensor="arc_temperature"),
        ),
        (
            " servo-timeout(joint=2, for=500ms) @ t=1s ",
            Fault("servo-timeout", AtTime(1.0), duration=0.5, joint=2),
        ),
        (
            "gap-wide(width=4.5mm;length=3cm)@s=150",
            Fault("gap-wide", AtSeam(150.0), width=4.5, length=30.0),
        ),
        ("gap-narrow@s=0.1m", Fault("gap-narrow", AtSeam(100.0), width=0.8)),
        ("gap-wide@t=2s", Fault("gap-wide", AtTime(2.0), width=4.0)),
    ],
)
def test_parse_faults(text: str, fault: Fault) -> None:
    assert parse_fault(text) == fault
    assert parse_scenario(text).faults == (fault,)
    # and the canonical description parses back to the same fault
    assert parse_fault(fault.describe()) == fault


def test_parameters_with_commas_inside_parentheses_are_one_item() -> None:
    sc = parse_scenario("servo-timeout(joint=3,for=1s)@t=2s,gas-empty@t=4s")
    assert [f.kind for f in sc.faults] == ["servo-timeout", "gas-empty"]
    assert parse_scenario(sc.describe()) == sc
    assert parse_scenario("   ") == Scenario()


@pytest.mark.parametrize(
    ("text", "token"),
    [
        ("tip-stuk@s=120mm", "'tip-stuk'"),
        ("tip-stuck@x=120mm", "'x=120mm'"),
        ("intruder@t=8h", "'8h'"),
        ("intruder@s=twelve", "'twelve'"),
        ("sensor-dropout(thermometer)", "'thermometer'"),
        ("sensor-dropout(for=1s)", "needs a sensor"),
        ("servo-timeout(joint=7)", "'7'"),
        ("tip-stuck(width=3mm)", "'width'"),
        ("gap-wide(width=abc)", "'abc'"),
        ("gap-wide(width=-1mm)", "width"),
        ("gap-wide(length=0mm)", "length"),
        ("intruder(for=0s)", "for=0"),
        ("intruder(2s)", "'2s'"),
        ("gap-wide(width=3mm", "unclosed"),
        ("gap-wide)@t=1s", "unbalanced"),
        ("intruder,,gas-empty", "empty item"),
        ("servo-timeout(joint=1;joint=2)", "given twice"),
        ("@t=1s", "empty fault kind"),
        ("intruder@t=-1s", "t=-1.0"),
    ],
)
def test_scenario_errors_name_the_bad_token(text: str, token: str) -> None:
    with pytest.raises(ConfigError) as info:
        parse_scenario(text)
    assert token in str(info.value)


TOML = """
[[fault]]
kind = "tip-stuck"
s = 120           # mm

[[fault]]
kind = "intruder"
t = "8s"
for = 2.5         # s

[[fault]]
kind = "sensor-dropout"
sensor = "gas_flow"
t = 1.0

[[fault]]
kind = "gap-narrow"
width = "0.5mm"
"""


def test_parse_toml_scenario() -> None:
    sc = parse_scenario_toml(TOML)
    assert sc.faults == (
        Fault("tip-stuck", AtSeam(120.0)),
        Fault("intruder", AtTime(8.0), duration=2.5),
        Fault("sensor-dropout", AtTime(1.0), sensor="gas_flow"),
        Fault("gap-narrow", Immediate(), width=0.5),
    )
    assert scenario_from_table({}) == Scenario()


@pytest.mark.parametrize(
    ("table", "token"),
    [
        ({"faults": []}, "faults"),
        ({"fault": "tip-stuck"}, "array of tables"),
        ({"fault": [{"t": 1}]}, "fault[0]: missing or non-string 'kind'"),
        ({"fault": [{"kind": "gas-empty"}, {"kind": "gas-leak"}]}, "fault[1]: unknown fault kind"),
        ({"fault": [{"kind": "gas-empty", "t": 1, "s": 2}]}, "both 't' and 's'"),
        ({"fault": [{"kind": "gas-empty", "t": True}]}, "t=True"),
        ({"fault": [{"kind": "intruder", "for": "soon"}]}, "'soon'"),
        ({"fault": [{"kind": "intruder", "joint": 1}]}, "'joint'"),
        ({"fault": [3]}, "fault[0] is 3"),
    ],
)
def test_toml_table_errors(table: dict[str, object], token: str) -> None:
    with pytest.raises(ConfigError) as info:
        scenario_from_table(table, "cell.toml")
    assert "cell.toml" in str(info.value) and token in str(info.value)


def test_invalid_toml_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match=r"weird\.toml: invalid TOML"):
        parse_scenario_toml("[[fault]\nkind=", "weird.toml")


def test_fault_constructor_validates() -> None:
    with pytest.raises(ConfigError, match="sensor"):
        Fault("sensor-dropout")
    with pytest.raises(ConfigError, match="joint"):
        Fault("servo-timeout", joint=0)
    with pytest.raises(ConfigError, match="kind"):
        Fault("meteor")  # type: ignore[arg-type]


# --- firing -------------------------------------------------------------------------------------


def test_intruder_fires_at_its_time_and_clears_after_its_duration() -> None:
    cell = WeldCell(scenario=parse_scenario("intruder(for=2s)@t=8s"))
    run_until(cell, 7.95)
    assert not cell.readings().intruder and cell.pending
    cell.step(DT)
    assert cell.t == pytest.approx(8.0) and cell.readings().intruder
    assert not cell.pending
    run_until(cell, 9.95)
    assert cell.readings().intruder
    cell.step(DT)
    assert not cell.readings().intruder
    assert [(round(e.t, 6), e.action) for e in cell.events] == [(8.0, "fired"), (10.0, "cleared")]


def test_manual_intruder_and_clearing_a_permanent_intruder_fault() -> None:
    cell = WeldCell(scenario=parse_scenario("intruder"))
    assert cell.readings().intruder  # immediate
    run_until(cell, 5.0)
    assert cell.readings().intruder
    cell.set_intruder(False)
    cell.step(DT)
    assert not cell.readings().intruder
    assert [e.action for e in cell.events] == ["fired", "cleared"]


def test_tip_stuck_fires_at_its_seam_position() -> None:
    cell = WeldCell(scenario=parse_scenario("tip-stuck@s=120mm"))
    go_to(cell, 100.0)
    cell.set_voltage(24.0)
    cell.set_gas_valve(True)
    s = 100.0
    while not cell.tip_stuck:
        assert s < 140.0, "tip-stuck never fired"
        s += 5.0 * DT
        x, y = cell.seam.centre(s)
        cell.move_tip((x, y, 10.0), cell.seam.heading(s))
        cell.step(DT)
    assert cell.seam_point.s == pytest.approx(120.0, abs=0.3)
    r = cell.readings()
    assert r.arc_voltage == 0.0 and not cell.arc_burning
    held = list(cell.joints)
    cell.step(DT)
    assert cell.joints == held


def test_gap_fault_at_a_seam_position_is_a_plate_defect_from_the_start() -> None:
    cell = WeldCell(scenario=parse_scenario("gap-wide@s=150mm,gap-narrow(width=0.6mm)@s=200mm"))
    assert cell.seam.width(160.0) == 4.0 and cell.seam.width(210.0) == 0.6
    assert cell.seam.width(175.0) == pytest.approx(cell.seam.width(176.0), abs=0.01)
    assert [e.t for e in cell.events] == [0.0, 0.0]
    go_to(cell, 160.0)
    wide = sum(cell.readings().linear_pixels)
    go_to(cell, 140.0)
    normal = sum(cell.readings().linear_pixels)
    assert wide >= normal + 3  # 4 mm at 0.5 mm per pixel vs about 2 mm


def test_gap_fault_in_time_starts_under_the_tip() -> None:
    cell = WeldCell(scenario=parse_scenario("gap-narrow(length=10mm)@t=1s"))
    go_to(cell, 80.0)
    assert cell.t < 1.0 and cell.events == [] and cell.seam.width(85.0) > 2.0
    run_until(cell, 1.0)
    (override,) = cell.seam.overrides
    assert override.s_from == pytest.approx(80.0, abs=1e-6)
    assert override.s_to == pytest.approx(90.0, abs=1e-6)
    assert cell.seam.width(85.0) == 0.8 and cell.seam.width(95.0) > 2.0
    assert [e.fault.kind for e in cell.events] == ["gap-narrow"]


def test_gas_empty_at_time() -> None:
    cell = WeldCell(scenario=parse_scenario("gas-empty@t=2s"))
    cell.set_gas_valve(True)
    run_until(cell, 1.0)
    assert cell.readings().gas_flow == pytest.approx(15.0, abs=0.5)
    run_until(cell, 2.0)
    r = cell.readings()
    assert r.gas_bottle_pressure == 0.0 and r.gas_flow == 0.0 and r.gas_line_pressure == 0.0


def test_sensor_dropout_freezes_the_reported_value_then_resumes() -> None:
    cell = WeldCell(seed=2, scenario=parse_scenario("sensor-dropout(arc_temperature;for=1s)@t=1s"))
    run_until(cell, 0.95)
    assert cell.readings().silent == frozenset()
    cell.step(DT)
    r1 = cell.readings()
    assert r1.silent == frozenset({"arc_temperature"})
    run_until(cell, 1.5)
    r2 = cell.readings()
    assert r2.arc_temperature == r1.arc_temperature  # stops reporting: the value is held
    assert r2.joints != r1.joints  # the others still report (fresh noise every step)
    run_until(cell, 2.0)
    r3 = cell.readings()
    assert r3.silent == frozenset() and r3.arc_temperature != r1.arc_temperature
    assert [(round(e.t, 6), e.action) for e in cell.events] == [(1.0, "fired"), (2.0, "cleared")]


def test_linear_sensor_dropout_holds_pixels_and_range() -> None:
    cell = WeldCell()
    go_to(cell, 0.0)
    cell.inject(Fault("sensor-dropout", sensor="linear_sensor"))
    before = cell.readings()
    go_to(cell, 150.0, 20.0)
    after = cell.readings()
    assert after.linear_pixels == before.linear_pixels and after.range_mm == before.range_mm
    assert cell.linear_view().range_mm == pytest.approx(20.0)


def test_servo_timeout_freezes_the_joint_and_silences_it() -> None:
    cell = WeldCell(scenario=parse_scenario("servo-timeout(joint=1;for=1s)@t=0.5s"))
    start = cell.joints[0]
    cell.set_joint_speed(1, 0.2)
    cell.set_joint_target(1, start + 1.0)
    run_until(cell, 0.5)
    moved = cell.joints[0]
    assert moved == pytest.approx(start + 0.1)
    r = cell.readings()
    assert r.servo_ok == (False, True, True, True, True) and "joint1" in r.silent
    reported = r.joints[0]
    run_until(cell, 1.45)
    assert cell.joints[0] == moved and cell.readings().joints[0] == reported
    run_until(cell, 2.0)
    assert cell.readings().servo_ok[0] and cell.joints[0] > moved


def test_pending_faults_and_immediate_injection() -> None:
    cell = WeldCell()
    cell.inject(Fault("tip-stuck", AtTime(3.0)))
    assert cell.pending == (Fault("tip-stuck", AtTime(3.0)),)
    cell.inject(Fault("gas-empty"))
    assert cell.bottle_pressure == 0.0
    run_until(cell, 3.0)
    assert cell.tip_stuck and not cell.pending
