"""scheduling - the clock interface of the NBS executor, and a deterministic one for tests.

:class:`Scheduler` is what :class:`chcos.apps.nbs.executor.NbsExecutor` needs of time (``now()``
and ``every(period, fn)``); :class:`RunnableScheduler` also runs until a time. The chcos kernel
supplies one (:class:`chcos.apps.nbs.adapter.KernelScheduler`); :class:`VirtualScheduler` is a
virtual clock with a timer heap, for tests and the figure 6.7 comparison.

Errors: :class:`~chcos.errors.KernelError` for a period that is not > 0 or a time in the past.
"""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from chcos.errors import KernelError

__all__ = ["Cancellable", "RunnableScheduler", "Scheduler", "VirtualScheduler", "VirtualTimer"]

_EPSILON = 1e-9  # virtual timers due within 1 ns of a deadline count as due (float rounding)


class Cancellable(Protocol):
    """A registered timer."""

    def cancel(self) -> None:
        """Stop the timer; calling it again does nothing."""


class Scheduler(Protocol):
    """The clock interface the executor needs; the chcos kernel supplies one."""

    def now(self) -> float:
        """Current time in seconds."""

    def every(self, period: float, fn: Callable[[], None]) -> Cancellable:
        """Call ``fn`` at now+period, now+2*period, ... until cancelled."""


class RunnableScheduler(Scheduler, Protocol):
    """A scheduler that can be driven for a span of time (virtual time in tests, benchmarks)."""

    def run_until(self, when: float) -> int:
        """Fire everything due up to ``when``; return how many callbacks ran."""


@dataclass(eq=False)
class VirtualTimer:
    """A timer armed on a :class:`VirtualScheduler` (one-shot when ``period`` is None)."""

    fn: Callable[[], None]
    origin: float
    period: float | None
    seq: int = 0
    k: int = 1
    cancelled: bool = False

    def cancel(self) -> None:
        """Stop the timer; calling it again does nothing."""
        self.cancelled = True

    def due(self) -> float:
        """When the timer fires next."""
        if self.period is None:
            return self.origin
        return self.origin + self.k * self.period


class VirtualScheduler:
    """A deterministic scheduler: a virtual clock and a heap of timers.

    Periodic timers fire at ``origin + k*period`` (computed afresh, so no drift accumulates);
    timers due at the same time fire in the order they were first armed. Time moves only in
    :meth:`run_until`. Exceptions from callbacks propagate (the clock stays at that callback).
    """

    def __init__(self, start: float = 0.0) -> None:
        self._now = start
        self._heap: list[tuple[float, int, VirtualTimer]] = []
        self._seq = itertools.count()

    def now(self) -> float:
        """Current virtual time in seconds."""
        return self._now

    def every(self, period: float, fn: Callable[[], None]) -> VirtualTimer:
        """Call ``fn`` every ``period`` seconds, first at now+period. Raises KernelError for
        a period that is not positive."""
        if not period > 0:
            raise KernelError(f"VirtualScheduler.every: period must be > 0 s, got {period!r}")
        timer = VirtualTimer(fn, self._now, period, next(self._seq))
        self._push(timer)
        return timer

    def call_at(self, when: float, fn: Callable[[], None]) -> VirtualTimer:
        """Call ``fn`` once at ``when`` (not before now). Raises KernelError for a past time."""
        if when < self._now - _EPSILON:
            raise KernelError(f"VirtualScheduler.call_at: {when} s is before now ({self._now} s)")
        timer = VirtualTimer(fn, when, None, next(self._seq))
        self._push(timer)
        return timer

    def _push(self, timer: VirtualTimer) -> None:
        heapq.heappush(self._heap, (timer.due(), timer.seq, timer))

    def run_until(self, when: float) -> int:
        """Fire every timer due up to ``when`` in time order, then set the clock to ``when``."""
        fired = 0
        while self._heap and self._heap[0][0] <= when + _EPSILON:
            due, _, timer = heapq.heappop(self._heap)
            if timer.cancelled:
                continue
            self._now = max(self._now, due)
            if timer.period is not None:
                timer.k += 1
                self._push(timer)
            timer.fn()
            fired += 1
        self._now = max(self._now, when)
        return fired

    def run_for(self, seconds: float) -> int:
        """:meth:`run_until` ``now() + seconds``."""
        return self.run_until(self._now + seconds)
