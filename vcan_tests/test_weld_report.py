"""The run as a picture: every run of the cell writes one self-contained HTML page beside its
map, and Chromium draws it (temperature along the seam against the band, position and phases
over time, the stand-off, faults and how they were handled, the assassin's reaction)."""

from __future__ import annotations

import io
import re
from pathlib import Path

from chcos.apps.weld.runner import run
from vcan_tests.support_view import browser_page


def test_the_run_report_is_written_beside_the_map_and_drawn(tmp_path: Path) -> None:
    out = io.StringIO()
    summary = run("direct", scenario="tip-stuck@s=120mm,intruder(for=1s)@t=75s",
                  workdir=tmp_path, out=out)
    page_file = tmp_path / "weld-report.html"
    assert summary["report"] == str(page_file) and (tmp_path / "sysfile.map").exists()
    assert f"the run as a picture: {page_file}" in out.getvalue()
    text = page_file.read_text(encoding="utf-8")
    assert "<script" not in text and "http" not in text.replace(
        'xmlns="http://www.w3.org/2000/svg"', "")  # self-contained
    with browser_page() as page:
        page.goto(page_file.as_uri())
        # three plots drawn, each with a real line of many points
        for cls in ("temp-plot", "pos-plot", "standoff-plot"):
            box = page.locator(f"svg.{cls}").bounding_box()
            assert box is not None and box["width"] > 500 and box["height"] > 200, (cls, box)
        d = page.locator("svg.temp-plot path.temp").get_attribute("d") or ""
        assert len(re.findall(r"[ML]", d)) > 100
        band = page.locator("svg.temp-plot rect.band").bounding_box()
        assert band is not None and band["height"] > 5
        assert page.locator("svg.pos-plot rect.phase").count() >= 4
        assert page.locator("svg.pos-plot line.fault").count() == 2
        faults = page.locator("ul.faults li").all_inner_texts()
        assert any("tip-stuck" in f for f in faults) and any("intruder" in f for f in faults)
        handled = " ".join(page.locator("ul.handled li").all_inner_texts())
        assert "E1 e-stop" in handled and "D3 alarm intruder" in handled
        figures = page.locator("table.figures").inner_text()
        assert "assassin reaction" in figures and " ms" in figures
        page.screenshot(path=str(tmp_path / "report.png"), full_page=True)
    assert (tmp_path / "report.png").stat().st_size > 10_000
