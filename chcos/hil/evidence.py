"""evidence - the HIL evidence of one run (``chcos run --trace``, the welding job's report): the
run watched from its start, its trace written at the end, and what device states it reached.

:class:`RunEvidence` attaches an :class:`chcos.hil.observe.Observer` to a System before its
install script (the ``observe`` hook of :func:`chcos.cli.cellsystem.open_cell` and of the welding
cell), with a :class:`chcos.hil.trace.TraceRecorder` and, if asked, a
:class:`chcos.hil.coverage.CellCoverage`; :meth:`RunEvidence.finish` stops watching (after the
shutdown: its safe values are part of the run) and writes the trace files.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from chcos.hil.coverage import CellCoverage, Coverage
from chcos.hil.observe import Observer
from chcos.hil.trace import Trace, TraceError, TraceRecorder, write_mcap

if TYPE_CHECKING:
    from chcos.system.embedded import System

#: seconds of clock time between two reads of the drivers' bus status (with coverage)
POLL = 0.02


class RunEvidence:
    """One run's evidence: its trace, written at the end to each of ``paths`` (``.mcap``: MCAP,
    else the text format; ``.gz`` compressed), and with ``coverage`` the states it reached.
    ``header`` goes into the trace (``system``, ``clock``)."""

    def __init__(self, paths: Sequence[str | Path] = (), *, coverage: bool = False,
                 **header: str) -> None:
        self.paths = [Path(p) for p in paths]
        self.recorder = TraceRecorder(**header)
        self._coverage = coverage
        self.cell_coverage: CellCoverage | None = None
        self.observer: Observer | None = None

    def attach(self, system: System, start: float | None = None) -> None:
        """Watch ``system`` from clock time ``start`` (default: now) on."""
        self.observer = Observer(system, start=start, poll=POLL if self._coverage else None)
        self.observer.sinks.append(self.recorder)
        if self._coverage:
            self.cell_coverage = CellCoverage(system, "run")
            self.observer.sinks.append(self.cell_coverage)
        self.observer.attach()

    @property
    def trace(self) -> Trace:
        """The trace so far."""
        return self.recorder.trace

    def coverage(self) -> Coverage | None:
        """The states the run reached against its catalogue (None without ``coverage``)."""
        if self.cell_coverage is None:
            return None
        cov = Coverage()
        cov.add_cell(self.cell_coverage)
        return cov

    def finish(self) -> list[str]:
        """Stop watching and write every trace file; what could not be written, one line
        each."""
        if self.observer is not None:
            self.observer.detach()
        errors = []
        for p in self.paths:
            try:
                if p.suffix == ".mcap":
                    write_mcap(self.recorder.trace, p)
                else:
                    self.recorder.trace.write(p)
            except TraceError as exc:
                errors.append(str(exc))
        return errors
