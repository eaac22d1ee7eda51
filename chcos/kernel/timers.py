"""timers - the kernel's timers (the thesis' delta list, kept as a heap of deadlines) and the
errors it collects from the callbacks it runs: a timer callback or interrupt handler that raises
is logged and kept, and :meth:`Timers.check` raises it later."""

from __future__ import annotations

import logging
import traceback
from collections import deque
from collections.abc import Callable
from heapq import heappop, heappush

from chcos.errors import HandlerError
from chcos.kernel.clock import Clock

log = logging.getLogger("chcos.kernel.scheduler")

#: How many collected handler errors the kernel keeps.
KEEP_ERRORS = 100



class Timer:
    """A pending timer; :meth:`cancel` makes it a no-op. Created by :meth:`Kernel.call_at`."""

    __slots__ = ("base", "callback", "cancelled", "count", "deadline", "period")

    def __init__(self, deadline: float, callback: Callable[[], None], period: float | None) -> None:
        self.deadline = deadline
        self.base = deadline
        self.count = 0
        self.callback = callback
        self.period = period
        self.cancelled = False

    def cancel(self) -> None:
        """Stop the timer from firing (again)."""
        self.cancelled = True


class Timers:
    """Timers and collected errors for :class:`chcos.kernel.scheduler.Kernel` (its base)."""

    clock: Clock
    _seq: int
    _timers: list[tuple[float, int, Timer]]
    irq_errors: list[str]
    _unchecked: deque[HandlerError]

    def call_at(self, deadline: float, callback: Callable[[], None],
                period: float | None = None) -> Timer:
        """Run ``callback`` on the kernel thread at clock time ``deadline`` (and every ``period``
        seconds after, drift-free, if given). Raises ValueError for a non-positive period."""
        if period is not None and period <= 0:
            raise ValueError(f"timer period must be positive, got {period}")
        tm = Timer(deadline, callback, period)
        self._seq += 1
        heappush(self._timers, (deadline, self._seq, tm))
        return tm

    def call_later(self, delay: float, callback: Callable[[], None]) -> Timer:
        """Run ``callback`` once, ``delay`` seconds from now."""
        return self.call_at(self.clock.now() + delay, callback)

    def every(self, period: float, callback: Callable[[], None]) -> Timer:
        """Run ``callback`` every ``period`` seconds, the first time one period from now."""
        return self.call_at(self.clock.now() + period, callback, period)

    def _fire_timers(self, now: float) -> None:
        timers = self._timers
        while timers and timers[0][0] <= now:
            _, _, tm = heappop(timers)
            if tm.cancelled:
                continue
            if tm.period is not None:
                tm.count += 1
                # no accumulated rounding; whole nanoseconds so k * period lands on k * period
                tm.deadline = round(tm.base + tm.count * tm.period, 9)
                self._seq += 1
                heappush(timers, (tm.deadline, self._seq, tm))
            try:
                tm.callback()
            except Exception as exc:  # a failing timer callback must not stop the kernel
                self._record_irq_error("timer", exc)

    def _record_irq_error(self, where: str, exc: Exception) -> None:
        text = f"{where}: {type(exc).__name__}: {exc}"
        log.error("interrupt handler failed: %s\n%s", text, traceback.format_exc())
        self.irq_errors.append(text)
        del self.irq_errors[:-KEEP_ERRORS]
        err = HandlerError(f"{where} failed on the kernel thread: {type(exc).__name__}: {exc}")
        err.__cause__ = exc
        self._unchecked.append(err)

    def check(self) -> None:
        """Raise the oldest error collected on the kernel thread and not raised yet: a
        :class:`HandlerError` naming the interrupt handler or timer callback that failed, its
        exception chained as the cause, with how many more are waiting. Each collected error
        is raised once (the texts stay in :attr:`irq_errors`). Thread-safe; returns quietly
        when nothing failed."""
        try:
            err = self._unchecked.popleft()
        except IndexError:
            return
        more = len(self._unchecked)
        if more:
            err.add_note(f"{more} more handler error(s) collected; check() again")
        raise err
