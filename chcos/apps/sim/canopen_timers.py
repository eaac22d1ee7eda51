"""canopen_timers - the timers of a simulated CANopen node, pure and drift-free: each next due
time is the previous due time plus the period (never the late time it was noticed plus the
period), so that the n-th heartbeat or event-timer TPDO is due at exactly n periods whatever the
granularity of the clock that advances the node.

:class:`Periodic` is the heartbeat producer's; :class:`TpdoTimer` an event-driven TPDO's (its
event timer and its inhibit time, CiA 301 0x180n:05 and :03). Both are told the time
(:meth:`Periodic.fire`, :meth:`TpdoTimer.fire`) and say what came due by then; a clock that
advances by more than a period gets every due time it passed, up to :data:`CATCH_UP` at once (the
rest is skipped, the phase kept).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

#: Tolerance for due times built by adding periods (float sums of tick steps).
EPSILON = 1e-9
#: Due times one call returns at most; beyond, the timer skips to its next due time after now.
CATCH_UP = 100


@dataclass
class Periodic:
    """A timer due every ``period`` seconds from its start (``due`` None: stopped)."""

    period: float = 0.0
    due: float | None = None

    def start(self, now: float, period: float) -> None:
        """Run every ``period`` seconds, the first time one period after ``now`` (a period of
        0 or less stops it)."""
        self.period = period
        self.due = now + period if period > 0 else None

    def stop(self) -> None:
        """Stop the timer."""
        self.due = None

    def fire(self, now: float, limit: int = CATCH_UP) -> list[float]:
        """The due times reached by ``now`` (oldest first, ``limit`` at most: the timer skips
        the others, keeping its phase), the timer moved past them."""
        times: list[float] = []
        due = self.due
        while due is not None and due <= now + EPSILON:
            if len(times) == limit:
                due += self.period * (math.floor((now - due) / self.period) + 1)
                break
            times.append(due)
            due += self.period
        self.due = due
        return times


@dataclass
class TpdoTimer:
    """When an event-driven TPDO (transmission type 254/255) goes out, in node time: on a change
    of a mapped value, unless within ``inhibit`` seconds of its last transmission (then at the
    end of the inhibit time), and ``event`` seconds after its last transmission (the event
    timer: the longest interval between two; None: no event timer). The event timer runs from
    :meth:`configure` on; every transmission restarts it from the time it was due."""

    inhibit: float = 0.0
    event: float | None = None
    last: float | None = None
    event_due: float | None = None
    pending: bool = False

    def configure(self, now: float, inhibit: float, event: float | None) -> None:
        """New parameters at ``now``: the event timer starts again, the last transmission is
        kept (its inhibit time still holds)."""
        self.inhibit = max(0.0, inhibit)
        self.event = event if event else None
        self.event_due = now + self.event if self.event else None

    def changed(self, now: float) -> bool:
        """A mapped value changed at ``now``: True if the TPDO goes out now (then call
        :meth:`sent`), False if the inhibit time holds it until :meth:`due`."""
        if self.last is not None and now < self.last + self.inhibit - EPSILON:
            self.pending = True
            return False
        return True

    def sent(self, at: float) -> None:
        """The TPDO went out at ``at``: the inhibit time and the event timer start from it."""
        self.last = at
        self.pending = False
        if self.event:
            self.event_due = at + self.event

    def due(self) -> float | None:
        """When the TPDO goes out next without a change (None: not before a change)."""
        times = [t for t in (self.event_due,
                             self.last + self.inhibit if self.pending and self.last is not None
                             else None) if t is not None]
        if not times:
            return None
        due = min(times)
        return max(due, self.last + self.inhibit) if self.last is not None else due

    def fire(self, now: float) -> list[float]:
        """The transmission times reached by ``now`` (oldest first), each recorded as sent."""
        times: list[float] = []
        while (due := self.due()) is not None and due <= now + EPSILON:
            if len(times) == CATCH_UP:
                if self.event and self.event_due is not None:
                    skipped = math.floor((now - self.event_due) / self.event) + 1
                    self.event_due += self.event * max(1, skipped)
                self.pending = False
                break
            times.append(due)
            self.sent(due)
        return times
