"""The map drawn by level: layout, SVG (no graphviz), dot, text, and ``chcos map``."""

from __future__ import annotations

import io
import itertools
import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest

from chcos.system import sysmap
from chcos.system.textview import render_text
from chcos.viewer import ViewerError
from chcos.viewer.cli import map_main
from chcos.viewer.graph import COMMAND_COLOR, SENSORY_COLOR, Live, render_dot, render_svg
from chcos.viewer.layout import check_doc, layout, link_key
from vcan_tests.support_view import FIG65_TASKS, fig65_system

SVG = "{http://www.w3.org/2000/svg}"


@pytest.fixture
def fig65_map(tmp_path: Path) -> Path:
    """A sysfile.map of the figure 6.5 system after 2 s of virtual time."""
    s = fig65_system(tmp_path)
    try:
        s.run_for(2.0)
        s.sysmgr.save_map()
    finally:
        s.shutdown()
    return tmp_path / "sysfile.map"


def _groups(root: ET.Element, cls: str) -> list[ET.Element]:
    return [g for g in root.iter(f"{SVG}g") if cls in (g.get("class") or "").split()]


def test_layout_rows_by_level_devices_at_zero(fig65_map: Path) -> None:
    lay = layout(sysmap.read(fig65_map))
    levels = [row[0].level for row in lay.rows]
    assert levels == [3, 2, 1, 0]
    assert {n.name for n in lay.rows[0]} == {"C1"}
    assert {n.name for n in lay.rows[1]} == {"B1", "B2"}
    assert {n.name for n in lay.rows[3]} >= {"S1", "S2", "S3", "M1", "M2", "./testfile"}
    ys = {lv: lay.rows[i][0].y for i, lv in enumerate(levels)}
    assert ys[3] < ys[2] < ys[1] < ys[0]
    for row in lay.rows:  # no overlapping boxes within a row
        xs = [n.x for n in row]
        assert all(b - a >= 140 for a, b in itertools.pairwise(xs))
    assert lay.width >= max(n.x for n in lay.nodes.values()) + 70


def test_layout_keeps_children_under_parents(fig65_map: Path) -> None:
    lay = layout(sysmap.read(fig65_map))
    x = {n.name: n.x for n in lay.nodes.values()}
    # S1, S2 and M1 belong to A1, S3 and M2 to A2: the barycentre order keeps them apart
    assert max(x["S1"], x["S2"], x["M1"]) < min(x["S3"], x["M2"])
    assert (x["A1"] < x["A2"]) == (x["S1"] < x["S3"])


def test_svg_shows_every_task_and_direction_by_type(fig65_map: Path) -> None:
    doc = sysmap.read(fig65_map)
    root = ET.fromstring(render_svg(doc))
    nodes = {g.get("data-name"): g for g in _groups(root, "node")}
    assert set(FIG65_TASKS) <= set(nodes)
    assert {"S1", "S2", "S3", "M1", "M2"} <= set(nodes)
    links = _groups(root, "link")
    explicit = [lk for lk in doc["links"] if not lk["implicit"]]
    assert len(links) == len(explicit)
    for g in links:
        path = g.find(f"{SVG}path")
        assert path is not None
        d = (path.get("d") or "").replace("M", "").replace("C", "").split()
        y1 = float(d[0].split(",")[1])
        y2 = float(d[-1].split(",")[1])
        if g.get("data-type") == "sensory":
            assert y2 < y1, g.get("data-link")  # drawn up
            assert path.get("stroke") == SENSORY_COLOR
        else:
            assert y2 > y1, g.get("data-link")  # drawn down
            assert path.get("stroke") == COMMAND_COLOR
    c1b1 = next(g for g in links if g.get("data-link") == "C1/B1")
    prio = next(t for t in c1b1.iter(f"{SVG}tspan") if t.get("class") == "prio")
    assert prio.text == "p9"  # setpri -9 C1 B1 of the install script


def test_svg_live_overlay_rates_ages_marks(fig65_map: Path) -> None:
    doc = sysmap.read(fig65_map)
    doc["devices"][0]["status"] = "stale"
    live = Live({"S1/A1:sensory": 10.0}, {"S2": 0.25}, {"B2": ("suspend", "host suspend B2")},
                frozenset({"B2"}))
    root = ET.fromstring(render_svg(doc, live))
    s1a1 = next(g for g in _groups(root, "link") if g.get("data-link") == "S1/A1")
    rate = next(t for t in s1a1.iter(f"{SVG}tspan") if t.get("class") == "rate")
    assert rate.text == " 10.0/s"
    nodes = {g.get("data-name"): g for g in _groups(root, "node")}
    assert "alert" in (nodes["S1"].get("class") or "")
    rect = nodes["S1"].find(f"{SVG}rect")
    assert rect is not None and rect.get("fill") == "#ff8a80"
    assert "age 0.25 s" in "".join(nodes["S2"].itertext())
    assert {"frozen", "marked", "mark-suspend"} <= set((nodes["B2"].get("class") or "").split())
    assert "suspend" in "".join(nodes["B2"].itertext())


def test_svg_escapes_names() -> None:
    doc: dict[str, Any] = {"machines": [0], "tasks": [
        {"name": "a<b&c", "level": 1, "machine": 0, "status": "waiting"}],
        "links": [{"src": "./in\"put", "dst": "a<b&c", "type": "sensory", "priority": 8}]}
    root = ET.fromstring(render_svg(doc))  # well-formed
    assert {g.get("data-name") for g in _groups(root, "node")} == {"a<b&c", './in"put'}


def test_implicit_links_only_on_request(tmp_path: Path) -> None:
    s = fig65_system(tmp_path)
    try:
        doc = s.sysmgr.map_doc()
    finally:
        s.shutdown()
    plain = layout(doc)
    full = layout(doc, implicit=True)
    assert "host" not in plain.nodes
    assert full.nodes["host"].level == 4  # above the top task
    assert len(full.edges) > len(plain.edges)
    assert all(not e.link["implicit"] for e in plain.edges)
    assert link_key({"src": "host", "dst": "C1", "type": "command", "implicit": True}) == \
        "host/C1:command*"


def test_dot_ranks_levels_and_points_sensory_links_up(fig65_map: Path) -> None:
    dot = render_dot(sysmap.read(fig65_map))
    assert dot.startswith("digraph chcos {") and dot.rstrip().endswith("}")
    assert dot.count("rank=same") == 4
    assert '"A1" -> "S1" [color="#1b8a3a", fontcolor="#1b8a3a", label="p8", dir=back];' in dot
    assert '"C1" -> "B1" [color="#1f5fbf", fontcolor="#1f5fbf", label="p9"];' in dot


def test_text_lists_levels_files_and_rates(fig65_map: Path) -> None:
    doc = sysmap.read(fig65_map)
    text = render_text(doc, rates={"S1/A1:sensory": 9.5})
    lines = text.splitlines()
    order = [ln for ln in lines if ln.startswith("level")]
    assert order[:3] == ["level 3", "level 2", "level 1"]
    assert "level 0 (files and terminals)" in lines
    assert any("S1/A1" in ln and "9.5/s" in ln for ln in lines)
    assert "9.5/s" not in render_text(doc)


def test_check_doc_rejects_non_maps() -> None:
    with pytest.raises(ViewerError, match="tasks"):
        check_doc({"links": []})
    with pytest.raises(ViewerError, match="lacks src"):
        check_doc({"tasks": [], "links": [{"src": "a"}]})
    with pytest.raises(ViewerError, match="JSON object"):
        render_svg([])  # type: ignore[arg-type]


@pytest.mark.parametrize("fmt", ["text", "dot", "svg"])
def test_map_main_formats(fig65_map: Path, fmt: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert map_main([str(fig65_map), "--format", fmt]) == 0
    out = capsys.readouterr().out
    for task in FIG65_TASKS:
        assert task in out
    if fmt == "svg":
        ET.fromstring(out)
    elif fmt == "dot":
        assert "digraph" in out
    else:
        assert "C1/B1" in out and "p9" in out


def test_map_main_output_file_and_errors(fig65_map: Path, tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    target = tmp_path / "map.svg"
    assert map_main([str(fig65_map), "-f", "svg", "-o", str(target), "--implicit"]) == 0
    assert "host" in target.read_text()
    bad = tmp_path / "bad.map"
    bad.write_text(json.dumps({"format": "something else"}))
    assert map_main([str(bad)], out=io.StringIO()) == 1
    assert "not a chcos system map" in capsys.readouterr().err
    assert map_main([str(tmp_path / "missing.map")]) == 1
    assert "cannot read" in capsys.readouterr().err
