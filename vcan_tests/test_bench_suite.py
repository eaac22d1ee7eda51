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


def test_instruction_counts_split_each_program_by_where_its_code_lives() -> None:
    """The full-path benchmark's counted figure: every thread is traced (chcos' reader and
    kernel threads, the peer's listener), only the exchange counts (not the set-up), and the
    same run counted twice gives (nearly) the same figure."""
    from tools import bench_fullpath as fp

    raw = [fp.count_instructions(lambda k, i=i: fp.raw_rate(k, f"ops-test-raw-{i}"), 200)
           for i in range(2)]
    # the same up to one-off work (a first call's lazy set-up): within 1 %
    assert abs(sum(raw[0].values()) - sum(raw[1].values())) <= 0.01 * sum(raw[1].values())
    assert raw[0]["python-can"] == raw[1]["python-can"]
    assert raw[0]["python-can"] > 300 and "chcos" not in raw[0]
    path = fp.count_instructions(lambda k: fp.full_path(k, 8, "ops-test-path"), 200)
    # chcos' own code runs on its reader and kernel threads: counted only if they are traced
    assert path["chcos"] > 300
    assert path["python-can"] > 2 * raw[0]["python-can"] * 0.8   # two frames per loop
    # the set-up (System, install, start) is left out: a few thousand instructions per loop
    # if it were counted at 200 loops
    assert sum(path.values()) < 6 * sum(raw[0].values())
    text = fp.instruction_text({"raw": raw[0], "chcos": path, "asyncio_cantools": path})
    assert "chcos/program 1.00" in text


def test_a_full_path_batch_takes_its_ratios_round_by_round() -> None:
    """paired_batch runs every program once per round, and a ratio is the median of the
    rounds' own ratios (not the ratio of the medians); chcos answered every frame it got."""
    import statistics

    from tools import bench_fullpath as fp

    b = fp.paired_batch(90, window=8, pairs=3, tag=f"pair-test-{id(fp)}",
                        programs=fp.PROGRAMS)
    assert {p: len(r) for p, r in b.rates.items()} == {p: 3 for p in fp.PROGRAMS}
    assert set(b.cpu) == set(fp.PROGRAMS) - {"raw"} and all(len(c) == 3 for c in b.cpu.values())
    assert all(r > 0 for rates in b.rates.values() for r in rates)
    rounds = [c / r for c, r in zip(b.rates["chcos"], b.rates["raw"], strict=True)]
    assert b.ratio("chcos", "raw") == statistics.median(rounds)
    assert b.rate("asyncio_bytes") == statistics.median(b.rates["asyncio_bytes"])
    assert b.sent[0] == 90 and 0 <= b.sent[1] <= 90
