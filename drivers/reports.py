"""reports - bus errors reported once per streak, with counts, instead of once per event.

A device that refuses the same request at every poll (exception 2 ten times a second) is one
condition, not ten warnings a second. :class:`Reports` reports the first error of a streak -
one ``(kind, subject)``, e.g. ``("exception-2", "unit 1 holding 5..5")`` - through
``host.error`` (counted, the bus's last error, a WARNING), counts the repeats silently
(``host.stat(..., error=True)``: the statistics stay exact), logs one WARNING with the count
per ``period`` of the kernel clock while the streak goes on, and one line when it ends
(:meth:`Reports.ok`). Used by the Modbus drivers; any driver with recurring errors can take it.
"""

from __future__ import annotations

import logging
import threading
from dataclasses import dataclass

from drivers.base import DriverHost

log = logging.getLogger("chcos.drivers.reports")
#: seconds of the kernel clock between two reports of a streak that goes on
PERIOD = 10.0


@dataclass
class _Streak:
    since: float
    reported_at: float
    repeats: int = 0       # since the last report
    total: int = 1
    detail: str = ""


class Reports:
    """The streaks of errors of one bus (see the module doc). Thread-safe."""

    def __init__(self, host: DriverHost, bus: str, period: float = PERIOD) -> None:
        self._host = host
        self._bus = bus
        self.period = period
        self._lock = threading.Lock()
        self._streaks: dict[tuple[str, str], _Streak] = {}

    def error(self, kind: str, subject: str, detail: str, device: str = "") -> None:
        """An error of class ``kind`` about ``subject`` (``detail`` says what happened): the
        first of a streak is reported, the others counted (and summed up each period)."""
        now = self._host.now()
        key = (kind, subject)
        summary: tuple[int, int, float] | None = None
        with self._lock:
            s = self._streaks.get(key)
            if s is None:
                self._streaks[key] = _Streak(now, now, detail=detail)
            else:
                s.repeats += 1
                s.total += 1
                s.detail = detail
                if now - s.reported_at >= self.period:
                    summary = (s.repeats, s.total, s.since)
                    s.repeats, s.reported_at = 0, now
        if s is None:
            self._host.error(self._bus, kind, detail, device)
            return
        self._host.stat(self._bus, kind, 1, device, error=True)
        if summary is not None:
            log.warning("bus %s: %s: %s: %d more since the last report (%d since t=%.1f s); "
                        "last: %s", self._bus, kind, subject, *summary, detail)

    def ok(self, subject: str) -> None:
        """``subject`` works again: every streak about it ends (one line each, if it had
        repeats)."""
        if not self._streaks:
            return
        with self._lock:
            ended = [(k, s) for k, s in self._streaks.items() if k[1] == subject]
            for k, _ in ended:
                del self._streaks[k]
        for (kind, _), s in ended:
            if s.total > 1:
                log.warning("bus %s: %s: %s: ended after %d error(s) since t=%.1f s", self._bus,
                            kind, subject, s.total, s.since)

    def flush(self) -> None:
        """At stop: report the counts not yet reported."""
        with self._lock:
            items = [(k, s) for k, s in self._streaks.items() if s.repeats]
            for _, s in items:
                s.repeats = 0
        for (kind, subject), s in items:
            log.warning("bus %s: %s: %s: %d error(s) since t=%.1f s, still going on at stop; "
                        "last: %s", self._bus, kind, subject, s.total, s.since, s.detail)
