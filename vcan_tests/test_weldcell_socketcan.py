"""The good-gap welding job over real SocketCAN (vcan0: the CANopen servos, vcan1: the raw CAN
sensors) inside User-Mode Linux.

Two halves. ``test_good_gap_over_socketcan`` (marked ``socketcan``) is the job itself; it runs
where vcan0/vcan1 are up, that is inside UML, and only when CHCOS_UML_WELD=1 (it takes about five
minutes there: UML makes every system call slow). ``test_good_gap_passes_inside_uml`` is the
host side: it boots UML with CHCOS_UML_WELD=1 and runs the first half there. Its UML run starts
as soon as the session's tests are collected (marker ``uml_background``, see conftest), so it
overlaps the rest of the suite on the other core; the test waits for the result and checks that
the job ran (passed, not skipped) and welded the seam in band, with the five CiA 402 joint drives
enabled (on their side) for the job and brought to SWITCH ON DISABLED by the shutdown's safe stop
(quick stop 0x02, then disable voltage 0x00, over vcan0).
"""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import pytest

from chcos.apps.weld.cell import open_cell
from vcan_tests.conftest import opt_in, require
from vcan_tests.uml import (
    BACKGROUND,
    GUEST_RESULTS,
    REPO_ROOT,
    BackgroundUml,
    require_uml,
    uml_boot_problem,
)

GUEST_TIMEOUT = 780.0   # seconds for the whole UML run; about ten minutes are needed
GUEST_TEST = "test_good_gap_over_socketcan"


@pytest.mark.socketcan
def test_good_gap_over_socketcan(tmp_path: Path) -> None:
    from vcan_tests.uml import socketcan_channel

    require(socketcan_channel() is not None, "SocketCAN vcan0 (runs inside User-Mode Linux)")
    opt_in("CHCOS_UML_WELD", "the whole welding job inside UML (about five minutes; "
           "test_good_gap_passes_inside_uml runs it on every CI run)")
    with open_cell("buses", workdir=tmp_path, interface="socketcan",
                   channels=("vcan0", "vcan1")) as cell:
        cell.start_job(None)
        cell.run(200.0)
        outcome = cell.outcome()
        summary = cell.summary()
        drives = [d.power.name for d in cell.drives]          # the drives' side, job over
    # and after the shutdown's safe stops (over vcan0: quick stop, then disable voltage)
    after = [(d.power.name, d.received[-2:]) for d in cell.drives]
    out = os.environ.get("CHCOS_UML_WELD_OUT")
    if out:
        Path(out).write_text(json.dumps({"outcome": outcome, "summary": summary,
                                         "drives": drives, "after": after}, default=str))
    assert outcome is not None and outcome["outcome"] == "welded", outcome
    assert summary["welded_mm"] >= 0.99 * summary["seam_mm"], summary
    assert summary["in_band_pct"] >= 95.0, summary
    assert drives == ["ENABLED"] * 5, drives
    assert after == [("SWITCH_ON_DISABLED", [0x02, 0x00])] * 5, after


def start_in_background(config: pytest.Config) -> None:
    """Boot UML and start the job there (once per session; nothing where UML cannot boot)."""
    runs = config.stash.setdefault(BACKGROUND, {})
    if "weld" in runs or uml_boot_problem() is not None:
        return
    workdir = Path(tempfile.mkdtemp(prefix="chcos-weld-uml-"))
    env = dict(os.environ, CHCOS_UML_WELD="1", CHCOS_UML_WELD_OUT=str(workdir / "weld.json"))
    argv = [sys.executable, "-m", "pytest", "-m", "socketcan", "-rs", "-p", "no:cacheprovider",
            f"--junitxml={workdir / 'weld.xml'}", "vcan_tests/test_weldcell_socketcan.py"]
    runs["weld"] = (BackgroundUml.start(argv, workdir, env=env, timeout=GUEST_TIMEOUT,
                                        cwd=REPO_ROOT), workdir)


@pytest.mark.uml
@pytest.mark.slow
@pytest.mark.uml_background
def test_good_gap_passes_inside_uml(request: pytest.FixtureRequest,
                                    record_property: Callable[[str, object], None]) -> None:
    require_uml()
    start_in_background(request.config)   # already running unless this test was selected late
    run, workdir = request.config.stash[BACKGROUND]["weld"]
    result = run.result()
    wall = time.monotonic() - run.started
    detail = f"status {result.returncode}\n{result.stdout[-6000:]}\n{result.stderr[-3000:]}"
    assert result.returncode == 0, detail
    cases = {c.get("name"): [k.tag for k in c] for c in ET.parse(workdir / "weld.xml").iter(
        "testcase")}
    assert cases.get(GUEST_TEST) == [], f"the job did not pass inside UML: {cases}\n{detail}"
    done = json.loads((workdir / "weld.json").read_text())
    summary = done["summary"]
    for key in ("welded_mm", "in_band_pct", "seconds"):
        record_property(f"uml_weld_{key}", summary[key])
    assert done["outcome"]["outcome"] == "welded"
    assert summary["in_band_pct"] >= 95.0, summary
    # the CiA 402 joint drives, on their side: enabled for the job, safe-stopped at shutdown
    assert done["drives"] == ["ENABLED"] * 5, done["drives"]
    assert done["after"] == [["SWITCH_ON_DISABLED", [2, 0]]] * 5, done["after"]
    request.config.stash.setdefault(GUEST_RESULTS, []).append(
        f"welding job (good gap) over vcan0/vcan1 inside UML: welded, "
        f"{summary['in_band_pct']:.1f} % in band, {wall:.0f} s from boot to halt")
