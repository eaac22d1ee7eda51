"""requests - the jobs of a Modbus driver and what their answers mean for the devices.

Each job - a poll of the sensors of one period, a write, the liveness probe, the watchdog
write, the read-back of write-failed actuators, the first read after a connect - is a generator
that yields the requests it wants sent (:class:`Exchange`, or a :class:`Batch` of requests to
send at once over several connections) and is sent back their :data:`Outcome` (a
:class:`drivers.modbus.transactions.Outcome`, or :class:`Sent` for a broadcast). The engines
(:mod:`drivers.modbus.engine`) run the same jobs on a worker thread over a socket or serial
port, or on the kernel thread against an in-process slave; a job raises :class:`LinkLost` when
what came back (nothing, several times) is a connection-level cause, and an engine throws it
into the job when the transport fails under it.

What an outcome means:

* data: the readings (a poll's go to the host as one interrupt, at the end of the poll, with the
  scale factors read in the same poll applied), the device's request-level failures end;
* an exception answer: the devices of that request fail with the code and its meaning (on a
  gateway, 0x0A/0x0B are the unit's absence: its devices fail as a silent unit's); a refused
  write fails the actuator (cause ``write``) and starts its read-back;
* an unusable answer (bad CRC, junk, truncated, wrong function, unit or transaction id, short
  byte count, no echo): counted by cause, never delivered; the request's devices fail (cause
  ``malformed``) at the first one if the request was never answered well, else after
  :data:`MALFORMED_LIMIT` in a row;
* no answer: on a serial line or a gateway the unit fails (:class:`drivers.modbus.link.Units`),
  on a TCP device the request's devices fail (cause ``timeout``); the link decides whether the
  connection is lost (:meth:`drivers.modbus.link.Link.unanswered`).

Errors are reported once per streak with their counts (:class:`drivers.reports.Reports`).
"""

from __future__ import annotations

import enum
from collections import Counter
from collections.abc import Callable, Generator, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.base import DriverHost, deliver_all
from drivers.codecs.modbus import (
    BIT_TABLES,
    Absent,
    Point,
    exception_text,
    reading_of,
    scale_factor_error,
    scale_factor_point,
    unscaled,
    value_error,
)
from drivers.health import Health
from drivers.modbus.config import BusPlan, PlannedRead
from drivers.modbus.link import Link, Units
from drivers.modbus.transactions import (
    Answer,
    Cause,
    NoAnswer,
    Outcome,
    Refused,
    Request,
    Unusable,
    bits_of,
    read_request,
    registers_of,
    write_request,
)
from drivers.reports import Reports

#: unusable answers in a row (after good ones) that fail a request's devices, as CAN fails a
#: sensor after three malformed frames
MALFORMED_LIMIT = 3
#: exception codes to a read-back that still mean the unit answered: the entry cannot be read
UNIT_ANSWERED = frozenset({1, 2, 3})
#: exception codes of a gateway whose unit is absent or silent
GATEWAY_CODES = frozenset({10, 11})
WRITE_CAUSE = "write"
WATCHDOG_CAUSE = "watchdog"
EXCEPTION_CAUSE = "exception"
MALFORMED_CAUSE = "malformed"
TIMEOUT_CAUSE = "timeout"
UNIMPLEMENTED_CAUSE = "unimplemented"
#: the causes a good answer to a device's own request ends
REQUEST_CAUSES = (EXCEPTION_CAUSE, MALFORMED_CAUSE, TIMEOUT_CAUSE)


@dataclass(frozen=True, slots=True)
class Exchange:
    """A job's step: send ``request``, and send me its outcome."""

    request: Request


@dataclass(frozen=True, slots=True)
class Batch:
    """A job's step: send ``requests`` at once (over several connections), and send me their
    outcomes in the same order."""

    requests: tuple[Request, ...]


@dataclass(frozen=True, slots=True)
class Sent:
    """The outcome of a broadcast: it went out; by protocol nobody answers it."""


class LinkLost(Exception):
    """The connection is lost (a connection-level cause): ``str(exc)`` says why."""


Step = Exchange | Batch
JobRun = Generator[Step, Any, None]


class Role(enum.Enum):
    """What a request is to the devices it concerns: a poll's read of their values, a probe of
    their unit, or another request (a write, a read-back, the watchdog)."""

    READ = "read"
    PROBE = "probe"
    OTHER = "other"


READ, PROBE, OTHER = Role.READ, Role.PROBE, Role.OTHER


@dataclass(frozen=True)
class QueuedWrite:
    """A write job's value and the epoch of its unit when it was queued (see
    :meth:`drivers.codecs.modbus.UnitBackoff.epoch`): a write queued before its unit stopped
    answering is not sent after that."""

    device: str
    value: Any
    epoch: int


class ModbusRequests:
    """The jobs of one Modbus bus and what their outcomes mean (see the module doc). Its state
    is the engine's thread's (one job at a time); :meth:`epoch` is read on any thread."""

    def __init__(self, host: DriverHost, bus: str, name: str, plan: BusPlan, health: Health,
                 link: Link, units: Units, reports: Reports, parallel: bool,
                 clock: Callable[[], float], arm_readback: Callable[[], None]) -> None:
        self._host = host
        #: queues the read-back of the write-failed actuators (the driver's)
        self._arm_readback = arm_readback
        #: the engine's clock (the guard of a unit that missed a request is kept on it)
        self._clock = clock
        self._bus = bus
        #: ``modbus-rtu bus line`` - the start of every reason
        self.name = name
        self.plan = plan
        self._health = health
        self.link = link
        self.units = units
        self._reports = reports
        self._parallel = parallel
        #: requests that got no usable answer, by cause (``crc``, ``framing``, ``timeout``...)
        self.unanswered: Counter[str] = Counter()
        self._bad: dict[str, int] = {}          # subject -> unusable answers in a row
        self._good: set[str] = set()            # subjects answered well at least once
        #: actuators whose last write failed with their unit there: read back until it answers
        self.readback: set[str] = set()
        self._beats = 0

    def epoch(self, device: str) -> int:
        """The epoch of ``device``'s unit now (see :class:`QueuedWrite`)."""
        p = self.plan.points.get(device)
        return self.units.epoch(p.unit) if p is not None else 0

    # ---- polls ------------------------------------------------------------------------------
    def poll(self, reads: Sequence[PlannedRead]) -> JobRun:
        """One poll: its reads (at once over several connections where the bus has them, else
        in order, a dead unit's sitting out its turn), then the readings as one interrupt."""
        got: list[tuple[Point, list[Any]]] = []
        factors: dict[tuple[int, str, int], int] = {}
        try:
            if self._parallel and len(reads) > 1:
                self._host.stat(self._bus, "requests", len(reads))
                outcomes = yield Batch(tuple(r.request for r in reads))
                self._batch(reads, outcomes, got, factors)
                return
            for r in reads:
                if not self.units.due(r.read.unit):
                    continue
                self._host.stat(self._bus, "requests")
                outcome = yield Exchange(r.request)
                self._read_outcome(r, outcome, got, factors)
        finally:    # the readings taken, before a lost link fails the devices
            deliver_all(self._host, self._readings(got, factors))

    def _batch(self, reads: Sequence[PlannedRead], outcomes: Sequence[Outcome],
               got: list[tuple[Point, list[Any]]],
               factors: dict[tuple[int, str, int], int]) -> None:
        """The outcomes of a parallel poll: the answered ones first (they show the connection
        carries answers), then the others; a lost connection after all of them."""
        order = sorted(range(len(reads)), key=lambda i: isinstance(outcomes[i], NoAnswer))
        lost = ""
        for i in order:
            try:
                self._read_outcome(reads[i], outcomes[i], got, factors)
            except LinkLost as exc:
                lost = lost or str(exc)
        if lost:
            raise LinkLost(lost)

    def _read_outcome(self, planned: PlannedRead, outcome: Outcome,
                      got: list[tuple[Point, list[Any]]],
                      factors: dict[tuple[int, str, int], int]) -> None:
        """What one read's outcome means (see the module doc)."""
        r = planned.read
        devices = [p.device for p in r.points if p.device]
        where = f"{self.name} {r.describe()}"
        if not self._judge(r.describe(), r.unit, where, devices, outcome,
                           planned.request.pdu, READ):
            return
        assert isinstance(outcome, Answer)
        entries: list[Any] = (bits_of(outcome, r.count) if r.table in BIT_TABLES
                              else registers_of(outcome))
        for p in r.points:
            off = p.address - r.address
            part = entries[off:off + p.size]
            if p.device:
                got.append((p, part))
            elif part:
                factors[(p.unit, p.table, p.address)] = part[0] - 0x10000 \
                    if part[0] & 0x8000 else part[0]

    def _readings(self, got: Iterable[tuple[Point, list[Any]]],
                  factors: Mapping[tuple[int, str, int], int]) -> list[tuple[str, Any]]:
        """The readings of a poll, each with its scale factor read in the same poll (a value
        whose factor was not read is not delivered)."""
        out: list[tuple[str, Any]] = []
        for p, part in got:
            sf = None
            if p.scale_factor is not None:
                sf = factors.get((p.unit, p.table, p.scale_factor))
                if sf is None:
                    continue
            where = f"{self.name} {p.describe()} (device {p.device})"
            try:
                value = reading_of(p, part, sf)
            except (ValueError, IndexError) as exc:
                self._reports.error(MALFORMED_CAUSE, p.describe(), f"{where}: {exc}", p.device)
                self._health.fail(p.device, MALFORMED_CAUSE, f"{where}: {exc}")
                continue
            if isinstance(value, Absent):
                self._health.fail(p.device, UNIMPLEMENTED_CAUSE,
                                  f"{where}: not implemented ({value.reason})")
                continue
            if self._health.has_causes(p.device):
                for cause in (MALFORMED_CAUSE, UNIMPLEMENTED_CAUSE):
                    self._health.clear(p.device, cause, f"{where}: a value")
            out.append((p.device, value))
        return out

    # ---- what an outcome means --------------------------------------------------------------
    def _judge(self, subject: str, unit: int, where: str, devices: Sequence[str],
               outcome: Outcome, request: bytes, role: Role) -> bool:
        """Count and report ``outcome`` of the request ``subject`` (of ``role``: a poll's read
        of ``devices``, a probe of their unit, or another request about them); True for an
        answer with data. Raises LinkLost when nothing came back and that loses the
        connection."""
        if isinstance(outcome, NoAnswer):
            self._no_answer(subject, unit, where, devices, outcome, request, role)
            return False
        self.link.answered(unit)
        if self.plan.per_unit and not (isinstance(outcome, Refused)
                                       and outcome.code in GATEWAY_CODES):
            self.units.back(unit)
        if role is not OTHER:
            ended = REQUEST_CAUSES if role is READ else (TIMEOUT_CAUSE,)
            if isinstance(outcome, Answer) or role is PROBE:
                for d in devices:
                    if self._health.has_causes(d):
                        for cause in ended:
                            self._health.clear(d, cause, f"{where} answered")
        if isinstance(outcome, Answer):
            self._reports.ok(subject)
            self._bad.pop(subject, None)
            self._good.add(subject)
            return True
        if isinstance(outcome, Refused):
            self._refused(subject, unit, where, devices, outcome.code, request, role)
        elif isinstance(outcome, Unusable):
            self._unusable(subject, where, devices, outcome, role)
        return False

    def _refused(self, subject: str, unit: int, where: str, devices: Sequence[str], code: int,
                 request: bytes, role: Role) -> None:
        text = exception_text(code)
        self._reports.error(f"exception-{code}", subject, f"{where}: {text}",
                            devices[0] if devices else "")
        self._bad.pop(subject, None)
        if code in GATEWAY_CODES and self.plan.per_unit:
            self.units.silent(unit, where, text, self._clock(), request)
        elif role is READ:
            for d in devices:
                self._health.fail(d, EXCEPTION_CAUSE, f"{where} (device {d}): {text}")

    def _unusable(self, subject: str, where: str, devices: Sequence[str], outcome: Unusable,
                  role: Role) -> None:
        self.unanswered[outcome.cause.value] += 1
        self._reports.error(outcome.cause.value, subject, f"{where}: {outcome.detail}",
                            devices[0] if devices else "")
        n = self._bad[subject] = self._bad.get(subject, 0) + 1
        if role is not READ or (subject in self._good and n < MALFORMED_LIMIT):
            return
        why = (f"{n} unusable answers in a row, the last: {outcome.detail}"
               if subject in self._good else outcome.detail)
        for d in devices:
            self._health.fail(d, MALFORMED_CAUSE, f"{where} (device {d}): {why}")

    def _no_answer(self, subject: str, unit: int, where: str, devices: Sequence[str],
                   outcome: NoAnswer, request: bytes, role: Role) -> None:
        self.unanswered[Cause.TIMEOUT.value] += 1
        self._reports.error(Cause.TIMEOUT.value, subject, f"{where}: {outcome.detail}",
                            devices[0] if devices else "")
        if self.plan.per_unit:
            self.units.silent(unit, where, outcome.detail, self._clock(), request)
        elif role is not OTHER:
            for d in devices:
                self._health.fail(d, TIMEOUT_CAUSE, f"{where} (device {d}): {outcome.detail}")
        lost = self.link.unanswered()
        if lost:
            raise LinkLost(lost)

    # ---- the liveness probe and the first read after a connect ------------------------------
    def contact(self) -> JobRun:
        """Right after a TCP connect: read one entry of the first device of each different
        request, until one is answered; as many silent ones as lose a connection lose this
        one (see :meth:`drivers.modbus.link.Link.unanswered`)."""
        for p in self.contact_points():
            yield from self._probe_one(p, "probe after connect", OTHER)
            if self.link.proven:
                return

    def contact_points(self) -> list[Point]:
        """The points probed after a connect: the first of each planned read, then those of
        the units no poll reads, at most :data:`drivers.modbus.link.SILENT_REQUESTS`."""
        firsts = [next(q for q in r.read.points if q.device) for plan in self.plan.polls.values()
                  for r in plan if any(q.device for q in r.read.points)]
        return (firsts + list(self.plan.probed))[:self.link.silent_limit]

    def probe(self) -> JobRun:
        """The periodic probe of the units no poll reads (an actuator-only bus, or on a line
        the units with actuators only): one entry of each one's first actuator."""
        for p in self.plan.probed:
            if self.units.due(p.unit):
                yield from self._probe_one(p, "probe", PROBE)

    def _probe_one(self, p: Point, what: str, role: Role) -> JobRun:
        where = f"{self.name} {what} of {p.describe()}"
        req = read_request(p.unit, p.table, p.address, 1, where)
        self._host.stat(self._bus, "requests")
        outcome = yield Exchange(req)
        if isinstance(outcome, NoAnswer):
            outcome = NoAnswer(f"no answer: {outcome.detail}")
        self._judge(f"{what} {p.describe()}", p.unit, where, [p.device], outcome, req.pdu, role)

    # ---- writes -----------------------------------------------------------------------------
    def write(self, job: QueuedWrite) -> JobRun:
        """One write: refused unsent when its unit stopped answering since it was queued or
        the value does not fit; a scale factor read first where the address has one; then the
        write and what its answer means."""
        p = self.plan.points[job.device]
        value = job.value
        if not p.broadcast and job.epoch != self.units.epoch(p.unit):
            stale = (f"{self.name} unit {p.unit} stopped answering after the write was queued: "
                     f"not sent (re-issue it)")
            self._host.error(self._bus, "not-sent", f"write {value!r} to {p.device}: {stale}",
                             p.device)
            self._host.write_failed(p.device, value, stale)
            return
        where = f"{self.name} {p.describe()}"
        raw = value
        if p.scale_factor is not None:
            raw = yield from self._unscaled(p, value, where)
            if raw is None:
                return
        why = value_error(p.type, raw, p.count)
        if why is not None:
            self._host.error(self._bus, "range", f"write {value!r} to {p.device}: {why}",
                             p.device)
            self._host.write_failed(p.device, value, why)
            return
        req = (write_request(p.unit, p.table, p.address, bit=bool(raw), what=where)
               if p.table == "coil" else
               write_request(p.unit, p.table, p.address, p.encode(raw), what=where))
        self._host.stat(self._bus, "requests", device=p.device)
        try:
            outcome = yield Exchange(req)
        except LinkLost as exc:
            self._host.write_failed(p.device, value, f"connection to {self.link.where} lost: "
                                                     f"{exc}")
            raise
        self._write_outcome(p, value, where, req, outcome)

    def _unscaled(self, p: Point, value: Any, where: str) -> Generator[Step, Any, int | None]:
        """The raw value of ``value`` for ``p`` after reading its scale factor (None, the write
        reported failed, when the factor cannot be read or the value not represented)."""
        sf_point = scale_factor_point(p)
        req = read_request(p.unit, p.table, sf_point.address, 1, where)
        self._host.stat(self._bus, "requests", device=p.device)
        outcome = yield Exchange(req)
        why = ""
        sf = 0
        if isinstance(outcome, Answer):
            word = registers_of(outcome)[0]
            sf = word - 0x10000 if word & 0x8000 else word
            why = scale_factor_error(sf) or ""
        else:
            why = _outcome_text(outcome)
        raw = unscaled(value, sf) if not why else None
        if raw is None:
            text = (f"{where} (device {p.device}): scale factor {p.table} {p.scale_factor}: "
                    f"{why or f'{value!r} is no integer multiple of 10^{sf}'}")
            self._host.error(self._bus, "scale-factor", text, p.device)
            self._host.write_failed(p.device, value, text)
        return raw

    def _write_outcome(self, p: Point, value: Any, where: str, req: Request,
                       outcome: Outcome | Sent) -> None:
        name = p.device
        if isinstance(outcome, Sent):       # broadcast: nobody answers it, by protocol
            self._host.written(name, value)
            return
        subject = f"write {p.describe()}"
        try:
            ok = self._judge(subject, p.unit, where, [name], outcome, req.pdu, OTHER)
        except LinkLost:
            self._host.write_failed(name, value, f"{where}: write not answered")
            raise
        if ok:
            self._host.written(name, value)
            self.readback.discard(name)
            self._health.clear(name, WRITE_CAUSE, f"{where}: write answered")
            return
        text = f"{where} (device {name}): {_write_text(outcome)}"
        self._host.write_failed(name, value, text)
        self._write_failed(name, text)

    def _write_failed(self, name: str, reason: str) -> None:
        """A write failed while its unit is there: the actuator fails (cause ``write``) and is
        read back until its unit answers, so the failure does not latch."""
        self._health.fail(name, WRITE_CAUSE, reason)
        self.readback.add(name)
        self._arm_readback()

    # ---- the read-back of write-failed actuators --------------------------------------------
    def read_back(self) -> JobRun:
        """Read each write-failed actuator's own entries: data, or an exception answer saying
        the entry cannot be read (codes 1, 2, 3), is its unit answering - the write failure
        ends; busy, acknowledge, other codes and silence keep it."""
        for name in sorted(self.readback):
            p = self.plan.points[name]
            if p.broadcast or not self.units.due(p.unit):
                continue
            where = f"{self.name} read-back of {p.describe()}"
            req = read_request(p.unit, p.table, p.address, p.size, where)
            self._host.stat(self._bus, "requests")
            outcome = yield Exchange(req)
            self._judge(f"read-back {p.describe()}", p.unit, where, [name], outcome, req.pdu,
                        OTHER)
            if isinstance(outcome, Answer) or (isinstance(outcome, Refused)
                                               and outcome.code in UNIT_ANSWERED):
                self.readback.discard(name)
                extra = (f" ({exception_text(outcome.code)})" if isinstance(outcome, Refused)
                         else "")
                self._health.clear(name, WRITE_CAUSE, f"{where} (device {name}) answered"
                                                      f"{extra}")

    # ---- the watchdog register ----------------------------------------------------------------
    def beat(self) -> JobRun:
        """Write the next watchdog value. An exception answer fails the devices of the
        watchdog's unit (cause ``watchdog``: the PLC will act on the loss) until a write is
        answered; no answer is handled as any request's."""
        wd = self.plan.watchdog
        if wd is None or not self.units.due(wd.unit):
            return
        value = wd.value_at(self._beats)
        self._beats += 1
        where = f"{self.name} watchdog {wd.describe()}"
        req = write_request(wd.unit, wd.table, wd.address, [value], bit=bool(value), what=where)
        self._host.stat(self._bus, "requests")
        outcome = yield Exchange(req)
        if isinstance(outcome, Sent):
            self._host.stat(self._bus, "watchdog")
            return
        names = [n for n, q in self.plan.points.items() if q.unit == wd.unit]
        ok = self._judge(f"watchdog {wd.describe()}", wd.unit, where, [], outcome, req.pdu,
                         OTHER)
        if ok:
            self._host.stat(self._bus, "watchdog")
            for name in names:
                self._health.clear(name, WATCHDOG_CAUSE, f"{where}: write answered")
        elif isinstance(outcome, Refused):
            text = f"{where}: write refused with {exception_text(outcome.code)}"
            for name in names:
                self._health.fail(name, WATCHDOG_CAUSE, f"{text} (device {name})")


def _outcome_text(outcome: Outcome | Sent) -> str:
    if isinstance(outcome, Refused):
        return exception_text(outcome.code)
    if isinstance(outcome, Unusable):
        return f"unusable answer ({outcome.cause.value}): {outcome.detail}"
    if isinstance(outcome, NoAnswer):
        return outcome.detail
    return "no answer"


def _write_text(outcome: Outcome | Sent) -> str:
    if isinstance(outcome, Refused):
        return f"write refused with {exception_text(outcome.code)}"
    if isinstance(outcome, NoAnswer):
        return f"write not answered: {outcome.detail}"
    return f"write answer malformed: {_outcome_text(outcome)}"
