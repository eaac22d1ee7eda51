"""The NBS baseline (Appendix 1's H1-H3 with their G/M modules) on the welding cell: it inspects
the good gap, names the table row where welding fails, puts the actuators safe on an intruder
within one 28 ms cycle, and prints side by side with the CHC job (virtual time)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from chcos.apps.nbs.weldcell import NBS_SCRIPT, NbsCell
from chcos.apps.weld.cell import open_cell
from chcos.apps.weld.runner import main as weld_main
from vcan_tests.support_view import browser_page


def test_good_gap_direct_inspects_then_names_the_failing_row() -> None:
    with open_cell("direct", script=NBS_SCRIPT) as cell:
        nbs = NbsCell(cell)
        nbs.start_job()
        nbs.run(110.0)
        s = nbs.summary()
        assert not any(t.name in ("A4", "D2", "E2") for t in cell.system.tsktab)  # no CHC job
    # the inspection followed the whole seam (the end marker was reached) and went home
    assert [name for _, name in nbs.job] == ["INSPECT GAP", "WELD GAP"]
    assert nbs.job[1][0] > 50.0
    if s["outcome"] is not None and s["outcome"]["outcome"] == "welded":
        assert s["welded_mm"] > 0.9 * s["seam_mm"]
        return
    # or the summary names the row exactly: the arc struck, the pool had not reached the
    # threshold yet, so neither row 1 (arc off) nor row 2 (temp >= threshold) held
    first = s["failures"][0]
    assert re.search(r"H1 TURN ON ARC row 3 \(state 1 -> 0, lower CUT VOLTAGE, up 'arc fail'\)",
                     first), first
    assert "because no earlier row held (row 1 needs arc off; row 2 needs temp >= threshold)" \
        in first, first
    assert "arc on" in first.split("true:")[1]
    temp = float(re.search(r"temp=([0-9.]+)", first).group(1))  # type: ignore[union-attr]
    assert temp < 1450.0
    assert s["welded_mm"] < 0.1 * s["seam_mm"]
    assert any("H3 WELD GAP" in line for line in s["standing"])


def test_intruder_puts_the_actuators_safe_within_one_cycle() -> None:
    with open_cell("direct", scenario="intruder(for=1s)@t=5s", script=NBS_SCRIPT) as cell:
        nbs = NbsCell(cell)
        nbs.start_job()
        nbs.run(4.9)
        assert cell.outputs()["drives_enable"] == 1  # the inspection is moving the arm
        # on the CiA 402 joint drives, enabled by MOTORS ON (their side of it)
        assert [d.power.name for d in cell.drives] == ["ENABLED"] * 5
        assert all(d.received[:3] == [0x06, 0x07, 0x0F] for d in cell.drives)
        nbs.run(0.6)
        out = cell.outputs()
        assert (out["drives_enable"], out["volts_set"], out["wire_set"], out["gas_valve"]) == (
            0, 0.0, 0.0, 0)
        assert cell.system.devtab.get("intruder").value == 1  # still broken: held safe
        lat = nbs.summary()["latency_s"]
    assert len(lat) == 1 and lat[0] is not None
    assert 0.0 <= lat[0] <= 0.028 + 1e-6  # polled by G1 every 28 ms cycle


def test_hierarchy_nbs_prints_both_side_by_side(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    rc = weld_main(["--hierarchy", "nbs", "--binding", "direct", "--duration", "12",
                    "--scenario", "intruder(for=1s)@t=6s", "--workdir", str(tmp_path)])
    out = capsys.readouterr().out
    assert rc == 1  # the NBS job does not finish in 12 s
    table = out[out.index("side by side"):]
    header = table.splitlines()[1].split()
    assert header == ["CHC", "NBS"]
    for row in ("level 1 executions/s", "level 3 executions/s", "messages in all",
                "intruder -> safe", "weld length", "in band"):
        line = next(x for x in table.splitlines() if x.strip().startswith(row))
        assert len(re.findall(r"\d+", line[len(row) + 2:])) >= 2, line
    lat = re.search(r"intruder -> safe\s+([0-9.]+) ms\s+([0-9.]+) ms", table)
    assert lat is not None and float(lat.group(2)) <= 28.0, table
    nbs_rate = re.search(r"level 1 executions/s\s+\d+/s\s+(\d+)/s", table)
    assert nbs_rate is not None and int(nbs_rate.group(1)) == pytest.approx(3 / 0.028, abs=2)
    assert (tmp_path / "weld-report.html").is_file()
    assert (tmp_path / "weld-report-nbs.html").is_file()
    assert "NBS" in (tmp_path / "weld-report-nbs.html").read_text(encoding="utf-8")
    # the NBS report is the same drawing as the CHC one, with NBS's phases and reflex
    with browser_page() as page:
        page.goto((tmp_path / "weld-report-nbs.html").as_uri())
        for cls in ("temp-plot", "pos-plot", "standoff-plot"):
            box = page.locator(f"svg.{cls}").bounding_box()
            assert box is not None and box["width"] > 500 and box["height"] > 200, (cls, box)
        assert page.locator("svg.pos-plot rect.phase").count() >= 2
        handled = " ".join(page.locator("ul.handled li").all_inner_texts())
        assert "G1 reflex: intruder -> safe values" in handled
