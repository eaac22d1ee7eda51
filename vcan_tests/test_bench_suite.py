"""Tests of tools/bench_suite.py's own logic: the min/median/max cells, the Markdown table and
the README update between its markers (the measurements themselves are benchmarks, not tests)."""

from __future__ import annotations

from pathlib import Path

import pytest

from tools import bench_suite
from tools.suite_common import ROOT, SuiteRun, spread
from tools.suite_sections import cycle_model


def test_spread_is_min_median_max() -> None:
    assert spread([3.0, 1.0, 2.0]) == "1.00 / 2.00 / 3.00"
    assert spread([5.0, 1.0, 2.0, 100.0], "{:.1f}") == "1.0 / 3.5 / 100.0"
    assert spread([0.5]) == "0.50"


def _run(tmp_path: Path) -> SuiteRun:
    return SuiteRun(quick=True, reps=3, seed=1, out=tmp_path, soak_s=1.0, saturated_s=1.0)


def test_cycle_model_rows_reproduce_the_thesis_table(tmp_path: Path) -> None:
    run = _run(tmp_path)
    cycle_model(run)
    assert [r[3] for r in run.rows] == ["yes", "yes", "yes"]
    assert "3,075 total" in run.rows[2][2]


def test_markdown_escapes_pipes_and_names_the_conditions(tmp_path: Path) -> None:
    run = _run(tmp_path)
    info = {"date": "2026-11-24 01:00 UTC", "cpu": "X", "cores_allowed": 2, "python": "3.11",
            "python_can": "4.6", "loadavg_start": 0.5, "loadavg_end": 0.7}
    md = bench_suite.markdown([("a | b", "t", "1 / 2 / 3", "yes")], info, run, 600.0)
    assert "| a \\| b | t | 1 / 2 / 3 | yes |" in md
    assert "min / median / max of 3 batches" in md
    assert "load average 0.50 at the start, 0.70 at the end" in md


def test_update_readme_replaces_only_between_the_markers(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{bench_suite.BEGIN}\nold table\n{bench_suite.END}\nnotes\n",
                      encoding="utf-8")
    bench_suite.update_readme(readme, "new table\n")
    assert readme.read_text(encoding="utf-8") == (
        f"intro\n{bench_suite.BEGIN}\nnew table\n{bench_suite.END}\nnotes\n")


def test_update_readme_without_markers_names_them_and_leaves_the_file(tmp_path: Path) -> None:
    readme = tmp_path / "README.md"
    readme.write_text("no markers here\n", encoding="utf-8")
    with pytest.raises(SystemExit, match="bench_suite table: begin"):
        bench_suite.update_readme(readme, "x")
    assert readme.read_text(encoding="utf-8") == "no markers here\n"


def test_the_readme_has_the_markers() -> None:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert text.count(bench_suite.BEGIN) == 1 and text.count(bench_suite.END) == 1
    assert text.index(bench_suite.BEGIN) < text.index(bench_suite.END)


def test_only_one_section_writes_the_files(tmp_path: Path) -> None:
    assert bench_suite.main(["--quick", "--only", "6.4 cycle model", "--out",
                             str(tmp_path)]) == 0
    assert "6.4 cycle model computed" in (tmp_path / "table.md").read_text(encoding="utf-8")
    assert (tmp_path / "results.json").exists()
