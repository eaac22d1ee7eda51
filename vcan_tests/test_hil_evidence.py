"""HIL evidence on the cell ``chcos new`` writes (issue 52): its own tests, run by pytest in a
subprocess with ``--chcos-coverage``, produce a coverage file whose reached and not-reached
states are what they provoke; ``--chcos-coverage-fail-under`` fails a session below it; a run's
trace (``chcos run --virtual --trace``) diffs the same against a rerun while other processes
load the machine, and a deliberately changed set-point makes ``chcos diff`` exit 1 naming the
first diverging device at the time its commands first differ."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from chcos.cli.scaffold import create
from chcos.hil.trace import read_trace
from vcan_tests.support_hil import busy_processes, chcos, env

BLIP = "tests/test_cell.py::test_the_cell_rides_through_a_plc_blip"
FAILED = "tests/test_cell.py::test_a_failed_sensor_makes_the_valve_safe"
OPENS = "tests/test_cell.py::test_valve_opens_below_the_setpoint"
RAMP = "level=ramp(0, 200, 5)"


def _pytest(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args],
                          cwd=cell, env=env(), text=True, capture_output=True, timeout=600)


def _chcos(cell: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return chcos(cell, args)


def _states(doc: dict[str, Any], group: str, name: str) -> dict[str, dict[str, Any]]:
    """``class: state`` -> the state's entry, of one subject of a coverage file."""
    return {f"{s['class']}: {s['state']}": s for s in doc[group][name]["states"]}


def _reached(doc: dict[str, Any]) -> set[tuple[str, str, str]]:
    return {(g, n, f"{s['class']}: {s['state']}") for g in ("devices", "buses", "tasks")
            for n, subj in doc[g].items() for s in subj["states"] if s["reached"]}


@pytest.fixture
def cell(tmp_path: Path) -> Path:
    root = tmp_path / "tank"
    create(root)
    return root


def test_the_scaffolds_tests_reach_what_they_provoke(cell: Path) -> None:
    res = _pytest(cell, "--chcos-coverage=cov.json", "--chcos-coverage-fail-under=99", "-v")
    out = res.stdout
    # every test passed, but 99 % of the catalogue was not reached: the session fails
    assert "3 passed" in out, out + res.stderr
    assert res.returncode == 1, out
    assert "--chcos-coverage-fail-under=99: FAIL" in out, out
    assert "chcos device-state coverage" in out and "device level (sensor)" in out, out
    doc = json.loads((cell / "cov.json").read_text(encoding="utf-8"))
    assert doc["format"] == "chcos-coverage 1"
    assert set(doc["tests"]) == {BLIP, FAILED, OPENS}
    level = _states(doc, "devices", "level")
    valve = _states(doc, "devices", "valve")
    # the PLC blip: the sensor fails when the connection drops, goes stale (stale_after 1 s)
    # while the driver reconnects, and recovers; the failed sensor (cell.fail) fails and
    # recovers without any bus error: a reported failure, outside the Modbus catalogue
    assert level["status: stale"]["tests"] == [BLIP]
    assert level["status: failed"]["tests"] == sorted([BLIP, FAILED])
    assert level["status: recovered"]["tests"] == sorted([BLIP, FAILED])
    causes = {k for k, s in level.items() if k.startswith("failure: ") and BLIP in s["tests"]}
    # a silenced simulated PLC closes its port: the driver reports the connection lost
    # (a PLC that stays connected and stops answering would be a timeout)
    assert causes == {"failure: disconnected"}, causes
    assert level["failure: reported"]["tests"] == [FAILED]
    assert not level["failure: reported"]["catalogued"]
    assert not level["failure: timeout"]["reached"]
    # the valve: its safe value on each abnormal end of fill, after the blip on its recovery,
    # and at every shutdown; no test e-stops
    assert valve["safe value: abnormal completion"]["tests"] == sorted([BLIP, FAILED])
    assert valve["safe value: recovery"]["tests"] == [BLIP]
    assert valve["safe value: shutdown"]["tests"] == sorted([BLIP, FAILED, OPENS])
    assert not valve["safe value: e-stop"]["reached"]
    plc = _states(doc, "buses", "plc")
    assert plc["bus state: disconnected"]["tests"] == [BLIP]
    assert plc["bus state: reconnected"]["tests"] == [BLIP]
    fill = _states(doc, "tasks", "fill")
    assert fill["task: abnormal end"]["tests"] == sorted([BLIP, FAILED])
    assert fill["task: restart"]["tests"] == sorted([BLIP, FAILED])
    assert not fill["task: pre-empted"]["reached"]
    reached = _reached(doc)
    # nothing reached that nothing provoked: no exception answer, no bus-off anywhere
    assert not [r for r in reached if "exception" in r[2] or "bus-off" in r[2]], reached
    # a Modbus sensor has no NMT state, no EMCY, no CiA 402 state in its catalogue
    assert not [k for k in level if k.split(":")[0] in ("NMT", "EMCY", "CiA 402")]
    catalogued = [s for g in ("devices", "buses", "tasks") for subj in doc[g].values()
                  for s in subj["states"] if s["catalogued"]]
    assert doc["catalogued"] == len(catalogued)
    assert doc["reached"] == sum(1 for s in catalogued if s["reached"])
    assert f"device-state coverage: {doc['reached']} of {doc['catalogued']}" in out
    # -v: what each subject did not reach
    assert "not reached: failure: timeout" in out, out


def test_one_test_alone_meets_a_low_threshold_and_reaches_only_its_own_states(
        cell: Path) -> None:
    res = _pytest(cell, "--chcos-coverage", "--chcos-coverage-fail-under=5", "-k",
                  "valve_opens")
    assert res.returncode == 0, res.stdout + res.stderr
    assert "--chcos-coverage-fail-under=5: met" in res.stdout, res.stdout
    doc = json.loads((cell / "chcos-coverage.json").read_text(encoding="utf-8"))
    assert doc["tests"] == [OPENS]
    assert _reached(doc) == {("devices", "level", "status: OK"),
                             ("devices", "valve", "status: OK"),
                             ("devices", "valve", "safe value: shutdown")}


def _run(cell: Path, trace: str) -> None:
    res = _chcos(cell, "run", "system.toml", "--virtual", "--duration", "4", "--value", RAMP,
                 "--trace", trace)
    assert res.returncode == 0, res.stdout + res.stderr


def test_a_rerun_is_the_same_under_load_and_a_changed_setpoint_is_not(cell: Path) -> None:
    _run(cell, "golden.trace")
    with busy_processes() as procs:
        _run(cell, "rerun.trace")
        assert all(p.poll() is None for p in procs)   # they loaded the machine throughout
    same = _chcos(cell, "diff", "golden.trace", "rerun.trace")
    assert same.returncode == 0, same.stdout + same.stderr
    assert "the same" in same.stdout
    install = cell / "install.chcos"
    install.write_text(install.read_text(encoding="utf-8").replace("setpoint=120",
                                                                   "setpoint=110"),
                       encoding="utf-8")
    _run(cell, "changed.trace")
    diff = _chcos(cell, "diff", "golden.trace", "changed.trace")
    assert diff.returncode == 1, diff.stdout + diff.stderr
    # where the valve's commands first differ, read from the two files independently
    golden, changed = read_trace(cell / "golden.trace"), read_trace(cell / "changed.trace")
    a = [(e.t, e.value) for e in golden.entries if e.subject == "valve" and e.kind == "command"]
    b = [(e.t, e.value) for e in changed.entries if e.subject == "valve" and e.kind == "command"]
    t = next(x[0] for x, y in zip(a, b, strict=True) if x != y)
    assert 0.0 < t < 4.0
    first = diff.stdout.splitlines()[0]
    assert first.strip().startswith(f"valve: first divergence at t={t:.6f} s"), diff.stdout
    # the level followed the same ramp in both runs: only the valve diverges
    assert "1 diverge; the first at" in diff.stdout and "level:" not in diff.stdout
    assert [e for e in golden.entries if e.subject == "level"] == \
        [e for e in changed.entries if e.subject == "level"]
    broken = cell / "broken.trace"
    broken.write_text("# chcos-trace 1\n0.1 value level\n", encoding="utf-8")
    bad = _chcos(cell, "diff", "golden.trace", "broken.trace")
    assert bad.returncode == 2 and "broken.trace:2: missing value" in bad.stderr, bad.stderr


GOLDEN_TEST = '''
def test_the_run_is_its_golden_run(chcos_cell):
    cell = chcos_cell("system.toml", values={"level": "ramp(0, 200, 5)"})
    cell.run_for(3.0)
    assert cell.trace().entries
    cell.assert_golden("tests/golden/fill.trace")
'''


def test_a_cell_asserts_its_golden_trace_written_by_update_golden(cell: Path) -> None:
    (cell / "tests" / "test_golden.py").write_text(GOLDEN_TEST, encoding="utf-8")
    golden = cell / "tests" / "golden" / "fill.trace"
    missing = _pytest(cell, "tests/test_golden.py")
    assert missing.returncode == 1 and "no golden trace" in missing.stdout, missing.stdout
    assert "--chcos-update-golden" in missing.stdout
    written = _pytest(cell, "tests/test_golden.py", "--chcos-update-golden")
    assert written.returncode == 0, written.stdout
    trace = read_trace(golden)
    assert trace.header["system"] == "tank" and trace.header["clock"] == "virtual"
    assert {e.subject for e in trace.entries} >= {"level", "valve", "fill"}
    again = _pytest(cell, "tests/test_golden.py")
    assert again.returncode == 0, again.stdout
    install = cell / "install.chcos"
    install.write_text(install.read_text(encoding="utf-8").replace("setpoint=120",
                                                                   "setpoint=110"),
                       encoding="utf-8")
    changed = _pytest(cell, "tests/test_golden.py")
    assert changed.returncode == 1, changed.stdout
    assert "the run parts from its golden trace" in changed.stdout
    assert "valve: first divergence at t=" in changed.stdout, changed.stdout
