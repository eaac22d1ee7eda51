"""The viewer's data endpoints against the figure 6.5 system on virtual time, commands from the
page, the server-sent stream, the event log, and ``chcos view``."""

from __future__ import annotations

import io
import re
import threading
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.cli.view import view_main
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from chcos.viewer import ViewerError
from chcos.viewer.server import Viewer, serve
from chcos.viewer.snapshot import EventLog, Snapshotter, event_marks
from vcan_tests.support_view import (
    FIG65_TASKS,
    fig65_system,
    get,
    get_json,
    login,
    post_json,
    sse_messages,
    viewer_users,
)


@pytest.fixture
def fig65(tmp_path: Path) -> Iterator[System]:
    """The figure 6.5 system on a VirtualClock, C1 invoked, run for 2 virtual seconds."""
    s = fig65_system(tmp_path)
    s.run_for(2.0)
    yield s
    s.shutdown()


@pytest.fixture
def viewer(fig65: System) -> Iterator[Viewer]:
    """A viewer of the fig65 system on 127.0.0.1, a free port, with operator credentials."""
    v = serve(fig65, users=viewer_users())
    yield v
    v.stop()


def test_serve_picks_a_free_loopback_port(viewer: Viewer) -> None:
    assert viewer.url.startswith("http://127.0.0.1:")
    assert viewer.port > 0
    status, body = get(viewer.url)
    assert status == 200 and "<svg" not in body and 'src="/static/app.js"' in body
    for asset in ("app.js", "style.css"):
        assert get(viewer.url + "static/" + asset)[0] == 200


def test_snapshot_has_every_task_status_owner_and_device(viewer: Viewer) -> None:
    snap = get_json(viewer.url + "api/snapshot")
    assert snap["time"] == pytest.approx(2.0)
    tasks = {t["name"]: t for t in snap["map"]["tasks"]}
    assert set(tasks) == set(FIG65_TASKS)
    assert tasks["C1"]["owner"] == "host" and tasks["B1"]["owner"] == "C1"
    assert tasks["B1"]["priority"] == 9
    assert all(t["status"] in ("current", "ready", "waiting", "asleep", "suspended")
               for t in tasks.values())
    devices = {d["name"]: d for d in snap["map"]["devices"]}
    assert devices["S1"]["units"] == "mm" and devices["S1"]["status"] == "OK"
    assert snap["ages"]["S1"] == pytest.approx(0.0, abs=0.11)
    root = ET.fromstring(snap["svg"])
    names = {g.get("data-name") for g in root.iter("{http://www.w3.org/2000/svg}g")}
    assert set(FIG65_TASKS) <= names


def test_rates_from_successive_snapshots(fig65: System, viewer: Viewer) -> None:
    first = get_json(viewer.url + "api/snapshot?svg=0")
    sent0 = {lk["key"]: lk["sent"] for lk in first["map"]["links"]}
    fig65.run_for(2.0)
    second = get_json(viewer.url + "api/snapshot?svg=0")
    assert "svg" not in second
    assert second["time"] == pytest.approx(4.0)
    links = {lk["key"]: lk for lk in second["map"]["links"]}
    for key in ("S1/A1:sensory", "S2/A1:sensory", "S3/A2:sensory"):  # sensors at 10 Hz
        assert second["rates"][key] == pytest.approx(10.0, abs=0.5)
        assert links[key]["rate"] == second["rates"][key]
    for key, lk in links.items():  # every rate is exactly (sent now - sent then) / 2 s
        assert lk["rate"] == pytest.approx((lk["sent"] - sent0[key]) / 2.0)
    assert links["C1/B1:command"]["rate"] == 0.0
    # the clock has not moved: the rates stay as they were
    again = get_json(viewer.url + "api/snapshot?svg=0")
    assert again["rates"] == second["rates"] and again["seq"] == second["seq"] + 1


def test_event_log_and_marks_from_host_commands(fig65: System, viewer: Viewer) -> None:
    start = get_json(viewer.url + "api/snapshot?svg=0")["last_event"]
    fig65.execute("suspend B2")
    snap = get_json(viewer.url + f"api/snapshot?since={start}")
    assert [(e["kind"], e["detail"]) for e in snap["events"]] == [("suspend", "host suspend B2")]
    assert snap["marks"]["B2"]["kind"] == "suspend"
    assert "B2" in snap["map"]["frozen"]
    assert "mark-suspend" in snap["svg"]
    fig65.execute("resume B2")
    snap = get_json(viewer.url + f"api/snapshot?since={snap['last_event']}")
    assert [e["kind"] for e in snap["events"]] == ["resume"]
    assert "B2" not in snap["marks"] and "B2" not in snap["map"]["frozen"]
    assert get(viewer.url + "api/snapshot?since=x")[0] == 400


def test_setpri_and_invoke_from_the_page(fig65: System, viewer: Viewer) -> None:
    alice = login(viewer.url)
    status, ans = post_json(viewer.url + "api/command", {"line": "setpri -12 C1 B1"}, alice)
    assert (status, ans) == (200, {"ok": True, "answer": "C1/B1 priority 12"})
    snap = get_json(viewer.url + "api/snapshot")
    c1b1 = next(lk for lk in snap["map"]["links"] if lk["key"] == "C1/B1:command")
    assert c1b1["priority"] == 12
    assert '<tspan class="prio" font-weight="bold">p12</tspan>' in snap["svg"]
    status, ans = post_json(viewer.url + "api/command", {"line": "invoke -7 A3"}, alice)
    assert status == 200 and ans["answer"].startswith("A3 invoked at priority 7")
    snap = get_json(viewer.url + "api/snapshot?since=0")
    # the host's link outranks B1's (priority 4): A3 is pre-empted, and marked so
    assert [e["kind"] for e in snap["events"]][-3:] == ["setpri", "preempt", "invoke"]
    assert snap["marks"]["A3"]["kind"] == "preempt"
    assert next(t for t in snap["map"]["tasks"] if t["name"] == "A3")["owner"] == "host"


@pytest.mark.parametrize(("payload", "status", "error"), [
    ({"line": "setpri -120 C1 B1"}, 400, "out of range"),
    ({"line": "setpri -5 C1 A1"}, 400, "setpri"),
    ({"line": "invoke NOPE"}, 400, "no task named 'NOPE'"),
    ({"line": "install -m0i1 Z1 S1"}, 403, "only setpri and invoke"),
    ({"line": "inject S1 5"}, 403, "only setpri and invoke"),
    ({"line": "suspend A1"}, 403, "only setpri and invoke"),
    ({"line": "resume A1"}, 403, "only setpri and invoke"),
    ({"line": "invoke C1 'unbalanced"}, 400, "quotation"),
    ({"line": ""}, 400, "empty command line"),
    ({"cmd": "x"}, 400, "expected JSON"),
    (b"not json", 400, "expected JSON"),
])
def test_bad_commands_are_refused_with_a_reason(fig65: System, viewer: Viewer, payload: object,
                                                 status: int, error: str) -> None:
    before = fig65.sysmgr.map_doc()["links"]
    got, ans = post_json(viewer.url + "api/command", payload, login(viewer.url, "sam"))
    assert got == status and ans["ok"] is False and error in ans["error"]
    assert fig65.sysmgr.map_doc()["links"] == before


def test_viewer_is_read_only_without_credentials(fig65: System) -> None:
    with serve(fig65) as v:
        status, ans = post_json(v.url + "api/command", {"line": "setpri -9 C1 B2"})
        assert status == 403 and "read-only" in ans["error"]
        status, ans = post_json(v.url + "api/login", {"user": "alice", "password": "x"})
        assert status == 403 and "read-only" in ans["error"]
        assert get_json(v.url + "api/session") == {"user": None, "read_only": True}


def test_stream_sends_a_snapshot_then_deltas_with_new_events(fig65: System) -> None:
    with serve(fig65, period=0.05) as v:
        msgs = sse_messages(v.url + "api/stream", 3)
        first = msgs[0]
        assert first["type"] == "snapshot" and "svg" in first["state"]
        assert set(first["state"]["tasks"]) == set(FIG65_TASKS)
        # a newly connected page gets the history, then only what is new
        assert [e["kind"] for e in first["events"]][:3] == ["boot", "boot", "boot"]
        assert msgs[1]["events"] == [] and msgs[2]["events"] == []
        # the clock stands still (virtual time, kernel not running): the deltas carry only the
        # update number, never the map or the drawing again
        for m in msgs[1:]:
            assert m["type"] == "delta" and set(m["patch"]) <= {"seq"}, m["patch"]
        seqs = [first["state"]["seq"], *(m["patch"].get("seq") for m in msgs[1:])]
        assert seqs == sorted(seqs)


def test_map_endpoints(viewer: Viewer) -> None:
    status, svg = get(viewer.url + "api/map.svg")
    assert status == 200 and ET.fromstring(svg).tag.endswith("svg")
    status, dot = get(viewer.url + "api/map.dot")
    assert status == 200 and dot.startswith("digraph")
    status, text = get(viewer.url + "api/map.txt")
    assert status == 200 and text.startswith("machines: 0, 1, 2")


def test_event_log_keeps_the_newest() -> None:
    clock = VirtualClock(5.0)
    log = EventLog(clock, keep=3)  # times since the log (the system) started, not the clock's
    for i in range(5):
        if i == 4:
            clock.jump_to(6.5)
        log.event("install", f"T{i}")
    assert log.last_seq == 5
    assert [e.detail for e in log.since(0)] == ["T2", "T3", "T4"]
    assert [e.seq for e in log.since(4)] == [5]
    assert log.since(5) == [] and log.since(0)[0].time == 0.0 and log.since(4)[0].time == 1.5


@pytest.mark.parametrize(("kind", "detail", "marks"), [
    ("abnormal", "A1: ValueError: boom", [("A1", "abnormal")]),
    ("estop", "C1: operator", [("C1", "estop")]),
    ("suspend", "K9 suspended A2", [("A2", "suspend")]),
    ("suspend", "host suspend B2", [("B2", "suspend")]),
    ("resume", "host resume B2", [("B2", None)]),
    ("preempt", "B1 took A3 from B2 (priority 9 > 4)", [("A3", "preempt")]),
    ("device-stale", "S1: no data for 0.5 s", [("S1", "device-stale")]),
    ("device-ok", "S1", [("S1", None)]),
    ("estop", "shutdown: 2 actuator(s) at safe values", []),
    ("install", "A1 on machine 0", []),
])
def test_event_marks(kind: str, detail: str, marks: list[tuple[str, str | None]]) -> None:
    names = {"A1", "A2", "A3", "B1", "B2", "C1", "K9", "S1"}
    assert event_marks(kind, detail, names) == marks


def test_snapshotter_retries_torn_reads_then_gives_up(fig65: System,
                                                      monkeypatch: pytest.MonkeyPatch) -> None:
    snaps = Snapshotter(fig65)
    real = fig65.sysmgr.map_doc
    calls = {"n": 0}

    def flaky() -> dict[str, object]:
        calls["n"] += 1
        if calls["n"] == 1:
            raise RuntimeError("dictionary changed size during iteration")
        return real()

    monkeypatch.setattr(fig65.sysmgr, "map_doc", flaky)
    assert snaps.take(None)["seq"] == 1 and calls["n"] == 2

    def broken() -> dict[str, object]:
        raise KeyError("B3")

    monkeypatch.setattr(fig65.sysmgr, "map_doc", broken)
    with pytest.raises(ViewerError, match="no consistent snapshot"):
        snaps.take(None)


def test_viewer_errors(fig65: System) -> None:
    with pytest.raises(ViewerError, match="period"):
        Viewer(fig65, period=0)
    with serve(fig65) as v, pytest.raises(ViewerError, match="cannot serve"):
        serve(fig65, port=v.port)
    v = Viewer(fig65)
    v.stop()  # not started: nothing to do
    v.start()
    with pytest.raises(ViewerError, match="already started"):
        v.start()
    v.stop()


def test_chcos_view_serves_the_example(tmp_path: Path) -> None:
    stop = threading.Event()
    seen: dict[str, object] = {}

    def on_ready(v: Viewer) -> None:
        snap = get_json(v.url + "api/snapshot?svg=0")
        seen["tasks"] = {t["name"] for t in snap["map"]["tasks"]}
        seen["owner"] = {t["name"]: t["owner"] for t in snap["map"]["tasks"]}["C1"]
        seen["kinds"] = {e["kind"] for e in get_json(v.url + "api/snapshot?since=0&svg=0")
                         ["events"]}
        stop.set()

    out = io.StringIO()
    assert view_main(["--example", "fig65", "--workdir", str(tmp_path)], stop=stop,
                     on_ready=on_ready, out=out) == 0
    assert "chcos view: serving http://127.0.0.1:" in out.getvalue()
    assert "C1 invoked" in out.getvalue()
    assert seen["tasks"] == set(FIG65_TASKS) and seen["owner"] == "host"
    assert {"boot", "install", "setpri", "invoke"} <= seen["kinds"]  # type: ignore[operator]
    assert (tmp_path / "sysfile.map").is_file()


def test_chcos_view_from_a_map(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    s = fig65_system(tmp_path, invoke=False)
    s.shutdown()
    stop = threading.Event()
    seen: dict[str, object] = {}

    def on_ready(v: Viewer) -> None:
        snap = get_json(v.url + "api/snapshot?svg=0")
        seen["prio"] = next(lk["priority"] for lk in snap["map"]["links"]
                            if lk["key"] == "C1/B1:command")
        stop.set()

    assert view_main([str(tmp_path / "sysfile.map"), "--invoke", "C1", "--port", "0"],
                     stop=stop, on_ready=on_ready, out=io.StringIO()) == 0
    assert seen["prio"] == 9
    assert view_main([str(tmp_path / "nope.map")], out=io.StringIO()) == 1
    assert "cannot read system map" in capsys.readouterr().err


def test_chcos_view_terminal_redraws_with_rates(tmp_path: Path) -> None:
    stop = threading.Event()
    out = io.StringIO()
    assert view_main(["--example", "fig65", "--workdir", str(tmp_path), "--terminal",
                      "--read-only"], stop=stop, on_ready=lambda v: stop.set(), out=out) == 0
    screen = out.getvalue().split("\x1b[H\x1b[2J")[-1]
    lines = screen.splitlines()
    assert lines[1] == "level 3" and lines[2].startswith("  C1 ")
    assert re.search(r"v C1/B1 +command p9 .* +\d+\.\d/s$", lines[3]), lines[3]
    for task in FIG65_TASKS:
        assert f"  {task} " in screen
    assert "/s" in screen and "http://127.0.0.1:" in screen
