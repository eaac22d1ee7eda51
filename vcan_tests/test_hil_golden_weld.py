"""The welding cell's golden run (issue 52): every change to chcos is diffed against it. The job
runs in a fresh interpreter (``chcos run weld --trace``) while other processes load the machine,
and its trace must be the shipped golden trace, record for record (``chcos diff`` exits 0): every
device value and status change, every command and its confirmation, every task event at the
same virtual time. A change meant to alter the run regenerates the file:
``pytest vcan_tests/test_hil_golden_weld.py --chcos-update-golden`` (then commit it).

The protocol-free binding is deterministic now. The simulated buses are not yet (issue 47: their
drivers and peers hand frames between threads whose timing decides the order of interrupts
within an instant): their test is an expected failure until the virtual-time branches are
merged; it first checks that two runs, one under load, agree, and then needs its golden file,
written once with ``--chcos-update-golden``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from chcos import resources
from vcan_tests.support_hil import busy_processes, chcos

GOLDEN_DIR = Path(str(resources.path("chcos.apps.weld", "golden")))
#: virtual seconds of each golden run: the direct job inspects the seam, searches its start and
#: strikes the arc (about 29 s); the buses binding a stretch of its inspection
SECONDS = {"direct": 31.0, "buses": 5.0}


def golden(binding: str) -> Path:
    """The shipped golden trace of ``binding``."""
    return GOLDEN_DIR / f"{binding}.trace.gz"


def weld_trace(binding: str, where: Path, name: str, **env: str) -> Path:
    """The welding job's trace on ``binding`` for its golden stretch, run in a fresh
    interpreter in ``where``."""
    trace = where / f"{name}.trace.gz"
    res = chcos(where, ["run", "weld", "--binding", binding, "--duration",
                        str(SECONDS[binding]), "--trace", str(trace), "--workdir",
                        str(where / name)], **env)
    # the job is cut short at the golden stretch: exit status 1 (duration limit), never 2
    assert res.returncode in (0, 1), res.stdout + res.stderr
    assert trace.exists(), res.stdout + res.stderr
    return trace


@pytest.mark.slow
def test_the_direct_binding_runs_its_golden_run(tmp_path: Path, chcos_golden: Any) -> None:
    with busy_processes() as procs:
        new = weld_trace("direct", tmp_path, "loaded", PYTHONHASHSEED="17")
        assert all(p.poll() is None for p in procs)
    chcos_golden(new, golden("direct"))
    res = chcos(tmp_path, ["diff", str(golden("direct")), str(new)])
    assert res.returncode == 0, res.stdout + res.stderr
    # the golden run is worth guarding: the job inspected, searched and struck the arc, and
    # the trace holds the drives' commands, the line sensor's readings and the task events
    text = res.stdout
    assert "the same" in text, text
    from chcos.hil.trace import read_trace

    entries = read_trace(new).entries
    kinds = {e.kind for e in entries}
    assert {"value", "command", "confirmed", "event"} <= kinds, kinds
    assert any(e.subject == "volts_set" and e.kind == "command" and e.value for e in entries)
    assert {e.subject for e in entries if e.kind == "event"} >= {"E2", "D1", "D2"}


@pytest.mark.slow
@pytest.mark.xfail(strict=True, reason="issue 47: the simulated buses' drivers and peers still "
                   "hand frames between threads (interrupt order within an instant depends on "
                   "their timing); passes once the virtual-time branches are merged and the "
                   "golden trace is written (--chcos-update-golden)")
def test_the_simulated_buses_run_their_golden_run(tmp_path: Path, chcos_golden: Any) -> None:
    quiet = weld_trace("buses", tmp_path, "quiet")
    with busy_processes():
        loaded = weld_trace("buses", tmp_path, "loaded", PYTHONHASHSEED="17")
    res = chcos(tmp_path, ["diff", str(quiet), str(loaded)])
    assert res.returncode == 0, res.stdout + res.stderr
    chcos_golden(quiet, golden("buses"))


def test_the_report_shows_the_states_reached_and_where_the_run_parts(tmp_path: Path) -> None:
    report = tmp_path / "report.html"
    res = chcos(tmp_path, ["run", "weld", "--binding", "direct", "--duration", "2", "--seed", "1",
                           "--golden", str(golden("direct")), "--report", str(report),
                           "--tolerance", "arc_temp=0.5", "--workdir", str(tmp_path / "w")])
    assert res.returncode == 1, res.stdout + res.stderr      # cut short at 2 s
    # another measurement-noise seed: the joints' readings part from the golden run at once
    assert "golden run: " in res.stdout and "diverge; the first at t=0.010000 s" in res.stdout
    page = report.read_text(encoding="utf-8")
    assert "<h2>Device states this run reached</h2>" in page
    assert '<table class="cov">' in page and "device drives_enable" in page
    assert "<h2>Against the golden run</h2>" in page
    assert page.count('class="diverge-plot') == 4      # the first four diverging signals
    assert "golden (solid) and new (dashed), parting at t=0.010000 s" in page
