"""The welding cell's scenarios end to end: the appendix-2 hierarchy on the cell, virtual time.

Each test runs the whole job (E2: inspect, weld, go home) with one fault scenario, on the direct
binding and, parametrised, on the real buses (chcos.apps.weld.plant; see
support_weldcell.buses_or_skip).
Figures come from the cell model (ground truth) and from the tasks' world models.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from chcos.apps.weld.cell import Cell
from vcan_tests.support_weldcell import M, buses_or_skip, run_job

BINDINGS = ["direct", "buses"]
SAFE = {"drives_enable": 0.0, "volts_set": 0.0, "wire_set": 0.0, "gas_valve": 0.0}


def off(outputs: dict[str, Any]) -> bool:
    """Voltage, wire and gas are off (never switched on counts as off)."""
    return all(outputs[d] in (None, 0.0) for d in ("volts_set", "wire_set", "gas_valve"))


@pytest.mark.parametrize("binding", BINDINGS)
def test_good_gap_is_welded_start_to_end_in_band(binding: str, tmp_path: Path,
                                                 request: pytest.FixtureRequest) -> None:
    buses_or_skip(binding, always=True)
    # the direct run is the session's shared good-gap job (conftest.good_gap_job)
    run = (request.getfixturevalue("good_gap_job") if binding == "direct"
           else run_job(binding, "", tmp=tmp_path))
    assert run.outcome is not None and run.outcome["outcome"] == "welded", run.outcome
    assert run.outcome["inspection"]["inspection"] == "OK"
    s = run.summary
    assert s["welded_mm"] >= 0.99 * s["seam_mm"], s
    assert s["in_band_pct"] >= 95.0, s
    # the tip was hot for a minute, yet D3 raised nothing: its context (B1: weld on) said so
    assert run.worlds["D3"]["sensory"].get("alarms", []) == []
    assert max(run.worlds["D2"]["command"]["result"].speed_range) <= 10.0
    assert off(run.outputs) and run.model["volts"] == 0.0 and not run.model["gas"]
    home = run.outcome["home"]["at"]
    assert abs(home[2] - 250.0) < 1.0
    assert run.irq_errors == []
    assert all(t["abnormal"] == 0 for t in run.tasks.values()), run.tasks
    # the joint drives, on their side: enabled by the job (shutdown, switch on, enable
    # operation) and never anything else while it welded; the shutdown's safe stop then
    # brought each to SWITCH ON DISABLED through a quick stop (the master's disable voltage)
    welding = {p: states for p, states in run.drive_phases.items() if p.startswith("weld/")}
    assert welding and all(states == {"ENABLED"} for states in welding.values()), \
        run.drive_phases
    for name, d in run.drives.items():
        assert d["power"] == "ENABLED", (name, d)
        assert [cw for cw in d["received"] if cw][:3] == [0x06, 0x07, 0x0F], (name, d)
        assert run.drives_after[name]["power"] == "SWITCH_ON_DISABLED", run.drives_after[name]
        assert run.drives_after[name]["history"][-2:] == ["QUICK_STOP", "SWITCH_ON_DISABLED"]
        assert run.drives_after[name]["received"][-1] == 0x00
    assert run.outcome["drives"] == {f"joint{n}": "OPERATION_ENABLED" for n in range(1, 6)}


@pytest.mark.parametrize("binding", BINDINGS)
@pytest.mark.parametrize(("fault", "reason"), [("gap-wide@s=150mm", "too wide"),
                                               ("gap-narrow(width=0.8mm)@s=80mm", "too narrow")])
def test_bad_gap_fails_inspection_and_nothing_is_welded(binding: str, fault: str, reason: str,
                                                         tmp_path: Path) -> None:
    buses_or_skip(binding)
    run = run_job(binding, fault, tmp=tmp_path)
    assert run.outcome is not None
    assert run.outcome["outcome"] == "inspection failed"
    assert run.outcome["reason"] == reason
    where = float(fault.split("s=")[1].removesuffix("mm"))
    assert where - 10.0 <= run.outcome["inspection"]["at_mm"] <= where + 10.0
    assert run.summary["welded_mm"] == 0.0
    assert run.outputs["volts_set"] is None and run.outputs["gas_valve"] is None
    assert run.tasks["D2"]["activations"] == 0
    assert run.outcome["home"] is not None and "at" in run.outcome["home"]


@pytest.mark.parametrize("binding", BINDINGS)
def test_stuck_tip_is_freed_by_c1_and_welding_resumes(binding: str, tmp_path: Path) -> None:
    buses_or_skip(binding)
    run = run_job(binding, "tip-stuck@t=45s", tmp=tmp_path)
    assert ("tip-stuck" in [k for _, k, _ in run.model["events"]])
    assert run.outcome is not None and run.outcome["outcome"] == "welded", run.outcome
    assert run.outcome["weld"]["unstuck"] == 1
    stuck = run.worlds["A6"]["sensory"]["positions"]["stuck"]
    assert stuck.stopped and 40.0 < stuck.t < 50.0
    assert run.worlds["C1"]["command"]["unstick"] == "freed"
    assert run.summary["welded_mm"] >= 0.99 * run.summary["seam_mm"]
    assert run.summary["in_band_pct"] >= 95.0, run.summary
    assert not run.model["stuck"]


@pytest.mark.parametrize("binding", BINDINGS)
def test_empty_gas_bottle_stops_the_weld_and_reports_gas_fail(binding: str,
                                                             tmp_path: Path) -> None:
    buses_or_skip(binding)
    run = run_job(binding, "gas-empty@t=50s", tmp=tmp_path)
    assert run.outcome is not None and run.outcome["outcome"] == "weld failed"
    assert "gas fail: bottle empty" in run.outcome["reason"]
    assert "B1" in run.tasks and run.tasks["B1"]["abnormal"] == 1
    assert "GasFailure" in run.tasks["B1"]["last_error"]
    assert run.tasks["D2"]["abnormal"] == 1 and "gas fail" in run.tasks["D2"]["last_error"]
    s = run.summary
    assert 50.0 < s["welded_mm"] < 0.9 * s["seam_mm"]
    assert s["no_gas_mm"] <= 2.0  # the weld stopped within a millimetre or two of the gas
    assert off(run.outputs)
    assert run.model["volts"] == 0.0 and not run.model["gas"] and run.model["wire"] == 0.0
    assert run.worlds["B1"]["command"]["reason"].startswith("gas fail: bottle empty")


@pytest.mark.parametrize("binding", BINDINGS)
def test_intruder_puts_every_output_at_its_safe_value_within_5ms(binding: str,
                                                                tmp_path: Path) -> None:
    buses_or_skip(binding)

    def reaction_over(cell: Cell) -> dict[str, Any]:
        # the job ends at the alarm; E1 goes on (B2's stop waits for the drives' statuswords)
        cell.run(1.0, until_done=False)
        return {}

    run = run_job(binding, "intruder@t=40s", tmp=tmp_path, after=reaction_over)
    assert run.outcome is not None and run.outcome["outcome"] == "aborted"
    assert "intruder" in run.outcome["reason"]
    lat = run.summary["latency_s"]
    assert len(lat) == 1 and lat[0] is not None and lat[0] <= 0.005, lat
    assert {k: run.outputs[k] for k in SAFE} == SAFE
    assert run.model["volts"] == 0.0 and not run.model["gas"] and run.model["wire"] == 0.0
    if binding == "direct":
        assert run.model["enabled"] is False
    reaction = run.worlds["E1"]["sensory"]["reactions"][0]
    # the four safe values and the five joint drives' safe stops
    assert reaction["alarm"] == "intruder" and reaction["estop_writes"] == 9
    assert set(reaction["suspended"]) >= {"D1", "D2", "B1", "B4"}
    assert all(v == "normal completion" for v in reaction["b2"].values()), reaction["b2"]
    # the whole reaction (e-stop, B2 with A6's quick stops joining the drives' safe stops, A6's
    # memorized position) took 0.02 s of virtual time on both bindings (the drives answer within
    # their 10 ms cycles): a generous bound
    assert reaction["done"] - reaction["seen"] < 0.5, reaction
    # each joint drive, on its side: enabled while the job ran, then the e-stop's safe stop
    # (quick stop, then disable voltage once stopped: option 6 does not disable by itself);
    # A6's quick stop (through B2) joined it, nothing enabled it again
    assert {"ENABLED"} in [states for p, states in run.drive_phases.items()
                           if p.startswith(("inspect", "weld"))]
    for name, d in run.drives.items():
        assert d["power"] == "SWITCH_ON_DISABLED", (name, d)
        assert d["history"][-3:] == ["ENABLED", "QUICK_STOP", "SWITCH_ON_DISABLED"], (name, d)
        assert d["received"][-2:] == [0x02, 0x00], (name, d)
    assert all(run.devices[f"joint{n}"] == "OK" for n in range(1, 6))
    assert run.tasks["D2"]["frozen"]
    assert ("estop", "E1: intruder: light curtain broken") in run.events


@pytest.mark.parametrize("binding", BINDINGS)
def test_sensor_dropout_is_reported_and_the_cell_made_safe(binding: str,
                                                          tmp_path: Path) -> None:
    buses_or_skip(binding)
    run = run_job(binding, "sensor-dropout(arc_temperature)@t=45s", tmp=tmp_path)
    assert run.outcome is not None and run.outcome["outcome"] == "aborted"
    assert "sensor failure: arc_temp" in run.outcome["reason"]
    alarms = run.worlds["D3"]["sensory"]["alarms"]
    assert [a["alarm"] for a in alarms] == ["sensor failure"]
    assert 45.0 < alarms[0]["t"] < 45.5
    assert run.devices["arc_temp"] in ("stale", "failed")
    assert {k: run.outputs[k] for k in SAFE} == SAFE
    assert run.model["volts"] == 0.0 and not run.model["gas"]


@pytest.mark.parametrize("binding", BINDINGS)
def test_a_task_that_raises_mid_weld_is_contained_and_reported(binding: str,
                                                              tmp_path: Path) -> None:
    buses_or_skip(binding)

    def intruder_afterwards(cell: Cell) -> dict[str, Any]:
        # the rest of the system runs on: the exception path still answers afterwards
        cell.inject("intruder(for=0.5s)")
        cell.run(1.0, until_done=False)
        return {"reactions": cell.world("E1")["sensory"].get("reactions", [])}

    run = run_job(binding, "", replace={"B4": f"{M}:faulty_b4"}, after=intruder_afterwards,
                  tmp=tmp_path)
    assert run.outcome is not None and run.outcome["outcome"] == "weld failed", run.outcome
    assert "B4 failed: RuntimeError: injected fault in B4" in run.outcome["reason"]
    assert run.tasks["B4"]["abnormal"] == 1
    assert run.tasks["D2"]["abnormal"] == 1
    s = run.summary
    assert 30.0 < s["welded_mm"] < 0.8 * s["seam_mm"]
    assert run.outcome["home"] is not None and "at" in run.outcome["home"]  # B3 still works
    assert off(run.outputs) and run.model["volts"] == 0.0
    assert run.irq_errors == []
    assert [r["alarm"] for r in run.extra["reactions"]] == ["intruder"]
