"""The thesis' section 6.4 cycle model reproduces its table (1150 / 2100 / 3075 interrupts/s)."""

from __future__ import annotations

import json

import pytest

from chcos.apps.bench import model64


def test_model_reproduces_the_thesis_table() -> None:
    rows = model64.table()
    assert [(r.per_cpu, r.total) for r in rows] == [(1150, 1150), (1050, 2100), (1025, 3075)]
    assert model64.clock_cycles() == model64.CPU_HZ - model64.CYCLES_LEFT
    assert rows[1].ratio_to_one == pytest.approx(2100 / 1150)


def test_remote_cost_bounds_are_the_only_costs_that_fit() -> None:
    lo, hi = model64.remote_cost_bounds()
    assert lo < model64.REMOTE_MESSAGE <= hi
    for cost, fits in ((lo - 50, False), ((lo + hi) / 2, True), (hi, True), (hi + 50, False)):
        totals = [r.total for r in model64.table(cost)]
        assert (totals == [1150, 2100, 3075]) is fits, cost


def test_cli_prints_assumptions_and_rows(capsys: pytest.CaptureFixture[str]) -> None:
    assert model64.main([]) == 0
    out = capsys.readouterr().out
    assert "A4" in out and "3,075" in out and "1.83x" in out
    assert model64.main(["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["total"] for r in doc["rows"]] == [1150, 2100, 3075]
