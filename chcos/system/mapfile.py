"""mapfile - when sysfile.map is written: atomically, soon after a change, never in a burst.

sysfile.map is written atomically after a change, at most every MAP_MIN_GAP seconds (and at
least MAP_COST_FACTOR write-durations apart, so a burst of N installs costs O(N), not O(N²));
the change still unwritten is written when the script ends, when the kernel goes idle or
``run`` returns, on ``map`` and at shutdown, or by a timer MAP_MIN_GAP later. A crash can
therefore lose the last fraction of a second of changes, never leave a map that does not
rebuild a system: every map on disk is a whole one (temporary file, fsync, rename; see
:func:`chcos.system.sysmap.write`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from chcos.system import sysmap

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
        self._dirty = False
        self._next = 0.0
        self._timer: threading.Timer | None = None

    def save(self) -> None:
        """Write the map now (atomically). Raises OSError if it cannot be written."""
        if self.path is None:
            return
        t0 = self.clock()
        sysmap.write(self.path, self.doc())
        self._dirty = False   # only once written: a failed write is tried again
        self.writes += 1
        t1 = self.clock()
        self._next = t1 + max(MAP_MIN_GAP, MAP_COST_FACTOR * (t1 - t0))

    def changed(self) -> None:
        """The tables changed: write now if the last write is long enough ago (see the module
        doc), else leave it to :meth:`flush` (end of a script or run, an idle kernel, a
        timer). Raises OSError if a write due now fails."""
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
        """Write the map if a change is not written yet. Raises OSError if it cannot be
        written."""
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
