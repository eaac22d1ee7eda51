"""timers - the kernel's timers (the thesis' delta list, kept as a heap of deadlines) and the
errors it collects from the callbacks it runs: a timer callback or interrupt handler that raises
is logged and kept, and :meth:`HandlerErrors.check` raises it later.

A periodic timer is drift-free: its k-th deadline is ``first + k * period``. When the kernel
comes back late (a long step, a stalled machine) and several of its deadlines have passed, it
fires once, not once per missed period: the periods it missed are skipped and counted
(:attr:`Timer.skipped`, :attr:`Timers.skipped_periods`), and its next deadline is the first
period boundary after now - as an RTOS' periodic task or ``trio``'s and ``asyncio``'s
schedulers do, so that a 20 kHz poll after a stall does not run hundreds of times back to back,
starving the tasks and control requests behind it."""

from __future__ import annotations

import logging
import traceback
from collections import deque
from collections.abc import Callable
from heapq import heappop, heappush, heapreplace

from chcos.errors import HandlerError
from chcos.kernel.clock import Clock

log = logging.getLogger("chcos.kernel.scheduler")

#: How many collected handler errors the kernel keeps.
KEEP_ERRORS = 100



class Timer:
    """A pending timer; :meth:`cancel` makes it a no-op. Created by :meth:`Kernel.call_at`."""

    __slots__ = ("base", "callback", "cancelled", "count", "deadline", "period", "skipped")

    def __init__(self, deadline: float, callback: Callable[[], None], period: float | None) -> None:
        self.deadline = deadline
        self.base = deadline
        self.count = 0
        self.callback = callback
        self.period = period
        self.cancelled = False
        #: periods of a periodic timer that passed without a call (see the module doc)
        self.skipped = 0

    def cancel(self) -> None:
        """Stop the timer from firing (again)."""
        self.cancelled = True


class HandlerErrors:
    """The errors collected on the kernel thread: an interrupt handler or timer callback that
    raises is logged and kept here, and :meth:`check` raises it later (the newest
    :data:`KEEP_ERRORS`)."""

    def __init__(self) -> None:
        #: text of every failed interrupt handler and timer callback (the newest KEEP_ERRORS)
        self.texts: list[str] = []
        self._unchecked: deque[HandlerError] = deque(maxlen=KEEP_ERRORS)

    def record(self, where: str, exc: Exception) -> None:
        """``where`` (a handler's name, or "timer") raised ``exc``: log it and keep it."""
        text = f"{where}: {type(exc).__name__}: {exc}"
        log.error("interrupt handler failed: %s\n%s", text, traceback.format_exc())
        self.texts.append(text)
        del self.texts[:-KEEP_ERRORS]
        err = HandlerError(f"{where} failed on the kernel thread: {type(exc).__name__}: {exc}")
        err.__cause__ = exc
        self._unchecked.append(err)

    def check(self) -> None:
        """Raise the oldest error collected and not raised yet: a :class:`HandlerError`
        naming the interrupt handler or timer callback that failed, its exception chained as
        the cause, with how many more are waiting. Each collected error is raised once (the
        texts stay in :attr:`texts`). Thread-safe; returns quietly when nothing failed."""
        try:
            err = self._unchecked.popleft()
        except IndexError:
            return
        more = len(self._unchecked)
        if more:
            err.add_note(f"{more} more handler error(s) collected; check() again")
        raise err


class Timers:
    """The kernel's timers, a heap of (deadline, sequence, :class:`Timer`) on ``clock``; a
    callback that raises is recorded in ``errors``. Owned by
    :class:`chcos.kernel.scheduler.Kernel`, which fires them between task steps."""

    def __init__(self, clock: Clock, errors: HandlerErrors) -> None:
        self.clock = clock
        self.errors = errors
        #: the pending timers, earliest first (ties: first come first)
        self.heap: list[tuple[float, int, Timer]] = []
        self._seq = 0
        #: periods that periodic timers skipped because the kernel came back too late for them
        self.skipped_periods = 0

    def call_at(self, deadline: float, callback: Callable[[], None],
                period: float | None = None) -> Timer:
        """Run ``callback`` on the kernel thread at clock time ``deadline`` (and every ``period``
        seconds after, drift-free, if given). Raises ValueError for a non-positive period."""
        if period is not None and period <= 0:
            raise ValueError(f"timer period must be positive, got {period}")
        tm = Timer(deadline, callback, period)
        self._seq += 1
        heappush(self.heap, (deadline, self._seq, tm))
        return tm

    def call_later(self, delay: float, callback: Callable[[], None]) -> Timer:
        """Run ``callback`` once, ``delay`` seconds from now."""
        return self.call_at(self.clock.now() + delay, callback)

    def every(self, period: float, callback: Callable[[], None]) -> Timer:
        """Run ``callback`` every ``period`` seconds, the first time one period from now."""
        return self.call_at(self.clock.now() + period, callback, period)

    def next_deadline(self) -> float | None:
        """The earliest deadline of a timer not cancelled (None: no timer)."""
        heap = self.heap
        while heap and heap[0][2].cancelled:
            heappop(heap)
        return heap[0][0] if heap else None

    def pending(self) -> int:
        """How many timers are pending (not cancelled)."""
        return sum(1 for _d, _s, tm in self.heap if not tm.cancelled)

    def fire(self, now: float) -> None:
        """Run the callback of every timer due at ``now`` (a periodic one re-armed first)."""
        timers = self.heap
        while timers:
            entry = timers[0]
            if entry[0] > now:
                return
            tm = entry[2]
            if tm.cancelled:
                heappop(timers)
                continue
            period = tm.period
            if period is not None:  # re-armed in place
                count = tm.count + 1
                # drift-free, whole nanoseconds (see _skip)
                deadline = round((tm.base + count * period) * 1e9) / 1e9
                if deadline <= now:  # late by at least one more period
                    count, deadline = self._skip(tm, count, now)
                tm.count = count
                tm.deadline = deadline
                self._seq += 1
                heapreplace(timers, (deadline, self._seq, tm))
            else:
                heappop(timers)
            try:
                tm.callback()
            except Exception as exc:  # a failing timer callback must not stop the kernel
                self.errors.record("timer", exc)

    def _skip(self, tm: Timer, count: int, now: float) -> tuple[int, float]:
        """Periodic ``tm``'s ``count``-th deadline has passed too: (count, deadline) of the
        first period boundary after ``now``; the boundaries in between are skipped and
        counted. Deadlines are ``base + count * period`` in whole nanoseconds: no accumulated
        rounding, and k * period lands on k * period."""
        period = tm.period
        assert period is not None
        base = tm.base
        late = count
        # the first boundary after now (a quotient within a hair of a whole number may land
        # on the boundary at now, or within a nanosecond of it: the one after, then)
        count = int((now - base) / period) + 1
        deadline = round((base + count * period) * 1e9) / 1e9
        while deadline <= now:
            count += 1
            deadline = round((base + count * period) * 1e9) / 1e9
        missed = count - late
        tm.skipped += missed
        self.skipped_periods += missed
        return count, deadline
