"""clock - the kernel's injected clock: real time for running cells, virtual time for tests.

The kernel asks the clock for the time and hands it the idle wait. A :class:`VirtualClock` never
waits: when every task is blocked and nothing is in flight it jumps straight to the next timer, so
time-dependent behaviour is exact and a test of minutes runs in milliseconds (as trio's MockClock).
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod


class Clock(ABC):
    """What the kernel needs from a clock."""

    virtual: bool = False

    @abstractmethod
    def now(self) -> float:
        """Current time in seconds (monotonic; origin is the clock's own)."""

    @abstractmethod
    def idle(self, wake: threading.Event, deadline: float | None) -> None:
        """Block the kernel thread until ``wake`` is set or ``deadline`` (clock time) passes.

        ``deadline`` None means no timer is pending. A virtual clock instead advances to
        ``deadline`` (the kernel calls it only when nothing can happen before then).
        """


class RealClock(Clock):
    """Wall-clock time from :func:`time.monotonic`; idles on the interrupt event."""

    #: Seconds from :func:`time.monotonic` (the C function itself: read several times per
    #: message, a Python wrapper around it would cost a frame each time).
    now = staticmethod(time.monotonic)

    def idle(self, wake: threading.Event, deadline: float | None) -> None:
        """Wait on ``wake`` until the deadline (or forever if there is none)."""
        if deadline is None:
            wake.wait()
        else:
            delay = deadline - time.monotonic()
            if delay > 0:
                wake.wait(delay)


class VirtualClock(Clock):
    """Simulated time that jumps ahead whenever the whole system is idle.

    ``start`` is the initial time. :meth:`advance` may also be called by a test between runs.
    """

    virtual = True

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)

    def now(self) -> float:
        """The current virtual time."""
        return self._t

    def advance(self, dt: float) -> None:
        """Move time forward by ``dt`` seconds; raises ValueError for a negative step."""
        if dt < 0:
            raise ValueError(f"virtual clock cannot go back ({dt} s)")
        self._t += dt

    def jump_to(self, t: float) -> None:
        """Move time to ``t`` if that is later than now (never backwards)."""
        self._t = max(self._t, t)

    def idle(self, wake: threading.Event, deadline: float | None) -> None:
        """Jump to the deadline; with none, wait for an interrupt from a device thread."""
        if deadline is None:
            wake.wait()
        else:
            self.jump_to(deadline)
