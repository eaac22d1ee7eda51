"""jobs - the job-queue scaffolding of the CANopen driver (the Modbus drivers own a
:class:`drivers.jobqueue.JobQueue` instead, which this driver can adopt).

Their bus I/O runs as jobs, in order, on one I/O thread of the driver: a poll of some sensors, a
write, a probe, an NMT command. The kernel side only enqueues (kernel timer callbacks and
:meth:`drivers.base.Driver.write` never block) and :meth:`JobDriver.settle` waits until every job
handed over so far is done. :class:`JobDriver` keeps that count (``_pending`` under the
``_idle`` condition), the set of polls already queued (a poll is queued at most once, however
late the I/O thread is), the ``write`` job and the settle, including the settle of an optional
:class:`drivers.threaded.ReaderThread` (``_rx``) whose frames the jobs wait for.

Polls are paced by the polls themselves (:meth:`JobDriver._poll_every`), as a field-bus master
paces its cycle: each poll is due one period after the previous one was due, armed with
``host.at`` when the I/O thread takes the previous one. A bus slower than the period is polled
back to back: a successor already due when its predecessor is taken is queued at once by the I/O
thread (counted ``polls-late`` in the bus statistics), so the kernel is not woken for polls at
all then, where a periodic timer would wake it every period while a slow poll is in flight. On a
virtual clock the polls fall exactly on the period's grid. The transport is
:class:`WorkerJobDriver`: a plain worker thread taking jobs from a :class:`queue.Queue` (the
CANopen driver, whose library calls block); a subclass writes ``_run(job)`` and may override
``_tick()`` (the longest wait for a job: its watchdog's period), or replace the worker's loop
``_work()`` by its own that takes the jobs.

:meth:`WorkerJobDriver._stop_worker` queues a ``stop`` job behind every job already queued, so
writes queued before the stop (the safe values at shutdown) still go out; a write the thread did
not get to is reported failed. A job ends with ``_done()`` exactly once, whether it ran or not. A
:meth:`JobDriver.flush` (shutdown) arms late successors through the host instead of queuing them,
so a bus polled back to back does not hold it until its timeout.
"""

from __future__ import annotations

import functools
import queue
import threading
import time
from abc import abstractmethod
from collections.abc import Hashable, Sequence
from enum import StrEnum
from typing import Any, NamedTuple

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import Driver, DriverHost
from drivers.threaded import ReaderThread


class JobOp(StrEnum):
    """What a job does, as far as this module is concerned: it paces the ``POLL`` jobs (their
    ``what`` a key typed by the driver), reports a ``WRITE`` job it drops as a failed write, and
    ends the worker at ``STOP``. ``OWN``: a job of the driver's own, its ``what`` a typed object
    the driver dispatches with ``match`` (the CANopen driver's :mod:`drivers.canopen_jobs`)."""

    POLL = "poll"
    WRITE = "write"
    STOP = "stop"
    OWN = "own"


class Job(NamedTuple):
    """One unit of bus I/O: ``op``, what it is about (a poll's key, typed by the driver; a
    write's device; a driver's own job object) and a write's value."""

    op: JobOp
    what: Any = None
    value: Any = None


STOP = Job(JobOp.STOP)
JOIN_TIMEOUT = 5.0   # s to wait for the I/O thread at stop


class JobDriver(Driver):
    """A driver whose bus I/O runs as jobs on its own thread (see the module doc). Subclasses
    provide the transport (:meth:`_put`); :attr:`_rx` may hold the reader thread whose input a
    settle must hand over first."""

    confirms_writes = True
    numeric_only = True

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._idle = threading.Condition()
        self._pending = 0
        self._polls_queued: set[Hashable] = set()
        #: paced polls: key -> period; key -> when the queued poll was due
        self._poll_plan: dict[Hashable, float] = {}
        self._poll_due_at: dict[Hashable, float] = {}
        self._rx: ReaderThread | None = None
        #: flushes under way: late successors are armed through the host, not queued at once
        self._flushing = 0

    @abstractmethod
    def _put(self, job: Job) -> bool:
        """Hand ``job`` to the I/O thread; False if it cannot take it (not running)."""

    def _submit(self, op: JobOp, what: Any = None, value: Any = None) -> bool:
        """Count and hand over one job; False (and not counted) if the thread cannot take it."""
        with self._idle:
            self._pending += 1
        if not self._put(Job(op, what, value)):
            self._done()
            return False
        return True

    def _submit_poll(self, key: Hashable) -> None:
        """Queue the poll ``key`` (job ``(POLL, key)``) unless it is queued already; the I/O
        thread calls :meth:`_poll_taken` when it takes it."""
        if key in self._polls_queued:   # the kernel's timer fires while the poll waits (or
            return                      # catches up): no lock (a racing take only defers it)
        with self._idle:
            if key in self._polls_queued:
                return
            self._polls_queued.add(key)
        if not self._submit(JobOp.POLL, key):
            self._poll_taken(key)

    def _poll_every(self, key: Hashable, period: float) -> None:
        """Poll ``key`` (job ``(POLL, key)``) every ``period`` seconds of the kernel clock, the
        first one period from now, paced by the polls (see the module doc). Call from start."""
        self._poll_plan[key] = period
        self._arm_poll(key, round(self.host.now() + period, 9))

    def _arm_poll(self, key: Hashable, due: float) -> None:
        self.host.at(due, functools.partial(self._poll_is_due, key, due))

    def _poll_is_due(self, key: Hashable, due: float) -> None:
        """Queue the poll ``key`` due at ``due`` (the kernel thread at that time, or the I/O
        thread for a late successor); taking it arms the next one."""
        with self._idle:
            self._poll_due_at[key] = due
        self._submit_poll(key)

    def _poll_taken(self, key: Hashable) -> None:
        """The poll ``key`` left the queue (run, or dropped): it may be queued again. A paced
        poll's successor is armed here, one period after this one was due; if that has passed
        already (counted ``polls-late``) it is queued at once, behind this one, without a
        round trip through the kernel. Nothing once the driver stops."""
        with self._idle:
            self._polls_queued.discard(key)
            due = self._poll_due_at.pop(key, None)
        if due is None or not self._running:
            return
        nxt = round(due + self._poll_plan[key], 9)
        now = self.host.now()
        if nxt > now or self._flushing:
            self._arm_poll(key, nxt)
            return
        self.host.stat(self.bus.name, "polls-late")
        self._poll_is_due(key, now)

    def _done(self) -> None:
        """One job is finished (run or dropped); wakes :meth:`settle` at the last one."""
        with self._idle:
            self._pending = max(0, self._pending - 1)
            if self._pending == 0:
                self._idle.notify_all()

    def _quiet(self) -> None:
        """At stop: nothing is outstanding any more (wakes every settle)."""
        with self._idle:
            self._pending = 0
            self._polls_queued.clear()
            self._idle.notify_all()

    def _write(self, device: str, value: Any) -> None:
        """Queue a ``write`` job for actuator ``device``; never blocks. A write the thread
        cannot take (a concurrent stop) is reported like one while stopped."""
        if not self._submit(JobOp.WRITE, device, value):
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")

    def flush(self, timeout: float) -> bool:
        """Wait until every job handed over so far (the writes among them) is done, as
        :meth:`settle`. Meanwhile a poll's late successor is armed through the host instead of
        queued at once, so a bus polled back to back does not keep the flush waiting until its
        timeout (at shutdown the kernel no longer runs what is armed)."""
        with self._idle:
            self._flushing += 1
        try:
            return self.settle(timeout)
        finally:
            with self._idle:
                self._flushing -= 1

    def settle(self, timeout: float) -> bool:
        """Hand over every frame the reader (if any) already received, then wait until no job
        is queued or running. True at once when stopped; False on timeout."""
        deadline = time.monotonic() + timeout
        rx = self._rx
        if rx is not None and not rx.settle(timeout):
            return False
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0,
                                       max(0.0, deadline - time.monotonic()))

    def _unsent_write(self, job: Job) -> None:
        """A write job dropped at stop, never run: reported failed."""
        if job.op == JobOp.WRITE:
            self.host.write_failed(job.what, job.value, f"{self.kind} bus {self.bus.name} "
                                                        f"stopped before the write was sent")


class WorkerJobDriver(JobDriver):
    """Jobs on a plain worker thread (see the module doc)."""

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._jobs: queue.Queue[Job] = queue.Queue()
        self._worker: threading.Thread | None = None
        self._taking = False

    @abstractmethod
    def _run(self, job: Job) -> None:
        """Run one job on the worker thread (:meth:`_done` follows by itself)."""

    def _tick(self) -> float:
        """Seconds the worker waits for a job at most (then it calls this again)."""
        return 0.5

    def _put(self, job: Job) -> bool:
        with self._idle:
            if not self._taking:
                return False
            self._jobs.put(job)
        return True

    def _start_worker(self) -> None:
        """Start the worker thread, ``<kind>-<bus>``."""
        with self._idle:
            self._taking = True
        self._worker = threading.Thread(target=self._work, name=f"{self.kind}-{self.bus.name}",
                                        daemon=True)
        self._worker.start()

    def _work(self) -> None:
        while True:      # ends on the stop job only, queued behind every job already there
            try:
                job = self._jobs.get(timeout=self._tick())
            except queue.Empty:
                continue
            if job.op == JobOp.STOP:
                return
            try:
                self._run(job)
            finally:
                self._done()

    def _stop_worker(self) -> None:
        """Run every queued job, end the worker, report the writes it did not get to."""
        with self._idle:
            was, self._taking = self._taking, False
            if was:
                self._jobs.put(STOP)
        worker, self._worker = self._worker, None
        if worker is not None and worker is not threading.current_thread():
            worker.join(timeout=JOIN_TIMEOUT)
        while True:    # the worker did not get to these (stuck past the join timeout)
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                break
            self._unsent_write(job)
        self._quiet()
