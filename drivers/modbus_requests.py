"""modbus_requests - the requests of the Modbus drivers: a poll's reads (in order on one
connection, or spread over several connections all outstanding at once) and a write, each on a
pymodbus synchronous client, with what its answer means for the devices (readings, exception
answers, no answer). :class:`ModbusRequests` holds the drivers' state and these requests; the life
cycle, the jobs and the supervision of the link are :class:`drivers.modbus_link.ModbusDriver`, the
kinds and the failure rules :mod:`drivers.modbus`.

Threads: the requests run on the driver's worker thread (:class:`drivers.jobs.WorkerJobDriver`);
a parallel poll (``connections`` > 1) runs the shares of the extra connections on a thread pool
of the driver, one thread per extra connection, while the worker runs the main connection's
share. What an answer means (statistics, failures, health, readings) is handled under one lock,
so the shares' answers are taken one at a time, as they come.
"""

from __future__ import annotations

import threading
from abc import abstractmethod
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any, ClassVar

from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import DriverHost, deliver_all
from drivers.codecs.modbus import (
    EXCEPTION_TEXT,
    Point,
    ReadRequest,
    UnitBackoff,
    Watchdog,
    reading_of,
    value_error,
)
from drivers.health import Health
from drivers.jobs import JobOp, WorkerJobDriver
from drivers.modbus_jobs import LinkChore

#: The health cause of an actuator whose last write failed with its unit there; cleared by a
#: later answered write or by the driver's own read-back (:meth:`ModbusRequests._read_back`).
WRITE_CAUSE = "write"
#: The health cause of every device of an RTU unit that stopped answering (cleared by any
#: answer from the unit).
UNIT_CAUSE = "unit"
#: The health cause of the devices of the watchdog's unit while the unit refuses the watchdog
#: write (an exception answer: the PLC's comm-loss logic will act).
WATCHDOG_CAUSE = "watchdog"
#: Exception codes to a read-back that still mean the unit answered: the entry cannot be read
#: (illegal function, data address, data value), not that the unit is busy or failing.
UNIT_ANSWERED = frozenset({1, 2, 3})
DEFAULT_DEAD_UNIT_BACKOFF = 8   # poll periods, at least, between two tries of a dead unit
#: a dead unit's tries take at most 1/DEAD_UNIT_SHARE of an RTU line's time
DEAD_UNIT_SHARE = 20


@dataclass(frozen=True)
class QueuedWrite:
    """A write job's value and the epoch of its unit when it was queued (see
    :meth:`drivers.codecs.modbus.UnitBackoff.epoch`): a write queued before its unit stopped
    answering is not sent after that."""

    value: Any
    epoch: int


def raw_value(value: Any) -> Any:
    """The value a write job carries (what :meth:`Driver.write` was given)."""
    return value.value if isinstance(value, QueuedWrite) else value


READ_METHOD = {"coil": "read_coils", "discrete": "read_discrete_inputs",
               "holding": "read_holding_registers", "input": "read_input_registers"}
#: The read function of each table, called with the client first (no bound method per request).
READ_CALL: dict[str, Callable[..., Any]] = {
    table: getattr(ModbusClientMixin, name) for table, name in READ_METHOD.items()}


class ModbusRequests(WorkerJobDriver):
    """The state of a Modbus driver and its requests (see the module doc); the link's
    supervision (:meth:`_answer`) and the client and link of the kind are the subclasses'."""

    kind: ClassVar[str] = ""
    #: A request timeout means the link is gone (TCP: the server or its connection hangs) rather
    #: than one unit not answering (RTU: the other units on the line may still answer).
    timeout_is_link_loss: ClassVar[bool] = False

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._health = Health(host)
        self._stop_seen = False
        self._client: Any = None
        self._connected = False
        self._plans: dict[float, list[ReadRequest]] = {}
        self._points: dict[str, Point] = {}
        #: the first actuator of each unit no poll reads: read every period as a liveness probe
        self._probed: list[Point] = []
        self._first_attempt = threading.Event()
        self._answered = True      # a request was answered since the last (re)connect
        self._units_answered: set[int] = set()   # RTU: the units that did, since then
        self._connects = 0
        #: modbus-tcp with ``connections`` > 1: the extra clients a poll of several requests
        #: spreads them over (opened after the main connection answered, closed with it).
        self._lanes: list[Any] = []
        self._lanes_tried = False
        #: the threads of the extra connections (made at the first parallel poll, ended at stop)
        self._pool: ThreadPoolExecutor | None = None
        #: held while an answer is taken (statistics, failures, health, readings): the shares of
        #: a parallel poll run on several threads
        self._lock = threading.Lock()
        #: actuators whose last write failed with their unit there: read back until it answers
        self._readback: set[str] = set()
        self._readback_armed = False
        self._lock_readback = threading.Lock()
        #: RTU: which units answer and how often a dead one is tried (see start())
        self._units = UnitBackoff(DEFAULT_DEAD_UNIT_BACKOFF)
        #: the bus's watchdog register (see start()) and how many times it was written
        self._watchdog: Watchdog | None = None
        self._beats = 0
        #: set by the shutdown flush: reconnect at the shortest delay from then on
        self._shutting_down = False

    # -- to be provided by the kinds ----------------------------------------------------------

    @abstractmethod
    def _make_client(self) -> Any:
        """A new pymodbus synchronous client for this bus, not connected (called on the worker
        thread)."""

    @abstractmethod
    def _link(self) -> str:
        """Where the bus goes (``host:port``, the serial port), for failure reasons."""

    def _connections(self) -> int:
        """How many connections a poll may use at once (``modbus-tcp``'s ``connections``; a
        serial line has one)."""
        return 1

    def _unanswered(self, request: str) -> tuple[str, str]:
        """The error class (``timeout``, and for RTU also ``crc``/``framing``) and the reason
        why the last request got no valid answer; the caller counts it as a bus error."""
        return "timeout", "no response"

    @abstractmethod
    def _answer(self, unit: int | None = None) -> None:
        """A request was answered (with data or an exception): the link works (see
        :meth:`drivers.modbus_link.ModbusDriver._answer`)."""

    # -- requests (I/O thread) ----------------------------------------------------------------

    def _open_lanes(self) -> list[Any]:
        """The clients a poll spreads its requests over: the main one, plus (once per
        connection, ``connections`` > 1) the extra connections that could be made. A server that
        refuses them (many devices accept only a few connections) is polled over fewer; that is
        counted (``host.error`` kind ``connections``), not a failure of any device: a connection
        is used only once it answered a read (many servers accept a connection and then close
        it, or never answer on it)."""
        want = self._connections()
        if want > 1 and not self._lanes_tried:
            self._lanes_tried = True
            for _ in range(want - 1):
                lane = self._make_client()
                if not self._lane_answers(lane):
                    lane.close()
                    self.host.error(self.bus.name, "connections",
                                    f"{self.kind} bus {self.bus.name}: {self._link()} took "
                                    f"{1 + len(self._lanes)} of {want} connections; polls use "
                                    f"those")
                    break
                self._lanes.append(lane)
        return [self._client, *self._lanes]

    def _lane_answers(self, lane: Any) -> bool:
        """Connect the extra client ``lane`` and read one entry of the first device on it;
        True if that was answered (data or an exception answer)."""
        p = next(iter(self._points.values()))
        try:
            if not (lane.connect() and lane.connected):
                return False
            self.host.stat(self.bus.name, "requests")
            READ_CALL[p.table](lane, p.address, count=1, device_id=p.unit)
        except (ModbusException, OSError):
            return False
        return bool(lane.connected)

    def _lane_pool(self) -> ThreadPoolExecutor:
        """The driver's threads for the extra connections' shares, one per extra connection."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self._connections() - 1,
                                            thread_name_prefix=f"{self.kind}-{self.bus.name}-lane")
        return self._pool

    def _end_lanes(self) -> None:
        """At stop: end the threads of the extra connections (a share still running - a request
        past the join timeout - ends by its own timeout)."""
        pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)

    def _poll(self, plan: Sequence[ReadRequest]) -> None:
        """Run the requests of one poll: in order on one connection, or - several requests and
        ``connections`` > 1 - spread over the connections, all of them outstanding at once (each
        connection runs its share in order on its own thread; a pymodbus client has one request
        in flight). Every request reports its own failures; a lost connection ends the poll
        with :class:`ConnectionException` (or the :class:`OSError` the socket raised) once every
        request is answered or failed."""
        batch: list[tuple[str, Any]] = []
        try:
            clients = self._open_lanes() if len(plan) > 1 else [self._client]
            if len(clients) == 1:
                c = self._client
                for request in plan:
                    self._read(request, c, batch)
                return
            n = min(len(clients), len(plan))
            pool = self._lane_pool()
            futures: list[Future[None]] = [
                pool.submit(self._share, plan[i::n], clients[i], batch) for i in range(1, n)]
            errors: list[BaseException] = []
            try:
                self._share(plan[0::n], clients[0], batch)
            except (ModbusException, OSError) as exc:
                errors.append(exc)
            for f in futures:
                err = f.exception()    # waits: every request has its timeout
                if err is not None:
                    errors.append(err)
            if errors:
                raise errors[0]
        finally:   # the poll's readings as one interrupt, before a lost link fails them
            deliver_all(self.host, batch)

    def _share(self, requests: Sequence[ReadRequest], c: Any,
               batch: list[tuple[str, Any]]) -> None:
        """One connection's share of a parallel poll, in order (a lane thread, or the worker)."""
        for request in requests:
            self._read(request, c, batch)

    def _read(self, r: ReadRequest, c: Any, batch: list[tuple[str, Any]]) -> None:
        """Run one read request on client ``c``; its readings go to ``batch`` (delivered at the
        end of the poll), its failures to the host at once. Raises ConnectionException when
        the link is lost (TCP: also when the server does not answer)."""
        with self._lock:
            if not self._units.due(r.unit):
                return                 # a dead unit sitting out its turn
            self.host.stat(self.bus.name, "requests")
        try:
            resp = READ_CALL[r.table](c, r.address, count=r.count, device_id=r.unit)
        except ModbusIOException as exc:
            with self._lock:
                self._read_unanswered(r, c, exc)
            return
        with self._lock:
            self._read_answered(r, resp, batch)

    def _read_unanswered(self, r: ReadRequest, c: Any, exc: ModbusIOException) -> None:
        kind, what = self._unanswered(r.describe())
        for p in r.points:
            self.host.error(self.bus.name, kind, f"{r.describe()}: {what}: {exc}", p.device)
        if not c.connected or self.timeout_is_link_loss:
            raise ConnectionException(f"no response: {exc}") from exc
        where = f"{self.kind} bus {self.bus.name} {r.describe()}"
        if kind == "timeout":
            self._unit_silent(r.unit, where, what)
            return
        for p in r.points:           # garbled: the unit is there, its answer was not usable
            self._health.fail(p.device, "exception", f"{where} (device {p.device}): {what}")

    def _read_answered(self, r: ReadRequest, resp: Any, batch: list[tuple[str, Any]]) -> None:
        if resp.isError():
            code = int(getattr(resp, "exception_code", 0))
            for p in r.points:
                self.host.error(self.bus.name, f"exception-{code}",
                                f"{r.describe()}: exception code {code}", p.device)
            for p in r.points:
                self._health.fail(p.device, "exception",
                                  f"{self.kind} bus {self.bus.name} {r.describe()} (device "
                                  f"{p.device}): exception code {code} "
                                  f"({EXCEPTION_TEXT.get(code, 'unknown')})")
            self._answer(r.unit)       # after the new cause: no OK in between
            return
        if not self._answered or self._units.dead(r.unit):
            self._answer(r.unit)
        entries = resp.bits if r.table in ("coil", "discrete") else resp.registers
        for p in r.points:
            off = p.address - r.address
            try:        # a point that is the whole answer takes it as it is (no copy)
                value = reading_of(p, entries if off == 0 and len(entries) == p.size else
                                   entries[off:off + p.size])
            except (ModbusException, IndexError, ValueError) as exc:
                self.host.error(self.bus.name, "malformed",
                                f"{r.describe()} answer for {p.device}: {exc}")
                continue
            if self._health.has_causes(p.device):
                self._health.clear(p.device, "exception", f"{r.describe()} answered")
            batch.append((p.device, value))

    def _write(self, device: str, value: Any) -> None:
        """Queue a ``write`` job stamped with its unit's epoch; never blocks."""
        p = self._points.get(device)
        job = QueuedWrite(value, self._units.epoch(p.unit) if p is not None else 0)
        if not self._submit(JobOp.WRITE, device, job):
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")

    def _write_point(self, p: Point, job: QueuedWrite) -> None:
        c = self._client
        value = job.value
        if job.epoch != self._units.epoch(p.unit):
            stale = (f"{self.kind} bus {self.bus.name} unit {p.unit} stopped answering after "
                     f"the write was queued: not sent (re-issue it)")
            self.host.error(self.bus.name, "not-sent", f"write {value!r} to {p.device}: {stale}",
                            p.device)
            self.host.write_failed(p.device, value, stale)
            return
        why = value_error(p.type, value)
        if why is not None:
            self.host.error(self.bus.name, "range", f"write {value!r} to {p.device}: {why}",
                            p.device)
            self.host.write_failed(p.device, value, why)
            return
        where = f"{self.kind} bus {self.bus.name} unit {p.unit} {p.table} {p.address}"
        self.host.stat(self.bus.name, "requests", device=p.device)
        try:
            if p.table == "coil":
                resp = c.write_coil(p.address, bool(value), device_id=p.unit)
            else:
                regs = p.encode(value)
                resp = (c.write_register(p.address, regs[0], device_id=p.unit) if len(regs) == 1
                        else c.write_registers(p.address, regs, device_id=p.unit))
        except ModbusIOException as exc:
            kind, what = self._unanswered(where)
            self.host.error(self.bus.name, kind, f"{where}: write not answered: {what}: {exc}",
                            p.device)
            if not c.connected or self.timeout_is_link_loss:
                raise ConnectionException(f"no response: {exc}") from exc
            self.host.write_failed(p.device, value, f"{where}: write not answered: {exc}")
            self._write_failed(p, f"{where} (device {p.device}): write not answered: {exc}")
            if kind == "timeout":
                self._unit_silent(p.unit, where, what)
            return
        except ConnectionException:
            raise                           # the link is lost: the worker's supervision
        except ModbusException as exc:      # an answer that is no valid answer
            text = f"{where} (device {p.device}): write answer malformed: {exc}"
            self.host.error(self.bus.name, "malformed", text, p.device)
            self.host.write_failed(p.device, value, text)
            self._write_failed(p, text)
            return
        if resp.isError():
            code = int(getattr(resp, "exception_code", 0))
            text = (f"{where} (device {p.device}): write refused with exception code "
                    f"{code} ({EXCEPTION_TEXT.get(code, 'unknown')})")
            self.host.error(self.bus.name, f"exception-{code}", text, p.device)
            self.host.write_failed(p.device, value, text)
            self._write_failed(p, text)
            self._answer(p.unit)       # after the new cause: no OK in between
            return
        self._answer(p.unit)
        self.host.written(p.device, value)
        self._readback.discard(p.device)
        self._health.clear(p.device, WRITE_CAUSE, f"{where}: write answered")

    # -- no latch: the read-back of actuators whose write failed -------------------------------

    def _write_failed(self, p: Point, reason: str) -> None:
        """A write to ``p`` failed while its unit is there (exception answer, or on RTU no
        answer): the actuator fails (cause ``write``) and is read back at the poll cadence
        until its unit answers (:meth:`_read_back`), so the failure does not latch while every
        command to it is refused."""
        self._health.fail(p.device, WRITE_CAUSE, reason)
        self._readback.add(p.device)
        self._arm_readback()

    def _arm_readback(self) -> None:
        """Queue the read-back job one ``poll_period`` from now, unless it is armed already
        (any thread)."""
        with self._lock_readback:
            if self._readback_armed or not self._running:
                return
            self._readback_armed = True
        period = float(self.bus.options.get("poll_period", 0.1))
        self.host.at(round(self.host.now() + period, 9), self._readback_due)

    def _readback_due(self) -> None:
        """The kernel timer of the read-back: hand the job to the worker."""
        with self._lock_readback:
            self._readback_armed = False
        self._submit_poll(LinkChore.READBACK)

    def _read_back(self) -> None:
        """The read-back job: read each write-failed actuator's own coil or registers. Data,
        or an exception answer saying the entry cannot be read (codes 1, 2, 3), is its unit
        answering: the write failure ends. Busy, acknowledge, other codes and silence keep it;
        the job is armed again while an actuator is left. On ``modbus-tcp`` silence is a lost
        link (raises ConnectionException)."""
        self._poll_taken(LinkChore.READBACK)
        try:      # a lost link ends the loop: armed again all the same
            for name in sorted(self._readback):
                if self._unit_due(self._points[name].unit):
                    self._read_back_one(name)
        finally:
            if self._readback:
                self._arm_readback()

    def _read_back_one(self, name: str) -> None:
        """Read write-failed actuator ``name``'s entries back (see :meth:`_read_back`)."""
        p = self._points[name]
        where = f"{self.kind} bus {self.bus.name} read-back of unit {p.unit} {p.table} " \
                f"{p.address}"
        self.host.stat(self.bus.name, "requests")
        try:
            resp = READ_CALL[p.table](self._client, p.address, count=p.size, device_id=p.unit)
        except ModbusIOException as exc:
            kind, what = self._unanswered(where)
            self.host.error(self.bus.name, kind, f"{where}: {what}: {exc}", name)
            if not self._client.connected or self.timeout_is_link_loss:
                raise ConnectionException(f"no response to the read-back: {exc}") from exc
            self._unit_silent(p.unit, where, what)
            return
        code = int(getattr(resp, "exception_code", 0)) if resp.isError() else 0
        self._answer(p.unit)
        if code and code not in UNIT_ANSWERED:
            self.host.error(self.bus.name, f"exception-{code}", f"{where}: exception code {code}",
                            name)
            return
        self._readback.discard(name)
        self._health.clear(name, WRITE_CAUSE, f"{where} (device {name}) answered" + (
            f" (exception code {code}: {EXCEPTION_TEXT.get(code, 'unknown')})" if code else ""))

    # -- the watchdog register ------------------------------------------------------------------

    def _beat(self) -> None:
        """The watchdog job: write the next watchdog value. Not answered: as any request
        (``modbus-tcp``: a lost link, raises ConnectionException; ``modbus-rtu``: the unit's
        devices fail). An exception answer fails the devices of the watchdog's unit (cause
        ``watchdog``: the PLC will act on the loss) until a write is answered."""
        wd = self._watchdog
        if wd is None or not self._unit_due(wd.unit):
            return
        c = self._client
        value = wd.value_at(self._beats)
        self._beats += 1
        where = f"{self.kind} bus {self.bus.name} watchdog {wd.describe()}"
        self.host.stat(self.bus.name, "requests")
        try:
            resp = (c.write_coil(wd.address, bool(value), device_id=wd.unit)
                    if wd.table == "coil" else
                    c.write_register(wd.address, value, device_id=wd.unit))
        except ModbusIOException as exc:
            kind, what = self._unanswered(where)
            self.host.error(self.bus.name, kind, f"{where}: write not answered: {what}: {exc}")
            if not c.connected or self.timeout_is_link_loss:
                raise ConnectionException(f"no response to the watchdog: {exc}") from exc
            self._unit_silent(wd.unit, where, f"watchdog write not answered: {what}")
            return
        self._answer(wd.unit)
        names = [n for n, q in self._points.items() if q.unit == wd.unit]
        if resp.isError():
            code = int(getattr(resp, "exception_code", 0))
            text = (f"{where}: write refused with exception code {code} "
                    f"({EXCEPTION_TEXT.get(code, 'unknown')})")
            self.host.error(self.bus.name, f"exception-{code}", text)
            for name in names:
                self._health.fail(name, WATCHDOG_CAUSE, f"{text} (device {name})")
            return
        self.host.stat(self.bus.name, "watchdog")
        for name in names:
            self._health.clear(name, WATCHDOG_CAUSE, f"{where}: write answered")

    def _unit_due(self, unit: int) -> bool:
        """Whether a request to ``unit`` goes out now (a dead unit sits out some turns)."""
        with self._lock:
            return self._units.due(unit)

    def _unit_silent(self, unit: int, where: str, what: str) -> None:
        """RTU: ``unit`` did not answer the request ``where``: every device of the unit fails
        (cause ``unit``), its later requests are thinned out (:class:`UnitBackoff`), and
        writes queued for it until now are not sent."""
        self._units.silent(unit)
        for name, q in self._points.items():
            if q.unit == unit:
                self._health.fail(name, UNIT_CAUSE, f"{where} (device {name}): {what}")

    def _unit_back(self, unit: int) -> None:
        """``unit`` answered after it had stopped: its devices lose the cause ``unit``."""
        if not self._units.answered(unit):
            return
        for name, q in self._points.items():
            if q.unit == unit:
                self._health.clear(name, UNIT_CAUSE, f"{self.kind} bus {self.bus.name}: unit "
                                                     f"{unit} answers again")
