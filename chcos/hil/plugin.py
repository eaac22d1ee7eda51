"""plugin - the HIL evidence in the chcos pytest plugin (:mod:`chcos.testing` re-exports the
hooks): ``--chcos-coverage[=FILE.json]``, ``--chcos-coverage-fail-under=PERCENT`` and
``--chcos-update-golden``, the watch on every ``chcos_cell`` (its trace, its coverage), the
terminal table and the golden-trace assertion.

Every cell a test builds is watched from before its install script (:class:`CellWatch`: an
:class:`chcos.hil.observe.Observer` with a :class:`chcos.hil.trace.TraceRecorder`, and with
coverage on a :class:`chcos.hil.coverage.CellCoverage` that also polls the drivers' bus status);
when the test's cells are shut down, their coverage joins the session's. The session's coverage
goes to the terminal (a table, the share of the catalogue reached) and to the JSON file; below
the threshold the session fails. Under pytest-xdist each worker sends its coverage to the
controller, which writes the file. Nothing here imports chcos until it is used.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from chcos.cli.cellsystem import Cell
    from chcos.hil.coverage import CellCoverage, Coverage
    from chcos.hil.observe import Observer
    from chcos.hil.trace import Trace, TraceRecorder

#: the coverage file written by a bare ``--chcos-coverage``
DEFAULT_FILE = "chcos-coverage.json"
#: seconds of clock time between two reads of the drivers' bus status (coverage only)
POLL = 0.02
_COVERAGE = pytest.StashKey["Coverage"]()
_WORKER_KEY = "chcos_coverage"


def pytest_addoption(parser: pytest.Parser) -> None:
    """The plugin's options (group ``chcos``)."""
    group = parser.getgroup("chcos", "chcos cells: HIL evidence")
    group.addoption("--chcos-coverage", nargs="?", const=DEFAULT_FILE, default=None,
                    metavar="FILE.json",
                    help="record which device states (status, failure causes, safe values, NMT, "
                         "EMCY, CiA 402, bus states, task ends) the tests' cells reached; a "
                         f"table in the summary, everything in FILE.json (default {DEFAULT_FILE})")
    group.addoption("--chcos-coverage-fail-under", type=float, default=None, metavar="PERCENT",
                    help="fail the session if less than PERCENT of the catalogued device states "
                         "were reached (records coverage; the file only with --chcos-coverage)")
    group.addoption("--chcos-update-golden", action="store_true", default=False,
                    help="write the golden traces that cell.assert_golden() and chcos_golden "
                         "compare against, instead of comparing")


def _enabled(config: pytest.Config) -> bool:
    return (config.getoption("--chcos-coverage") is not None
            or config.getoption("--chcos-coverage-fail-under") is not None)


def pytest_configure(config: pytest.Config) -> None:
    """With coverage on: the session's coverage, gathered from every test's cells."""
    if _enabled(config):
        from chcos.hil.coverage import Coverage

        config.stash[_COVERAGE] = Coverage()


def session_coverage(config: pytest.Config) -> Coverage | None:
    """The session's coverage (None when it is not recorded)."""
    return config.stash.get(_COVERAGE, None)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: Any) -> None:
    """pytest-xdist: a worker is done; its coverage joins the controller's."""
    cov = session_coverage(node.config)
    doc = getattr(node, "workeroutput", {}).get(_WORKER_KEY)
    if cov is not None and doc:
        cov.merge_json(json.loads(doc))


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Write the coverage file (a worker sends it to the controller instead) and fail the
    session below the threshold."""
    config = session.config
    cov = session_coverage(config)
    if cov is None:
        return
    root = Path(config.rootpath)
    workeroutput = getattr(config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput[_WORKER_KEY] = json.dumps(cov.to_json(root))
        return
    target = config.getoption("--chcos-coverage")
    if target is not None:
        path = Path(target)
        path = path if path.is_absolute() else Path(config.invocation_params.dir) / path
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(cov.to_json(root), indent=1) + "\n", encoding="utf-8")
    limit = config.getoption("--chcos-coverage-fail-under")
    if limit is not None and cov.share() < limit and session.exitstatus == 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int,
                            config: pytest.Config) -> None:
    """The coverage table, the share reached, the file, and the threshold's verdict."""
    cov = session_coverage(config)
    if cov is None or getattr(config, "workeroutput", None) is not None:
        return
    from chcos.hil.coverage import table_lines

    tr = terminalreporter
    tr.write_sep("-", "chcos device-state coverage")
    for line in table_lines(cov, verbose=config.getoption("verbose") > 0):
        tr.write_line(line)
    target = config.getoption("--chcos-coverage")
    if target is not None:
        tr.write_line(f"coverage file: {target} (the states, the tests that reached each)")
    limit = config.getoption("--chcos-coverage-fail-under")
    if limit is not None:
        share = cov.share()
        verdict = "FAIL" if share < limit else "met"
        tr.write_line(f"--chcos-coverage-fail-under={limit:g}: {verdict} "
                      f"({share:.1f} % reached)", red=share < limit, green=share >= limit)


# ---- one test's cells -------------------------------------------------------------------------
class CellWatch:
    """One cell watched from its start: its observer, its trace and (with coverage) its
    coverage."""

    def __init__(self, cell: Cell, test_id: str, coverage: bool, root: Path,
                 update_golden: bool) -> None:
        from chcos.hil.coverage import CellCoverage
        from chcos.hil.observe import Observer
        from chcos.hil.trace import TraceRecorder

        self.cell = cell
        self.root = root
        self.update_golden = update_golden
        self.recorder: TraceRecorder = TraceRecorder(system=cell.sf.name,
                                                     clock="virtual" if cell.virtual else "real")
        self.coverage: CellCoverage | None = (CellCoverage(cell.system, test_id) if coverage
                                              else None)
        self.observer: Observer = Observer(cell.system, start=cell.start,
                                           poll=POLL if coverage else None)
        self.observer.sinks.append(self.recorder)
        if self.coverage is not None:
            self.observer.sinks.append(self.coverage)
        self.observer.attach()

    def trace(self) -> Trace:
        """The cell's trace so far (a copy)."""
        from chcos.hil.trace import Trace

        t = self.recorder.trace
        return Trace(dict(t.header), list(t.entries), f"trace of {self.cell.sf.name}")

    def assert_golden(self, golden: str | Path, *,
                      tolerance: Mapping[str, float] | None = None, text: bool = False) -> None:
        """:func:`check_golden` of the trace so far against ``golden`` (relative to the pytest
        root directory)."""
        path = Path(golden)
        check_golden(self.trace(), path if path.is_absolute() else self.root / path,
                     update=self.update_golden, tolerance=tolerance, text=text)


class Evidence:
    """The cells of one test (``chcos_cell``'s): each watched from its start (:meth:`watch`,
    the cell's ``observe`` hook), their coverage added to the session's at :meth:`finish`
    (after the cells are shut down: their safe values at shutdown count)."""

    def __init__(self, request: pytest.FixtureRequest) -> None:
        self.config = request.config
        self.test_id = request.node.nodeid
        self.watches: list[CellWatch] = []

    def watch(self, cell: Cell) -> None:
        """Watch ``cell`` from now on (before its install script runs)."""
        self.watches.append(CellWatch(cell, self.test_id,
                                      session_coverage(self.config) is not None,
                                      Path(self.config.rootpath),
                                      bool(self.config.getoption("--chcos-update-golden"))))

    def watch_of(self, cell: Cell) -> CellWatch:
        """The watch of ``cell`` (made by :meth:`watch`)."""
        return next(w for w in self.watches if w.cell is cell)

    def finish(self) -> None:
        """Stop watching; every cell's coverage joins the session's."""
        cov = session_coverage(self.config)
        for w in self.watches:
            w.observer.detach()
            if cov is not None and w.coverage is not None:
                cov.add_cell(w.coverage)


# ---- golden traces ----------------------------------------------------------------------------
def check_golden(trace: Trace, golden: str | Path, *, update: bool,
                 tolerance: Mapping[str, float] | None = None, text: bool = False) -> None:
    """Compare ``trace`` with the golden trace file ``golden`` (:func:`chcos.hil.diff.compare`);
    with ``update`` write it there instead. Raises AssertionError with the first divergences
    (or saying how to write a missing golden file)."""
    from chcos.hil.diff import compare, report_lines
    from chcos.hil.trace import TraceError, read_trace

    path = Path(golden)
    if update:
        trace.write(path)
        return
    if not path.exists():
        raise AssertionError(f"no golden trace {path}: write it with pytest "
                             "--chcos-update-golden (and commit it)")
    try:
        stored = read_trace(path)
    except TraceError as exc:
        raise AssertionError(str(exc)) from exc
    result = compare(stored, trace, tolerance, text=text)
    if not result.same:
        raise AssertionError("the run parts from its golden trace (pytest --chcos-update-golden "
                             "writes the new one, if the change is meant):\n"
                             + "\n".join(report_lines(result)))


@pytest.fixture
def chcos_golden(request: pytest.FixtureRequest) -> Any:
    """``chcos_golden(trace, golden_file, tolerance=None, text=False)``: assert that a trace (a
    :class:`chcos.hil.trace.Trace`, or the path of a trace file) matches the golden trace file
    (relative paths start at the pytest root directory); with ``--chcos-update-golden`` the
    golden file is written instead. Raises AssertionError naming the first divergences."""
    update = bool(request.config.getoption("--chcos-update-golden"))
    root = Path(request.config.rootpath)

    def check(trace: Trace | str | Path, golden: str | Path, *,
              tolerance: Mapping[str, float] | None = None, text: bool = False) -> None:
        from chcos.hil.trace import read_trace

        t = read_trace(trace) if isinstance(trace, str | Path) else trace
        path = Path(golden)
        check_golden(t, path if path.is_absolute() else root / path, update=update,
                     tolerance=tolerance, text=text)

    return check
