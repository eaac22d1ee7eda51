"""Operations a cell needs (issue 39): ``chcos run --log FILE`` with rotation; the live view's
history of each device (a sparkline per device on the page, the same data as CSV)."""

from __future__ import annotations

import csv
import io
import itertools
import logging
import threading
import time
from pathlib import Path

import pytest

from chcos.cli import scaffold
from chcos.cli.main import main as cli_main
from chcos.helpers import free_port
from chcos.kernel.clock import VirtualClock
from chcos.viewer.history import History
from chcos.viewer.server import serve
from vcan_tests.support_view import get, get_json, small_cell


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    scaffold.create(tmp_path / "cell", port=free_port())
    return tmp_path / "cell"


def test_run_log_file_has_the_story_and_rotates(cell: Path, tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.log"
    root_level = logging.getLogger().level
    assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "3",
                     "--value", "level=100", "--log", str(log)]) == 0
    text = log.read_text(encoding="utf-8")
    assert "install: fill on machine 0" in text          # INFO events, without -v
    assert "chcos.run: system cell: healthy after 3.0 s" in text
    assert "INFO" not in capsys.readouterr().err         # the terminal keeps its level
    assert logging.getLogger().level == root_level       # put back after the run
    # a small size: the file rotates and keeps --log-keep old ones
    for _ in range(4):
        assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "1",
                         "--value", "level=100", "--log", str(log), "--log-size", "0.0005",
                         "--log-keep", "2"]) == 0
    assert (tmp_path / "run.log.1").exists() and (tmp_path / "run.log.2").exists()
    assert not (tmp_path / "run.log.3").exists()
    assert "healthy after 1.0 s" in log.read_text(encoding="utf-8") + \
        (tmp_path / "run.log.1").read_text(encoding="utf-8")


def test_run_log_refuses_an_unwritable_file(cell: Path, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    assert cli_main(["run", str(cell / "system.toml"), "--virtual", "--duration", "1",
                     "--log", str(tmp_path / "no" / "such" / "dir" / "run.log")]) == 2
    assert "--log" in capsys.readouterr().err


# ---- the live view's history: a sparkline per device, the same data as CSV ---------------------
def test_viewer_keeps_each_devices_history_and_serves_it_as_csv(tmp_path: Path) -> None:
    s = small_cell(tmp_path, clock=VirtualClock())
    viewer = serve(s)
    try:
        for value in (1.0, 2.5, 4.0):     # one value per virtual second, each seen by a sample
            s.devtab.inject("P1", value)
            s.run_for(1.0)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                got = get_json(viewer.url + "api/history")["devices"].get("P1", [])
                if got and got[-1][1] == value:
                    break
                threading.Event().wait(0.05)
            assert got and got[-1][1] == value, got
        status, text = get(viewer.url + "api/history.csv")
        assert status == 200
        rows = list(csv.DictReader(io.StringIO(text)))
        p1 = [float(r["value"]) for r in rows if r["device"] == "P1"]
        assert [v for i, v in enumerate(p1) if i == 0 or v != p1[i - 1]] == [1.0, 2.5, 4.0]
        times = [float(r["time_s"]) for r in rows if r["device"] == "P1"]
        assert times == sorted(times) and times[-1] - times[0] >= 1.9
        page = get(viewer.url)[1]
        assert 'href="/api/history.csv"' in page
        assert "sparkline" in get(viewer.url + "static/app.js")[1]
    finally:
        viewer.stop()
        s.shutdown()


def test_history_window_and_what_it_skips() -> None:
    h = History(window=10.0, every=1.0)
    for t in range(30):
        h.sample(float(t), [{"name": "a", "value": t}, {"name": "s", "value": "text"},
                            {"name": "b", "value": None}, {"name": "f", "value": t % 2 == 0}])
    h.sample(29.0, [{"name": "a", "value": 99}])         # the clock has not moved: ignored
    series = h.series()
    assert set(series) == {"a", "f"}
    assert [t for t, _v in series["a"]] == [float(t) for t in range(19, 30)]
    assert series["a"][-1] == (29.0, 29.0) and series["f"][-1] == (29.0, 0.0)
    assert not h.due(29.5) and h.due(30.0)


def test_thirty_devices_with_long_names_draw_without_overlapping_labels() -> None:
    """Each label is cut to what its node's width holds (the full name is the node's title),
    so the labels of neighbouring nodes on a row never run into each other."""
    import re
    import xml.etree.ElementTree as ET

    from chcos.viewer.graph import LINE_CHARS, NAME_CHARS, render_svg

    names = [f"supply_monitor_channel_{i:02d}_dc_bus_voltage" for i in range(30)]
    doc = {"tasks": [], "links": [],
           "devices": [{"name": n, "direction": "sensor", "machine": 0, "status": "OK",
                        "value": 123456.789, "units": "mV"} for n in names]}
    root = ET.fromstring(render_svg(doc))
    ns = {"s": "http://www.w3.org/2000/svg"}
    rows: dict[float, list[tuple[float, float]]] = {}
    for g in root.iter("{http://www.w3.org/2000/svg}g"):
        if g.get("data-kind") != "sensor":
            continue
        assert g.findtext("s:title", namespaces=ns) in names     # the full name on hover
        for t in g.findall("s:text", ns):
            text = "".join(t.itertext())
            bold = t.get("font-weight") == "bold"
            assert len(text) <= (NAME_CHARS if bold else LINE_CHARS), text
            width = len(text) * (7.4 if bold else 6.2)
            x, y = float(t.get("x", "0")), float(t.get("y", "0"))
            rows.setdefault(y, []).append((x - width / 2, x + width / 2))
    assert rows
    for spans in rows.values():
        spans.sort()
        for (_a0, a1), (b0, _b1) in itertools.pairwise(spans):
            assert a1 < b0, "labels overlap"
    assert re.search("…", ET.tostring(root, encoding="unicode"))   # cut, not dropped
