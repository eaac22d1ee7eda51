"""The welding cell's world model in use: C2's search plans (spiral, then a wider raster), the
plans' outcomes learned across runs beside the map, and every level's sensory messages going up."""

from __future__ import annotations

import json
from pathlib import Path

from vcan_tests.support_weldcell import run_job

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
    learned = json.loads((tmp_path / "learned" / "C2.json").read_text())
    assert learned["responses"]["find start of gap"]["spiral"][1] < \
        learned["responses"]["find start of gap"]["spiral"][0]
    assert all(t["abnormal"] == 0 for t in run.tasks.values()), run.tasks
