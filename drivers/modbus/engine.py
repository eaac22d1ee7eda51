"""engine - the two ways a Modbus driver runs its jobs (:mod:`drivers.modbus.requests`).

* :class:`ThreadEngine` - a worker thread of the driver over a real transport (a TCP
  connection, a serial port, :mod:`drivers.modbus.transport`): connect, prove the connection,
  run the jobs in order, reconnect with backoff when it is lost. Its timeouts and waits are wall
  time: its peer lives in wall time (another process, a serial line), whatever the kernel's
  clock; on a virtual clock the kernel's settle waits for its jobs (:meth:`ThreadEngine.settle`).
* :class:`KernelEngine` - on a virtual clock, against an in-process simulated slave
  (:mod:`drivers.codecs.modbus_direct`): the jobs run on the kernel thread in timer callbacks,
  the request's bytes handed to the slave in a call and its answer taken back; every timeout,
  retry, turnaround and reconnect delay is a kernel timer on the injected clock. A silent slave
  costs the request's timeout in virtual time; a Modbus RTU exchange takes its wire time at the
  line's baud rate (request and answer with their 3.5-character silences), a Modbus TCP one
  none. Nothing runs on another thread, so the kernel never waits for this driver
  (:meth:`KernelEngine.settle` is always quiet).

Both run the same jobs with the same rules: the bus's ``retries`` repeat a request that got no
usable answer; on a serial line a unit that missed a request is held quiet for its late answer
before another request goes to it (:meth:`drivers.modbus.link.Units.guard`); a broadcast is
followed by the turnaround delay; a job raising :class:`drivers.modbus.requests.LinkLost` (or a
transport failing under it) ends the connection; jobs that come while it is down are
completed without I/O (a write is reported failed at once).
"""

from __future__ import annotations

import contextlib
import functools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from drivers.base import DriverHost
from drivers.codecs.modbus import LineTiming
from drivers.codecs.modbus_direct import DirectSlave
from drivers.codecs.modbus_options import ModbusOptions
from drivers.jobqueue import JobQueue, Poll
from drivers.modbus.link import Link, Units
from drivers.modbus.requests import Batch, Exchange, JobRun, LinkLost, QueuedWrite, Sent, Step
from drivers.modbus.transactions import Answer, Outcome, Refused, Request
from drivers.modbus.transport import Transport, TransportLost, direct_exchange

JOIN_TIMEOUT = 5.0   # s to wait for the worker thread at stop
FLUSH_NOTICE = 0.05  # s: how soon a reconnect backoff notices that the shutdown flush began
TICK = 0.5           # s: the longest wait of the worker for a job


class Stop:
    """The job that ends the worker, queued behind every job already there."""


STOP = Stop()
Job = QueuedWrite | Stop


class Jobs(Protocol):
    """What an engine needs of its driver: the run of each job, what a job not run means, and
    the first job after a connect."""

    def run(self, job: Poll | QueuedWrite) -> JobRun:
        """The job's requests (see :mod:`drivers.modbus.requests`)."""

    def drop(self, job: Poll | QueuedWrite, why: str) -> None:
        """``job`` is completed without I/O (link down, stopped): ``why``."""

    def contact(self) -> JobRun | None:
        """The first job on a new connection (TCP: a probe read), None for none."""


@dataclass(frozen=True)
class Timing:
    """The waits of an engine, from the bus options."""

    timeout: float
    retries: int
    reconnect_delay: float
    reconnect_delay_max: float
    turnaround: float

    @classmethod
    def of(cls, o: ModbusOptions, turnaround: float) -> Timing:
        """The timing of options ``o``."""
        return cls(o.timeout, o.retries, o.reconnect_delay, o.reconnect_delay_max, turnaround)


def _usable(outcome: Outcome) -> bool:
    return isinstance(outcome, Answer | Refused)


class ThreadEngine:
    """The worker thread over a real transport (see the module doc)."""

    def __init__(self, name: str, host: DriverHost, queue: JobQueue[Job], link: Link,
                 units: Units, jobs: Jobs, transport: Transport, timing: Timing,
                 thread_name: str) -> None:
        self._name = name
        self._host = host
        self._queue = queue
        self._link = link
        self._units = units
        self._jobs = jobs
        self._transport = transport
        self._timing = timing
        self._thread_name = thread_name
        self._worker: threading.Thread | None = None
        self._first_attempt = threading.Event()
        self._stop_seen = False
        #: set by the shutdown flush: reconnect at the shortest delay from then on
        self._shutting_down = False

    @property
    def clock(self) -> Callable[[], float]:
        """The engine's clock: wall time."""
        return time.monotonic

    def start(self) -> None:
        """Start the worker and wait for its first connection attempt (a refused connection
        fails the devices; it is not an error here)."""
        self._queue.open()
        self._worker = threading.Thread(target=self._work, name=self._thread_name, daemon=True)
        self._worker.start()
        self._first_attempt.wait(self._timing.timeout + 2.0)

    def stop(self) -> None:
        """Run every job queued before, end the worker, report the writes it did not get to."""
        self._link.stopping = True
        self._queue.seal(STOP)
        worker, self._worker = self._worker, None
        if worker is not None and worker is not threading.current_thread():
            worker.join(timeout=JOIN_TIMEOUT)
        for job in self._queue.close():
            if not isinstance(job, Stop):
                self._jobs.drop(job, f"{self._name} stopped before the write was sent")
        self._transport.close()

    def flush(self, timeout: float) -> bool:
        """Wait until every job handed over is done; from then on a lost link is reconnected
        every ``reconnect_delay``."""
        self._shutting_down = True
        return self._queue.flush(timeout)

    def settle(self, timeout: float) -> bool:
        """Wait until no job is queued or running."""
        return self._queue.settle(timeout)

    # ---- the worker -------------------------------------------------------------------------
    def _work(self) -> None:
        """Connect, prove, serve the jobs; reconnect with backoff when the link drops; end at
        the stop job."""
        t = self._timing
        delay = t.reconnect_delay
        try:
            while not self._stop_seen:
                try:
                    self._transport.open()
                except (OSError, TransportLost) as exc:
                    self._host.stat(self._link.bus, "connect-failed")
                    self._link.down(f"cannot connect to {self._link.where}: {exc}")
                    self._first_attempt.set()
                    self._backoff(delay)
                    delay = min(delay * 2, t.reconnect_delay_max)
                    continue
                self._link.up()
                proven = False
                try:
                    contact = self._jobs.contact()
                    if contact is not None:
                        self._drive(contact)
                    proven = True
                    delay = t.reconnect_delay
                    self._first_attempt.set()
                    self._serve()
                except LinkLost as exc:
                    self._first_attempt.set()
                    self._link.down(str(exc))
                    self._drain()
                    if not proven:          # it took the connection, answered nothing
                        self._backoff(delay)
                        delay = min(delay * 2, t.reconnect_delay_max)
                finally:
                    self._transport.close()
        finally:
            self._first_attempt.set()

    def _serve(self) -> None:
        """Run jobs in order until the link drops (raises LinkLost) or the stop job comes."""
        queue = self._queue
        while True:
            job = queue.take(TICK)
            if job is None:
                if not queue.taking and queue.idle():   # a stop that gave up waiting
                    self._stop_seen = True
                    return
                continue
            try:
                if isinstance(job, Stop):
                    self._stop_seen = True
                    return
                self._drive(self._jobs.run(job))
            finally:
                queue.done()

    def _drain(self) -> None:
        """Complete every queued job without I/O while the link is down."""
        while True:
            job = self._queue.take_nowait()
            if job is None:
                return
            self._finish_unsent(job)

    def _finish_unsent(self, job: Job | Poll) -> None:
        try:
            if isinstance(job, Stop):
                self._stop_seen = True
            else:
                self._jobs.drop(job, f"{self._name} is not connected to {self._link.where}"
                                if not self._stop_seen else f"{self._name} stopped")
        finally:
            self._queue.done()

    def _backoff(self, delay: float) -> None:
        """Wait ``delay`` seconds (or until stop), completing jobs that arrive meanwhile (a
        write fails at once: the link is down). Once the shutdown flush began, the wait is
        ``reconnect_delay`` at most."""
        start = time.monotonic()
        while not self._stop_seen:
            wait = min(delay, self._timing.reconnect_delay) if self._shutting_down else delay
            left = start + wait - time.monotonic()
            if left <= 0:
                return
            job = self._queue.take(min(left, FLUSH_NOTICE))
            if job is not None:
                self._finish_unsent(job)

    def _drive(self, run: JobRun) -> None:
        """Run one job's requests on the transport (raises LinkLost when the link is lost)."""
        try:
            step = run.send(None)
            while True:
                try:
                    value = self._do(step)
                except TransportLost as exc:
                    lost = LinkLost(f"connection to {self._link.where} lost: {exc}")
                    try:
                        run.throw(lost)
                    except StopIteration:
                        pass
                    finally:
                        run.close()
                    raise lost from None
                step = run.send(value)
        except StopIteration:
            return

    def _do(self, step: Step) -> Any:
        t = self._timing
        if isinstance(step, Batch):
            out = self._transport.exchange_all(step.requests, t.timeout)
            return out
        return self._exchange(step.request)

    def _exchange(self, req: Request) -> Outcome | Sent:
        """One request with the bus's retries (and, on a serial line, the guard of its
        unit)."""
        t = self._timing
        if req.broadcast:
            self._transport.broadcast(req, t.turnaround)
            return Sent()
        outcome: Outcome | None = None
        extra = 1 if self._units.extra_try(req.unit) else 0
        for _ in range(t.retries + 1 + extra):
            until = self._units.guard(req.unit, req.pdu, time.monotonic())
            if until:
                self._transport.hold_quiet(until)
            outcome = self._transport.exchange(req, t.timeout)
            if _usable(outcome):
                return outcome
        assert outcome is not None
        return outcome


class KernelEngine:
    """The jobs on the kernel thread against an in-process slave (see the module doc)."""

    def __init__(self, name: str, host: DriverHost, queue: JobQueue[Job], link: Link,
                 units: Units, jobs: Jobs, slave: DirectSlave, timing: Timing,
                 line: LineTiming | None) -> None:
        self._name = name
        self._host = host
        self._queue = queue
        self._link = link
        self._units = units
        self._jobs = jobs
        self._slave = slave
        self._timing = timing
        self._line = line
        self._lock = threading.Lock()
        self._armed = False
        self._run: JobRun | None = None       # the job under way
        self._contacting = False
        self._batch: tuple[list[Request], list[Outcome]] | None = None
        self._stopped = False
        self._tid = 0
        self._delay = timing.reconnect_delay
        self._shutting_down = False
        self._tries = timing.retries + 1     # of the exchange under way

    @property
    def clock(self) -> Callable[[], float]:
        """The engine's clock: the kernel's."""
        return self._host.now

    def start(self) -> None:
        """Take jobs and connect (at once: the slave is in this process)."""
        self._queue.open()
        self._connect()

    def stop(self) -> None:
        """End the job under way (a write in it is reported failed) and report every job not
        run; no kernel timer of the engine does anything after this."""
        self._stopped = True
        self._link.stopping = True
        run, self._run = self._run, None
        if run is not None:
            with contextlib.suppress(LinkLost, StopIteration):
                run.throw(LinkLost(f"{self._name} stopped"))
        for job in self._queue.close():
            if not isinstance(job, Stop):
                self._jobs.drop(job, f"{self._name} stopped before the write was sent")

    def flush(self, timeout: float) -> bool:
        """Whether every job handed over is done (the kernel runs them: nothing to wait for
        here); from now on a lost link is reconnected every ``reconnect_delay``."""
        self._shutting_down = True
        return self._queue.idle()

    def settle(self, timeout: float) -> bool:
        """Always quiet: everything in flight is a kernel timer."""
        return True

    def wake(self) -> None:
        """A job came: run the queue from a timer callback now (once)."""
        with self._lock:
            if self._armed or self._stopped:
                return
            self._armed = True
        self._host.at(self._host.now(), self._pump)

    # ---- the connection -----------------------------------------------------------------------
    def _connect(self) -> None:
        if self._stopped:
            return
        if self._slave.framing == "tcp" and not self._slave.accepts():
            self._host.stat(self._link.bus, "connect-failed")
            self._link.down(f"cannot connect to {self._link.where}: connection refused")
            self._retry_connect()
            return
        self._link.up()
        self._tid = 0
        contact = self._jobs.contact()
        if contact is not None:
            self._contacting = True
            self._start(contact)
        else:
            self._delay = self._timing.reconnect_delay
            self.wake()

    def _retry_connect(self) -> None:
        t = self._timing
        delay = min(self._delay, t.reconnect_delay) if self._shutting_down else self._delay
        self._delay = min(self._delay * 2, t.reconnect_delay_max)
        self._host.at(self._host.now() + delay, self._connect)
        self._pump()            # what queued meanwhile completes without I/O

    def _lost(self, why: str, proven: bool) -> None:
        """The link is lost: reconnect at once after a connection that answered, else after
        the backoff."""
        self._link.down(why)
        if proven:
            self._delay = self._timing.reconnect_delay
            self._host.at(self._host.now(), self._connect)
            self._pump()
        else:
            self._retry_connect()

    # ---- the jobs -----------------------------------------------------------------------------
    def _pump(self) -> None:
        """Run queued jobs until one has to wait for a timer (or none is left)."""
        with self._lock:
            self._armed = False
        while not self._stopped and self._run is None:
            job = self._queue.take_nowait()
            if job is None:
                return
            if isinstance(job, Stop):
                self._queue.done()
                continue
            if not self._link.connected:
                try:
                    self._jobs.drop(job, f"{self._name} is not connected to {self._link.where}")
                finally:
                    self._queue.done()
                continue
            self._start(self._jobs.run(job))

    def _start(self, run: JobRun) -> None:
        self._run = run
        self._advance(None)

    def _advance(self, value: Any, error: LinkLost | None = None) -> None:
        """Send ``value`` (or throw ``error``) into the job under way and do its steps until
        one has to wait; then, at its end, the next job."""
        run = self._run
        while run is not None and run is self._run:
            try:
                step = run.throw(error) if error is not None else run.send(value)
            except StopIteration:
                self._job_done()
                return
            except LinkLost as exc:
                proven = not self._contacting
                self._run = None
                self._batch = None
                self._contacting = False
                if proven:
                    self._queue.done()
                self._lost(str(exc), proven)
                return
            error = None
            if isinstance(step, Batch):
                self._batch = (list(step.requests), [])
                step = Exchange(self._batch[0].pop(0))
            try:
                got = self._exchange(step.request, 0)
            except TransportLost as exc:
                error = LinkLost(f"connection to {self._link.where} lost: {exc}")
                self._batch = None
                continue
            if got is None:
                return                  # a timer goes on with it
            value = self._collect(got)
            if value is _MORE:
                return

    def _collect(self, outcome: Outcome | Sent) -> Any:
        """The value for the job from one exchange: the outcome, or a batch's outcomes once the
        last is in (meanwhile the next request of the batch goes out: :data:`_MORE`)."""
        if self._batch is None:
            return outcome
        left, got = self._batch
        assert not isinstance(outcome, Sent)
        got.append(outcome)
        if not left:
            self._batch = None
            return got
        try:
            nxt = self._exchange(left.pop(0), 0)
        except TransportLost as exc:
            self._batch = None
            self._advance(None, LinkLost(f"connection to {self._link.where} lost: {exc}"))
            return _MORE
        if nxt is None:
            return _MORE
        return self._collect(nxt)

    def _job_done(self) -> None:
        was_contact = self._contacting
        self._contacting = False
        self._run = None
        self._batch = None
        if was_contact:
            self._delay = self._timing.reconnect_delay
        else:
            self._queue.done()
        self.wake()

    def _exchange(self, req: Request, attempt: int) -> Outcome | Sent | None:
        """Hand ``req`` to the slave now: its outcome if it is known at once, else None (a
        timer resumes the job with it: the wire time, the timeout, a retry, the guard).
        Raises TransportLost when a TCP slave closed."""
        now = self._host.now()
        if attempt == 0:
            self._tries = self._timing.retries + 1 + (1 if self._units.extra_try(req.unit)
                                                      else 0)
        if req.broadcast:
            direct_exchange(self._slave, req, 0, now)
            self._later(now + self._wire(req, 0) + self._timing.turnaround, Sent(), req, attempt)
            return None
        if self._line is not None:
            until = self._units.guard(req.unit, req.pdu, now)
            if until > now:
                self._host.at(until, functools.partial(self._resume_exchange, self._run, req,
                                                       attempt))
                return None
        self._tid = self._tid % 0xFFFF + 1
        outcome, later = direct_exchange(self._slave, req, self._tid, now)
        if outcome is None:
            self._later(now + self._timing.timeout, later, req, attempt)
            return None
        wire = self._wire(req, 5 if isinstance(outcome, Refused) else req.rtu_answer_bytes())
        if wire > 0 or (not _usable(outcome) and attempt < self._tries - 1):
            self._later(now + wire, outcome, req, attempt)
            return None
        return outcome

    def _wire(self, req: Request, answer: int) -> float:
        if self._line is None:
            return 0.0
        sent = self._line.frame_time(len(req.pdu) + 3)
        return sent + (self._line.frame_time(answer) if answer else 0.0)

    def _later(self, when: float, outcome: Outcome | Sent, req: Request, attempt: int) -> None:
        self._host.at(when, functools.partial(self._arrived, self._run, outcome, req, attempt))

    def _arrived(self, run: JobRun | None, outcome: Outcome | Sent, req: Request,
                 attempt: int) -> None:
        """A timer of an exchange: retry it, or go on with its outcome."""
        if self._stopped or run is not self._run:
            return
        if not isinstance(outcome, Sent) and not _usable(outcome) \
                and attempt < self._tries - 1:
            self._resume_exchange(run, req, attempt + 1)
            return
        value = self._collect(outcome)
        if value is not _MORE:
            self._advance(value)

    def _resume_exchange(self, run: JobRun | None, req: Request, attempt: int) -> None:
        if self._stopped or run is not self._run:
            return
        try:
            got = self._exchange(req, attempt)
        except TransportLost as exc:
            self._batch = None
            self._advance(None, LinkLost(f"connection to {self._link.where} lost: {exc}"))
            return
        if got is None:
            return
        value = self._collect(got)
        if value is not _MORE:
            self._advance(value)


_MORE: Any = object()   # a batch goes on: the job waits for its other outcomes
