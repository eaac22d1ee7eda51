"""The welding cell over real SocketCAN (vcan0: the CANopen servos, vcan1: the raw CAN sensors)
inside User-Mode Linux.

Two halves. ``test_good_gap_over_socketcan`` (marked ``socketcan``) is the job itself; it runs
where vcan0/vcan1 are up, that is inside UML, and only when CHCOS_UML_WELD=1.
``test_good_gap_passes_inside_uml`` is the host side: it boots UML with CHCOS_UML_WELD=1 and runs
the first half there. Its UML run starts as soon as the session's tests are collected (marker
``uml_background``, see conftest), so it overlaps the rest of the suite on the other core; the
test waits for the result and checks that the job ran (passed, not skipped).

By default the job runs :data:`WIRING_SECONDS` of virtual time: what proves the vcan wiring (the
five CiA 402 joint drives enabled, on their side, over vcan0; the raw-CAN sensors and the servos'
TPDOs delivered over vcan1 and vcan0; the drives brought to SWITCH ON DISABLED by the shutdown's
safe stop, quick stop 0x02 then disable voltage 0x00, over vcan0). With CHCOS_UML_WELD_FULL=1 it
welds the whole good gap instead (about ten minutes inside UML, where every system call is slow)
and checks the seam welded in band. The guest runs in UML's time-travel mode
(``CHCOS_UML_TIME_TRAVEL``, default ``inf-cpu``: the guest's clock is independent of the host's
load), as a functional test; set it empty for real time.
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

GUEST_TIMEOUT = 780.0   # seconds for the whole UML run; the full job needs about ten minutes
GUEST_TEST = "test_good_gap_over_socketcan"
WIRING_SECONDS = 4.0    # virtual seconds: drives enabled, every bus delivering, then shutdown
#: the sensors whose readings prove each CAN bus's wiring: raw CAN on vcan1, TPDOs on vcan0
WIRING_SENSORS = ("arc_temp", "intruder", "start_marker", "theta1", "theta5")


def full_job() -> bool:
    """True when the whole job is asked for (CHCOS_UML_WELD_FULL=1), not the wiring run."""
    return os.environ.get("CHCOS_UML_WELD_FULL") == "1"


@pytest.mark.socketcan
def test_good_gap_over_socketcan(tmp_path: Path) -> None:
    from vcan_tests.uml import socketcan_channel

    require(socketcan_channel() is not None, "SocketCAN vcan0 (runs inside User-Mode Linux)")
    opt_in("CHCOS_UML_WELD", "the welding job inside UML "
           "(test_good_gap_passes_inside_uml runs it on every CI run)")
    full = full_job()
    with open_cell("buses", workdir=tmp_path, interface="socketcan",
                   channels=("vcan0", "vcan1")) as cell:
        cell.start_job(None)
        cell.run(200.0 if full else WIRING_SECONDS, until_done=full)
        outcome = cell.outcome()
        summary = cell.summary()
        readings = {n: cell.system.devtab.get(n).readings for n in WIRING_SENSORS}
        drives = [d.power.name for d in cell.drives]          # the drives' side, job over
    # and after the shutdown's safe stops (over vcan0: quick stop, then disable voltage)
    after = [(d.power.name, d.received[-2:]) for d in cell.drives]
    out = os.environ.get("CHCOS_UML_WELD_OUT")
    if out:
        Path(out).write_text(json.dumps({"full": full, "outcome": outcome, "summary": summary,
                                         "readings": readings, "drives": drives,
                                         "after": after}, default=str))
    assert drives == ["ENABLED"] * 5, drives
    assert after == [("SWITCH_ON_DISABLED", [0x02, 0x00])] * 5, after
    # every bus delivered for the whole run (sensors at 20..100 Hz)
    assert all(n >= 10 * WIRING_SECONDS for n in readings.values()), readings
    if full:
        assert outcome is not None and outcome["outcome"] == "welded", outcome
        assert summary["welded_mm"] >= 0.99 * summary["seam_mm"], summary
        assert summary["in_band_pct"] >= 95.0, summary


def start_in_background(config: pytest.Config) -> None:
    """Boot UML and start the job there (once per session; nothing where UML cannot boot)."""
    runs = config.stash.setdefault(BACKGROUND, {})
    if "weld" in runs or uml_boot_problem() is not None:
        return
    workdir = Path(tempfile.mkdtemp(prefix="chcos-weld-uml-"))
    env = dict(os.environ, CHCOS_UML_WELD="1", CHCOS_UML_WELD_OUT=str(workdir / "weld.json"))
    env.setdefault("CHCOS_UML_TIME_TRAVEL", "inf-cpu")
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
    # the CiA 402 joint drives, on their side: enabled for the job, safe-stopped at shutdown
    assert done["drives"] == ["ENABLED"] * 5, done["drives"]
    assert done["after"] == [["SWITCH_ON_DISABLED", [2, 0]]] * 5, done["after"]
    assert done["full"] == full_job()
    assert all(n >= 10 * WIRING_SECONDS for n in done["readings"].values()), done["readings"]
    if done["full"]:
        assert done["outcome"]["outcome"] == "welded"
        assert summary["in_band_pct"] >= 95.0, summary
        what = f"welded, {summary['in_band_pct']:.1f} % in band"
    else:
        what = (f"{summary['seconds']:.0f} s of the job: drives enabled, every sensor "
                f"delivering, safe stop confirmed (CHCOS_UML_WELD_FULL=1: the whole seam)")
    request.config.stash.setdefault(GUEST_RESULTS, []).append(
        f"welding job (good gap) over vcan0/vcan1 inside UML: {what}, {wall:.0f} s from boot "
        f"to halt")
