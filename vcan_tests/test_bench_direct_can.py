"""tools.bench_direct_can runs every section on both buses and prints their ratios (a smoke run
with few frames: no figure is judged)."""

from __future__ import annotations

import pytest

from tools import bench_direct_can


def test_the_benchmark_runs_each_section_on_both_buses(capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_direct_can.main(["--frames", "300", "--repeat", "1"]) == 0
    out = capsys.readouterr().out
    for title, _fn in bench_direct_can.SECTIONS:
        rows = [line for line in out.splitlines() if line.startswith(title)]
        assert [r.split()[-4] for r in rows] == ["virtual", "chcos-direct"], out
        assert rows[0].endswith("1.00x")
