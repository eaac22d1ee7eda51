"""jobqueue - the job queue of a request/response driver, as a part the driver owns.

A request/response driver (Modbus; CANopen's SDO side could adopt it) does its bus I/O as jobs
run in order by one runner: a worker thread (:meth:`JobQueue.take` blocks) or the kernel
thread itself (:meth:`JobQueue.take_nowait` from a timer callback, woken by the ``wake``
callback given at construction whenever a job arrives). The kernel side only submits (kernel
timer callbacks and :meth:`drivers.base.Driver.write` never block); :meth:`JobQueue.settle`
waits until every job handed over so far is done.

Polls are paced by the polls themselves (:meth:`JobQueue.poll_every`), as a field-bus master
paces its cycle: each poll is due one period after the previous one was due, armed with
``host.at`` when the runner takes the previous one; a poll is queued at most once, however late
the runner is. A bus slower than the period is polled back to back: a successor already due when
its predecessor is taken is queued at once (counted ``polls-late`` in the bus statistics), so
the kernel is not woken for polls at all then. On a virtual clock the polls fall exactly on the
period's grid. While a :meth:`JobQueue.flush` (shutdown) waits, late successors are armed
through the host instead of queued at once, so a bus polled back to back does not hold it until
its timeout. :meth:`JobQueue.close` (stop) returns the jobs never taken, for the driver to
report (a write it did not get to is reported failed).
"""

from __future__ import annotations

import functools
import threading
from collections import deque
from collections.abc import Callable, Hashable
from dataclasses import dataclass
from typing import Generic, TypeVar

from drivers.base import DriverHost

J = TypeVar("J")


@dataclass(frozen=True, slots=True)
class Poll:
    """The job of a paced poll: its key (typed by the driver)."""

    key: Hashable


class JobQueue(Generic[J]):
    """The jobs of one driver (see the module doc): the driver's own jobs ``J`` and its paced
    :class:`Poll` jobs. Thread-safe."""

    def __init__(self, host: DriverHost, bus: str, wake: Callable[[], None] = lambda: None
                 ) -> None:
        self._host = host
        self._bus = bus
        self._wake = wake
        self._cond = threading.Condition()
        self._jobs: deque[J | Poll] = deque()
        self._taking = False
        self._pending = 0
        self._queued: set[Hashable] = set()
        #: paced polls: key -> period; key -> when the queued poll was due
        self._plan: dict[Hashable, float] = {}
        self._due_at: dict[Hashable, float] = {}
        self._flushing = 0

    # ---- the driver's side -----------------------------------------------------------------
    def open(self) -> None:
        """Take jobs from now on (the driver starts)."""
        with self._cond:
            self._taking = True

    @property
    def taking(self) -> bool:
        """True between :meth:`open` and :meth:`close`."""
        return self._taking

    def submit(self, job: J | Poll) -> bool:
        """Queue ``job``; False (not queued) once the queue is closed."""
        with self._cond:
            if not self._taking:
                return False
            self._jobs.append(job)
            self._pending += 1
            self._cond.notify_all()
        self._wake()
        return True

    def poll_every(self, key: Hashable, period: float) -> None:
        """Poll ``key`` every ``period`` seconds of the kernel clock, the first one period from
        now, paced by the polls (see the module doc)."""
        self._plan[key] = period
        self._arm(key, round(self._host.now() + period, 9))

    def seal(self, last: J) -> bool:
        """Queue ``last`` (the driver's stop job) behind every job already queued and take no
        more jobs after it: the runner still runs what is queued (the writes handed over
        before the stop go out). False if the queue was closed already."""
        with self._cond:
            if not self._taking:
                return False
            self._jobs.append(last)
            self._pending += 1
            self._taking = False
            self._cond.notify_all()
        self._wake()
        return True

    def close(self) -> list[J | Poll]:
        """Take no more jobs; the jobs never taken (the caller reports them), and nothing is
        outstanding any more (every settle wakes)."""
        with self._cond:
            self._taking = False
            left = list(self._jobs)
            self._jobs.clear()
            self._pending = 0
            self._queued.clear()
            self._cond.notify_all()
        return left

    # ---- the runner's side ------------------------------------------------------------------
    def take(self, timeout: float) -> J | Poll | None:
        """The next job, waiting up to ``timeout`` wall seconds (None: none came, or the queue
        closed). A poll taken arms its successor (see the module doc)."""
        with self._cond:
            if not self._jobs and self._taking:
                self._cond.wait(timeout)
            if not self._jobs:
                return None
            job = self._jobs.popleft()
        if isinstance(job, Poll):
            self._taken(job.key)
        return job

    def take_nowait(self) -> J | Poll | None:
        """The next job, None if there is none (never waits: the kernel thread's runner)."""
        with self._cond:
            if not self._jobs:
                return None
            job = self._jobs.popleft()
        if isinstance(job, Poll):
            self._taken(job.key)
        return job

    def done(self) -> None:
        """One job taken is finished (run or dropped); wakes :meth:`settle` at the last one."""
        with self._cond:
            self._pending = max(0, self._pending - 1)
            if self._pending == 0:
                self._cond.notify_all()

    def idle(self) -> bool:
        """True when no job is queued or running."""
        return self._pending == 0

    def settle(self, timeout: float) -> bool:
        """Wait up to ``timeout`` wall seconds until no job is queued or running; True if so."""
        with self._cond:
            return self._cond.wait_for(lambda: self._pending == 0, timeout)

    def flush(self, timeout: float, wait: Callable[[float], bool] | None = None) -> bool:
        """:meth:`settle` (or ``wait(timeout)``, the driver's own), with late successors armed
        through the host meanwhile (see the module doc)."""
        with self._cond:
            self._flushing += 1
        try:
            return (wait or self.settle)(timeout)
        finally:
            with self._cond:
                self._flushing -= 1

    # ---- paced polls ------------------------------------------------------------------------
    def _arm(self, key: Hashable, due: float) -> None:
        self._host.at(due, functools.partial(self._due, key, due))

    def _due(self, key: Hashable, due: float) -> None:
        """Queue the poll ``key`` due at ``due``, unless it is queued already (the kernel
        thread at that time, or the runner for a late successor)."""
        if key in self._queued:     # the timer fires while the poll waits: no lock (a racing
            return                  # take only defers it)
        with self._cond:
            if key in self._queued or not self._taking:
                return
            self._queued.add(key)
            self._due_at[key] = due
        self.submit(Poll(key))

    def _taken(self, key: Hashable) -> None:
        """The poll ``key`` left the queue: it may be queued again, and its successor is due
        one period after it was; if that has passed already (counted ``polls-late``) it is
        queued at once, behind this one."""
        with self._cond:
            self._queued.discard(key)
            due = self._due_at.pop(key, None)
            if due is None or not self._taking:
                return
            flushing = self._flushing > 0
        nxt = round(due + self._plan[key], 9)
        now = self._host.now()
        if nxt > now or flushing:
            self._arm(key, nxt)
            return
        self._host.stat(self._bus, "polls-late")
        self._due(key, now)

