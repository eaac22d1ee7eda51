"""Shared fixtures (a system on virtual time with in-memory devices) and the suite's rules:
``require`` for environment needs (skip locally, fail under CI=true), ``opt_in`` for long runs
(the only skips allowed under CI), socketcan tests moved to the UML guest, a summary of both."""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import settings

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from vcan_tests.support_env import OPT_IN, opt_in, require, under_ci  # noqa: F401 (tests import them from here)

# no property test depends on the machine's speed: hypothesis' per-example deadline (200 ms) is
# a wall-clock limit that a loaded machine (two workers, other jobs) overruns
settings.register_profile("chcos", deadline=None)
settings.load_profile("chcos")

MakeSystem = Callable[..., System]


def memory_map(sensors: dict[str, int] | list[str] = (), actuators: dict[str, float | None]
               | list[str] = (), **device_kw: object) -> DeviceMap:
    """A device map of in-memory sensors and actuators on machine 0 (actuators: name -> safe
    value)."""
    bus = BusSpec("mem", "memory")
    devs = []
    for name in sensors:
        devs.append(DeviceSpec(name, "sensor", 0, "mem", **device_kw))  # type: ignore[arg-type]
    acts = actuators if isinstance(actuators, dict) else dict.fromkeys(actuators, 0.0)
    for name, safe in acts.items():
        devs.append(DeviceSpec(name, "actuator", 0, "mem", safe_value=safe, limits=(-100, 100)))
    return DeviceMap((bus,), tuple(devs))


@pytest.fixture
def make_system(tmp_path: Path) -> Iterator[MakeSystem]:
    """Build Systems on a VirtualClock, booted on machine 0, shut down after the test."""
    made: list[System] = []

    def make(devmap: DeviceMap | None = None, machines: tuple[int, ...] = (0,),
             **kw: object) -> System:
        s = System(devmap if devmap is not None else DeviceMap(), clock=VirtualClock(),
                   machines=machines, base_dir=tmp_path, map_path=tmp_path / "sysfile.map",
                   **kw)  # type: ignore[arg-type]
        made.append(s)
        return s

    yield make
    for s in made:
        s.shutdown()


@pytest.fixture(scope="session")
def good_gap_job(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """The welding job on a good gap, direct binding, no fault, run ONCE for the session
    (a :class:`vcan_tests.support_weldcell.JobRun`): several tests check different facts of
    this same deterministic run, on virtual time. ``extra`` holds, taken once the job is
    over: ``sent`` (messages sent per link ``src->dst``), ``steps`` (every task's steps) and
    ``secs`` (virtual seconds since the job started). Tests only read it."""
    from vcan_tests.support_weldcell import run_job

    def facts(cell: Any) -> dict[str, Any]:
        s = cell.system
        return {"sent": {f"{lk.src}->{lk.dst}": lk.sent for lk in s.msgtab},
                "steps": {t.name: t.steps for t in s.tsktab},
                "secs": s.kernel.clock.now() - cell.started}

    return run_job("direct", "", tmp=tmp_path_factory.mktemp("good-gap"), after=facts)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Start the long User-Mode-Linux runs of the selected tests marked ``uml_background`` (their
    module's ``start_in_background(config)``) now, so they overlap the rest of the session on
    the other core; each test then waits for its run's result."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        return  # each worker collects every test: the test itself starts its run when it runs
    for item in session.items:
        if isinstance(item, pytest.Function) and item.get_closest_marker("uml_background"):
            start = getattr(item.module, "start_in_background", None)
            if start is not None:
                start(item.config)


def pytest_sessionfinish(session: pytest.Session) -> None:
    """Stop background UML runs nobody collected (the session was interrupted)."""
    from vcan_tests.uml import BACKGROUND

    for run, _workdir in session.config.stash.get(BACKGROUND, {}).values():
        run.kill()


# -- environment requirements, opt-in runs, and what ran where ------------------------------------
# (require, opt_in, under_ci: vcan_tests.support_env, which the helpers import without a circle)

@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[None]:
    """Under CI a skip that is not an opt-in run (:func:`opt_in`) is a failure: whatever
    skipped it (``pytest.skip``, ``skipif``, ``importorskip``) found the environment
    incomplete."""
    outcome = yield
    report: pytest.TestReport = outcome.get_result()
    if not (under_ci() and report.skipped and not hasattr(report, "wasxfail")):
        return
    reason = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    if OPT_IN not in reason:
        report.outcome = "failed"
        report.longrepr = (f"skipped under CI=true, where only opt-in runs may skip: {reason}\n"
                           "(declare environment needs with vcan_tests.conftest.require)")


_SOCKETCAN_HERE = pytest.StashKey[list[str]]()


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests marked ``socketcan`` need vcan0; in a process without it (the host, whose kernel
    has no CAN) they are deselected: ``test_uml_socketcan.py`` runs them inside the guest, and
    the terminal summary says so."""
    from vcan_tests.uml import socketcan_channel

    if socketcan_channel() is not None:
        return
    keep, moved = [], []
    for item in items:
        (moved if item.get_closest_marker("socketcan") else keep).append(item)
    if moved:
        config.hook.pytest_deselected(items=moved)
        items[:] = keep
        config.stash[_SOCKETCAN_HERE] = [item.nodeid for item in moved]


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """Say what ran where: socketcan tests moved to the guest, and what the guest runs gave."""
    from vcan_tests.uml import GUEST_RESULTS

    moved = config.stash.get(_SOCKETCAN_HERE, [])
    results = config.stash.get(GUEST_RESULTS, [])
    if not moved and not results:
        return
    terminalreporter.section("real SocketCAN (vcan0/vcan1 in a User-Mode-Linux guest)")
    if moved:
        guest = "test_uml_socketcan.py::test_socketcan_suite_passes_inside_uml"
        selected = any(guest in i.nodeid for i in terminalreporter.stats.get("passed", [])
                       + terminalreporter.stats.get("failed", []))
        terminalreporter.write_line(
            f"{len(moved)} socketcan tests deselected in this process (no vcan0 here); they run "
            f"in the guest through {guest}" + ("" if selected else " (not run this time)"))
    for line in results:
        terminalreporter.write_line(line)


def pytest_configure(config: pytest.Config) -> None:
    """Run state (satellites' maps, logs and secrets, run reports, learned data) goes to a
    directory of this session, never to the user's ~/.local/state: CHCOS_STATE_DIR is set for
    the whole session (and every process it starts) unless the caller set it."""
    worker = os.environ.get("PYTEST_XDIST_WORKER")
    if not os.environ.get("CHCOS_STATE_DIR"):
        os.environ["CHCOS_STATE_DIR"] = tempfile.mkdtemp(prefix="chcos-test-state-")
        os.environ["CHCOS_TEST_STATE"] = "session"  # ours: a worker takes one of its own
    elif worker and os.environ.get("CHCOS_TEST_STATE") == "session":
        # a pytest-xdist worker: its own state directory, so that two tests on two workers
        # never share a system's state (the weld cell's report, a satellite's map)
        os.environ["CHCOS_STATE_DIR"] = tempfile.mkdtemp(prefix=f"chcos-test-state-{worker}-")
