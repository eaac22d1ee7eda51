"""The welding cell's world model in use: C2's search plans (spiral, then a wider raster), the
plans' outcomes learned across runs beside the map, and every level's sensory messages going up."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from vcan_tests.support_weldcell import JobRun, buses_or_skip, run_job

TRUE_START = (550.0, -150.0)


def test_first_search_fails_and_the_gap_is_welded_with_the_second_plan(tmp_path: Path) -> None:
    # told the gap starts 40 mm to the side: the spiral (30 mm) cannot see it, the raster can
    far = {"start": [TRUE_START[0] + 40.0, TRUE_START[1] - 10.0]}
    run = run_job("direct", "", command=far, tmp=tmp_path, limit=240.0)
    assert run.outcome is not None and run.outcome["outcome"] == "welded", run.outcome
    assert run.summary["welded_mm"] >= 0.99 * run.summary["seam_mm"]
    plans = run.worlds["C2"]["command"]["plans"]
    assert [(p["plan"], p["ok"]) for p in plans][:2] == [("spiral", False), ("raster", True)]
    assert "no start-of-gap marker within 30 mm" in plans[0]["error"]
    assert any(h.startswith("C2: plan spiral failed") for h in run.summary["handled"])
    learned = json.loads((tmp_path / "learned" / "C2.json").read_text())
    assert learned["responses"]["find start of gap"]["spiral"][1] < \
        learned["responses"]["find start of gap"]["spiral"][0]
    assert all(t["abnormal"] == 0 for t in run.tasks.values()), run.tasks


def test_good_gap_sends_sensory_results_up_from_every_level(good_gap_job: JobRun) -> None:
    run = good_gap_job  # the session's good-gap job, direct binding (conftest.good_gap_job)
    assert run.outcome is not None and run.outcome["outcome"] == "welded", run.outcome
    msgs = run.summary["messages"]
    for level in (1, 2, 3, 4):
        assert msgs.get(f"level {level} up", 0) > 0, msgs
    sent = run.extra["sent"]
    # B5.s (level 2), C2.s (level 3) reach the exception task; D1.s, D2.s reach the job
    assert sent["B5->D3"] >= 4 and sent["C2->D3"] >= 2, sent
    assert sent["D1->E2"] >= 10 and sent["D2->E2"] >= 10, sent
    # D2's temperature comparison is its world model's error vector against its prediction
    assert run.worlds["D2"]["sensory"]["cmp"] in ("above", "equal", "below")


@pytest.mark.parametrize("binding", ["direct", "buses"])
def test_wire_empty_stops_the_weld_and_is_reported(binding: str, tmp_path: Path) -> None:
    buses_or_skip(binding)
    # the spool runs out during the weld (the inspection is over by t=30 s)
    run = run_job(binding, "wire-empty@t=45s", tmp=tmp_path)
    assert run.outcome is not None and run.outcome["outcome"] == "weld failed", run.outcome
    assert "wire fail: electrode supply empty" in run.outcome["reason"]
    assert 10.0 <= run.summary["welded_mm"] <= run.summary["seam_mm"] - 20.0, run.summary
    assert "wire fail" in run.worlds["B1"]["command"]["reason"]  # then D2 turned it off
    assert any("B1" in h and "wire fail" in h for h in run.summary["handled"]), \
        run.summary["handled"]
    assert run.model["volts"] == 0.0 and not run.model["gas"] and run.model["wire"] == 0.0


def test_a_failed_supply_sensor_is_reported_and_the_cell_made_safe(tmp_path: Path) -> None:
    run = run_job("direct", "sensor-dropout(wire_remaining)@t=45s", tmp=tmp_path)
    assert run.outcome is not None and run.outcome["outcome"] != "welded", run.outcome
    alarms = run.worlds["D3"]["sensory"].get("alarms", [])
    assert any(a["alarm"] == "sensor failure" and "wire_left" in a["detail"] for a in alarms), \
        alarms
    assert run.devices["wire_left"] == "failed" or run.devices["wire_left"] == "stale", \
        run.devices
    assert run.model["volts"] == 0.0 and not run.model["gas"]
