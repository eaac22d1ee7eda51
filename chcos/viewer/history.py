"""history - each device's recent values for the live view: a sparkline per device on the page
and the same data as CSV (``/api/history.csv``).

:class:`History` keeps, per device with a numeric value, samples (seconds since the start on the
system's clock, value) taken by the viewer once per ``every`` seconds of that clock, for the last
``window`` seconds (at most ``keep`` samples per device). It is filled from the viewer's own
snapshots, so it costs the kernel nothing, and it records from the viewer's start whether or not
a page is open.
"""

from __future__ import annotations

import csv
import io
import math
import threading
from collections import deque
from collections.abc import Iterable
from typing import Any

WINDOW = 600.0
"""Seconds of history kept by default (the last ten minutes)."""


class History:
    """Recent (time, value) samples per device; thread-safe (see the module doc)."""

    def __init__(self, window: float = WINDOW, every: float = 1.0, keep: int = 3600) -> None:
        if not (window > 0 and every > 0 and keep > 0):
            raise ValueError("history: window, every and keep must be positive")
        self.window = window
        self.every = every
        self.keep = keep
        self._lock = threading.Lock()
        self._series: dict[str, deque[tuple[float, float]]] = {}
        self._last: float | None = None

    def due(self, now: float) -> bool:
        """True if a sample is due at clock time ``now`` (``every`` seconds after the last)."""
        return self._last is None or now - self._last >= self.every - 1e-9

    def sample(self, now: float, devices: Iterable[dict[str, Any]]) -> None:
        """Record each device's ``value`` at ``now`` (numbers and booleans; others skipped),
        dropping samples older than ``window``. A time not after the last sample's is ignored
        (the clock has not moved)."""
        with self._lock:
            if self._last is not None and now <= self._last:
                return
            self._last = now
            for d in devices:
                v = d.get("value")
                if isinstance(v, bool):
                    v = float(v)
                if not isinstance(v, int | float) or not math.isfinite(v):
                    continue
                s = self._series.get(d["name"])
                if s is None:
                    s = self._series[d["name"]] = deque(maxlen=self.keep)
                s.append((now, float(v)))
            for s in self._series.values():
                while s and s[0][0] < now - self.window:
                    s.popleft()

    def series(self) -> dict[str, list[tuple[float, float]]]:
        """Every device's samples, oldest first."""
        with self._lock:
            return {name: list(s) for name, s in sorted(self._series.items())}

    def as_json(self) -> dict[str, Any]:
        """``{"window": s, "devices": {name: [[t, v], ...]}}`` for the page."""
        return {"window": self.window,
                "devices": {n: [[t, v] for t, v in s] for n, s in self.series().items()}}

    def as_csv(self) -> str:
        """The samples as CSV: a ``time_s,device,value`` header, then one row per sample in
        time order."""
        rows = sorted((t, name, v) for name, s in self.series().items() for t, v in s)
        out = io.StringIO()
        w = csv.writer(out, lineterminator="\n")
        w.writerow(["time_s", "device", "value"])
        for t, name, v in rows:
            w.writerow([f"{t:.3f}", name, repr(v)])
        return out.getvalue()
