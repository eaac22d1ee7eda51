"""mapfile - when sysfile.map is written: atomically, soon after a change, never in a burst.

sysfile.map is written atomically after a change, at most every MAP_MIN_GAP seconds (and at
least MAP_COST_FACTOR write-durations apart, so a burst of N installs costs O(N), not O(N²));
the change still unwritten is written when the script ends, when the kernel goes idle or
``run`` returns, on ``map`` and at shutdown, or by a timer MAP_MIN_GAP later. A crash can
therefore lose the last fraction of a second of changes, never leave a map that does not
rebuild a system: every map on disk is a whole one (temporary file, fsync, rename; see
:func:`chcos.system.sysmap.write`).

The map is a record, never a reason to stop the cell: a write that fails (a full disk, a
directory that is not writable) raises nothing into the kernel or the command that changed
the tables; :attr:`MapFile.error` then says, in one line naming the file and the error
(``cannot write /run/cell/sysfile.map: No space left on device (ENOSPC)``), what could not be
written, that line is logged once (and once more when a write succeeds again), the change is
kept as unwritten and tried again at the next occasion. ``chcos run`` puts it in its summary,
``chcos shell`` prints it and ends with status 1.
"""

from __future__ import annotations

import errno
import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from chcos.system import sysmap

log = logging.getLogger("chcos.system.mapfile")

MAP_MIN_GAP = 0.25      # seconds between two sysfile.map writes during a burst of changes
MAP_COST_FACTOR = 10.0  # ... and at least this many times the last write's duration


class MapFile:
    """The map file at ``path`` (None: the system keeps no map), written from ``doc()``.
    ``interrupt(fn)`` runs ``fn`` on the kernel thread (the timer's writes go there)."""

    def __init__(self, path: Path | None, doc: Callable[[], dict[str, Any]],
                 interrupt: Callable[..., None]) -> None:
        self.path = path
        self.doc = doc
        self.interrupt = interrupt
        self.clock: Callable[[], float] = time.monotonic  # paces the writes
        self.writes = 0
        #: the last write's failure in one line (None: the last write succeeded, or none yet)
        self.error: str | None = None
        #: how many writes failed
        self.failures = 0
        self._dirty = False
        self._next = 0.0
        self._timer: threading.Timer | None = None

    def save(self) -> bool:
        """Write the map now (atomically); True if it was written. A failure raises nothing:
        it is in :attr:`error` (see the module doc) and the change stays unwritten."""
        if self.path is None:
            return True
        t0 = self.clock()
        self._dirty = True
        try:
            sysmap.write(self.path, self.doc())
        except OSError as exc:
            self._failed(exc)
            return False
        finally:
            t1 = self.clock()
            self._next = t1 + max(MAP_MIN_GAP, MAP_COST_FACTOR * (t1 - t0))
        self._dirty = False   # only once written: a failed write is tried again
        self.writes += 1
        if self.error is not None:
            log.warning("%s written again (after %d failed write(s))", self.path, self.failures)
            self.error = None
        return True

    def _failed(self, exc: OSError) -> None:
        self.failures += 1
        text = f"cannot write {self.path}: {describe_os_error(exc)}"
        if text != self.error:
            log.error("%s; the cell goes on, the map is written at the next change", text)
        self.error = text

    def changed(self) -> None:
        """The tables changed: write now if the last write is long enough ago (see the module
        doc), else leave it to :meth:`flush` (end of a script or run, an idle kernel, a
        timer). A failed write raises nothing (see :attr:`error`)."""
        if self.path is None:
            return
        self._dirty = True
        if self.clock() >= self._next:
            self.save()
        elif self._timer is None:
            delay = max(0.0, self._next - self.clock())
            timer = threading.Timer(delay, self.interrupt, (self._timed,))
            timer.daemon = True
            self._timer = timer
            timer.start()

    def flush(self) -> None:
        """Write the map if a change is not written yet (a failure: see :attr:`error`)."""
        if self._dirty:
            self.save()

    def _timed(self) -> None:
        """The timer armed by :meth:`changed`, run on the kernel thread: writes what waits (or
        arms itself again if it fired a little early)."""
        self._timer = None
        if self._dirty:
            self.changed()

    def on_idle(self) -> None:
        """Idle hook: write the map if a change waits and its time has come."""
        if self._dirty and self.clock() >= self._next:
            self.save()


def describe_os_error(exc: OSError) -> str:
    """An OSError in a few words with its symbolic name: ``No space left on device
    (ENOSPC)``."""
    name = errno.errorcode.get(exc.errno or 0)
    what = exc.strerror or str(exc)
    return f"{what} ({name})" if name else what
