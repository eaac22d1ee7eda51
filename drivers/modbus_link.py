"""modbus_link - what the ``modbus-tcp`` and ``modbus-rtu`` drivers share: the options both take,
the life cycle, the jobs (polls, writes, probes) on the driver's worker thread
(:class:`drivers.jobs.WorkerJobDriver`, pymodbus' synchronous clients) and the supervision of
the link (connect, probe, reconnect with backoff, failing and recovering the devices). The
requests themselves are :mod:`drivers.modbus_requests`; the kinds, their options and the failure
rules are described in :mod:`drivers.modbus`.
"""

from __future__ import annotations

import math
import queue
import time
from collections.abc import Sequence
from typing import Any

from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from chcos.helpers import is_int, is_number
from drivers.codecs.modbus import (
    RAW_RANGE,
    Point,
    UnitBackoff,
    accepted,
    check_address,
    check_watchdog,
    plan_reads,
    point_of,
    value_error,
    watchdog_of,
)
from drivers.jobs import Job, JobOp
from drivers.modbus_jobs import LinkChore, SensorPoll
from drivers.modbus_requests import (
    DEAD_UNIT_SHARE,
    DEFAULT_DEAD_UNIT_BACKOFF,
    READ_CALL,
    ModbusRequests,
    QueuedWrite,
    raw_value,
)

PROBE_PERIOD = 1.0   # s between liveness probes of an actuator-only bus without poll_period
FLUSH_NOTICE = 0.05  # s: how soon a reconnect backoff notices that the shutdown flush began
MAX_CONNECTIONS = 16   # the most connections a modbus-tcp bus may open for parallel polls
COMMON_OPTIONS = ("timeout", "retries", "reconnect_delay", "reconnect_delay_max", "poll_period",
                  "watchdog")


def dead_unit_backoff(bus: BusSpec) -> int:
    """The most poll periods between two tries of a unit that stopped answering: the bus's
    ``dead_unit_backoff``, else 8 - but never so few that the dead unit's tries take more than
    a twentieth of the line's time (the live units keep 95 % of their polls)."""
    o = bus.options
    if "dead_unit_backoff" in o:
        return int(o["dead_unit_backoff"])
    return max(DEFAULT_DEAD_UNIT_BACKOFF, share_turns(bus))


def dead_unit_first(bus: BusSpec) -> int:
    """The poll periods between the first two tries of a unit that stopped answering (later
    gaps double up to :func:`dead_unit_backoff`): as many as keep its tries within a twentieth
    of the line's time from its first miss on, so the live units keep their rate while the
    unit is backed off too, not only once the backoff reached its cap; 1 (the next poll) when
    a try costs little beside the poll period. Never more than the cap."""
    return min(dead_unit_backoff(bus), share_turns(bus))


def share_turns(bus: BusSpec) -> int:
    """Poll periods per try of a dead unit that keep its tries (``timeout`` x (``retries`` +
    1) each, the time such a try holds the line) within a twentieth of the line's time."""
    o = bus.options
    cost = float(o.get("timeout", 1.0)) * (int(o.get("retries", 1)) + 1)
    period = float(o.get("poll_period", 0.1))
    return max(1, math.ceil((DEAD_UNIT_SHARE - 1) * cost / period - 1e-9))


def check_common(bus: BusSpec, own: Sequence[str]) -> list[str]:
    """Errors of the options both kinds share, and of keys neither knows."""
    k = bus.key
    o = bus.options
    valid = (*own, *COMMON_OPTIONS)
    errs = [f"{k}.{key}: unknown option for a {bus.kind} bus; valid options: {', '.join(valid)}"
            for key in o if key not in valid]
    for key in ("timeout", "reconnect_delay", "reconnect_delay_max", "poll_period"):
        if key in o and not (is_number(o[key]) and o[key] > 0):
            errs.append(f"{k}.{key}: expected a number of seconds > 0, got {o[key]!r}")
    if "retries" in o and not (is_int(o["retries"]) and o["retries"] >= 0):
        errs.append(f"{k}.retries: expected an integer >= 0, got {o['retries']!r}")
    errs.extend(check_watchdog(bus))
    return errs


class ModbusDriver(ModbusRequests):
    """What both Modbus kinds share: the life cycle, the jobs and the link's supervision on top
    of the requests (:class:`drivers.modbus_requests.ModbusRequests`); subclasses make the
    client and describe the link."""

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """Errors of a device address: unit, table, address range for the type, word order."""
        return check_address(bus, device)

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of the address's type: 0..1 for a coil, the integer types' ranges, the
        largest float32; None for float64."""
        return RAW_RANGE.get(point_of(device).type)

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """The sensor's ``poll_period``, else the bus's, else 0.1 s."""
        return float(device.address.get("poll_period", bus.options.get("poll_period", 0.1)))

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Validate, plan the polls, start the I/O thread and make the first connection attempt
        (a refused connection fails the devices; it is not an error here). Raises
        :class:`BusError` for invalid options."""
        errs = self.check_bus(self.bus)
        for dev in self.devices.values():
            errs.extend(self.check_device(self.bus, dev))
        if errs:
            raise BusError(f"{self.kind} bus {self.bus.name} ({self.bus.file}): " + "; ".join(errs))
        default = float(self.bus.options.get("poll_period", 0.1))
        by_period: dict[float, list[Point]] = {}
        for dev in self.devices.values():
            self._points[dev.name] = point_of(dev)
            if dev.direction == "sensor":
                period = float(dev.address.get("poll_period", default))
                by_period.setdefault(period, []).append(self._points[dev.name])
        self._plans = {p: plan_reads(pts) for p, pts in by_period.items()}
        seen = {q.unit for plan in self._plans.values() for r in plan for q in r.points}
        for q in self._points.values():      # the first actuator of each unit no poll reads
            if q.unit not in seen:
                seen.add(q.unit)
                self._probed.append(q)
        self._watchdog = watchdog_of(self.bus)
        units = {p.unit for p in self._points.values()}
        if self._watchdog is not None:
            units.add(self._watchdog.unit)
        self._units = UnitBackoff(dead_unit_backoff(self.bus), dead_unit_first(self.bus), units)
        self._start_worker()
        self._running = True
        timeout = float(self.bus.options.get("timeout", 1.0))
        self._first_attempt.wait(timeout + 2.0)
        for period in self._plans:
            self._poll_every(SensorPoll(period), period)
        if self._watchdog is not None:
            self._poll_every(LinkChore.WATCHDOG, self._watchdog.period)
        if self._probed:      # units with actuators only: nothing read would notice
            self._poll_every(LinkChore.PROBE,
                             float(self.bus.options.get("poll_period", PROBE_PERIOD)))

    def stop(self) -> None:
        """Stop the I/O thread and close the connection. Idempotent; never raises."""
        self._running = False
        self._stop_worker()   # runs every job queued before: they go out first
        self._end_lanes()

    # -- kernel side --------------------------------------------------------------------------

    def check_value(self, device: str, value: Any) -> str | None:
        """Why raw ``value`` does not fit the device's coil or register type (None if it does):
        a coil takes 0/1, an integer type an integer within its range, a float type a finite
        number within its range. Nothing is rounded here."""
        p = self._point(device)
        return None if p is None else value_error(p.type, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """What the device's coil or register type holds (see :func:`accepted`)."""
        p = self._point(device)
        return None if p is None else accepted(p.type)

    def _point(self, device: str) -> Point | None:
        """``device``'s point (None for a device not on this bus)."""
        return self._points.get(device) or (point_of(self.devices[device])
                                            if device in self.devices else None)

    # -- I/O thread ---------------------------------------------------------------------------

    def _work(self) -> None:
        """The worker thread: connect, probe, serve the jobs; reconnect with backoff when the
        link drops; end at the stop job."""
        o = self.bus.options
        delay = first = float(o.get("reconnect_delay", 0.1))
        most = float(o.get("reconnect_delay_max", 5.0))
        try:
            self._client = self._make_client()
            while not self._stop_seen:
                ok = self._client.connect()
                if ok and self._client.connected:
                    self._connects += 1
                    if self._connects > 1:
                        self.host.stat(self.bus.name, "reconnects")
                    self._link_up()
                    if self.timeout_is_link_loss and not self._probe():
                        self._first_attempt.set()
                        self._backoff(delay)
                        delay = min(delay * 2, most)
                        self._close()
                        continue
                    delay = first
                    self._first_attempt.set()
                    self._serve()
                else:
                    self.host.stat(self.bus.name, "connect-failed")
                    self._link_down(f"cannot connect to {self._link()}")
                    self._first_attempt.set()
                    self._backoff(delay)
                    delay = min(delay * 2, most)
                self._close()
        finally:
            self._first_attempt.set()
            if self._client is not None:
                self._close()

    def _close(self) -> None:
        """Close the main connection and every extra one of the parallel polls."""
        lanes, self._lanes, self._lanes_tried = self._lanes, [], False
        for lane in lanes:
            lane.close()
        self._client.close()

    def _backoff(self, delay: float) -> None:
        """Wait ``delay`` seconds (or until stop), completing jobs that arrive meanwhile (a
        write fails at once: the link is down). Once the shutdown flush began, the wait is
        ``reconnect_delay`` at most, so a peer that returns within the flush's window is
        reached while the safe values are still being re-issued."""
        start = time.monotonic()
        shortest = float(self.bus.options.get("reconnect_delay", 0.1))
        while not self._stop_seen:
            wait = min(delay, shortest) if self._shutting_down else delay
            left = start + wait - time.monotonic()
            if left <= 0:
                return
            try:        # wakes now and then to notice a flush that begins meanwhile
                job = self._jobs.get(timeout=min(left, FLUSH_NOTICE))
            except queue.Empty:
                continue
            self._finish_unsent(job)

    def flush(self, timeout: float) -> bool:
        """As :meth:`drivers.jobs.JobDriver.flush` (shutdown: wait until every write handed
        over is answered or reported failed); from then on, until stop, a lost link is
        reconnected every ``reconnect_delay`` instead of after the grown backoff."""
        self._shutting_down = True
        return super().flush(timeout)

    def _link_up(self) -> None:
        """Connected - not yet healthy: the link clears on the first answered request."""
        self._connected = True
        self._answered = False
        self._units_answered = set()
        if not self.timeout_is_link_loss:  # RTU: an open port is not a unit that answers
            for name, p in self._points.items():
                self._health.fail(name, "link", f"{self.kind} bus {self.bus.name}: "
                                                f"{self._link()} is open, unit {p.unit} has not "
                                                f"answered a request yet")

    def _answer(self, unit: int | None = None) -> None:
        """A request was answered (with data or an exception): the link works - on RTU for
        the devices of the ``unit`` that answered (the others stay failed until theirs does),
        and a unit that had stopped answering is back."""
        if unit is not None and self._units.dead(unit):
            self._unit_back(unit)
        if self._answered:
            return
        if not self.timeout_is_link_loss and unit is not None:
            if unit in self._units_answered:
                return
            self._units_answered.add(unit)
            for name, p in self._points.items():
                if p.unit == unit:
                    self._health.clear(name, "link", f"{self.kind} bus {self.bus.name}: unit "
                                                     f"{unit} on {self._link()} answered")
            self._answered = self._units_answered >= {p.unit for p in self._points.values()}
            return
        self._answered = True
        for name in self.devices:
            self._health.clear(name, "link", f"{self.kind} bus {self.bus.name}: a request to "
                                             f"{self._link()} was answered")

    def _probe(self) -> bool:
        """Right after a connect: read one entry of the first device; True if answered (the
        link is up), False (link down, devices still failed) if not."""
        p = next(iter(self._points.values()), None)
        if p is None:
            return True
        self.host.stat(self.bus.name, "requests")
        try:
            READ_CALL[p.table](self._client, p.address, count=1, device_id=p.unit)
        except (ModbusException, OSError) as exc:
            self.host.error(self.bus.name, "timeout", f"probe of {self._link()} after connect: "
                                                      f"no answer: {exc}")
            self._link_down(f"{self._link()} accepted the connection but sent no response: {exc}")
            return False
        self._answer(p.unit)
        return True

    def _liveness(self) -> None:
        """The periodic probe of the units no poll reads (an actuator-only bus, or on a line the
        units that have actuators only): read each one's first actuator's first entry. An
        answer (data or an exception) means the unit is there; none is a lost link on
        ``modbus-tcp`` (raises ConnectionException: reconnect, probe, recovery) and on
        ``modbus-rtu`` fails the unit's devices (cause ``unit``) until it answers."""
        for p in self._probed:
            if not self._unit_due(p.unit):
                continue
            where = f"{self.kind} bus {self.bus.name} probe of unit {p.unit} {p.table} " \
                    f"{p.address}"
            self.host.stat(self.bus.name, "requests")
            try:
                READ_CALL[p.table](self._client, p.address, count=1, device_id=p.unit)
            except ModbusIOException as exc:
                kind, what = self._unanswered(where)
                self.host.error(self.bus.name, kind, f"{where}: {what}: {exc}")
                if not self._client.connected or self.timeout_is_link_loss:
                    raise ConnectionException(f"no response to the probe: {exc}") from exc
                self._unit_silent(p.unit, where, f"no answer: {what}")
                continue
            self._answer(p.unit)

    def _link_down(self, why: str) -> None:
        was = self._connected
        self._connected = False
        reason = f"{self.kind} bus {self.bus.name}: {why}"
        for name in self.devices:
            self._health.fail(name, "link", reason)
        if was:
            self.host.error(self.bus.name, "disconnected", reason)
        self._drain()

    def _drain(self) -> None:
        """Complete every queued job without I/O while the link is down."""
        while not self._jobs.empty():
            self._finish_unsent(self._jobs.get_nowait())

    def _finish_unsent(self, job: Job) -> None:
        """Complete ``job`` without I/O (the link is down, or the driver stops): a write is
        reported failed, a poll taken (the chores' read-back armed again while an actuator is
        left), the stop job seen."""
        match job:
            case Job(JobOp.STOP):
                self._stop_seen = True
                return
            case Job(JobOp.WRITE, str(device), value):
                why = (f"{self.kind} bus {self.bus.name} is not connected to {self._link()}"
                       if not self._stop_seen else f"{self.kind} bus {self.bus.name} stopped")
                self.host.error(self.bus.name, "disconnected",
                                f"write {raw_value(value)!r} to {device} dropped: {why}", device)
                self.host.write_failed(device, raw_value(value), why)
            case Job(JobOp.POLL, LinkChore.READBACK):
                self._poll_taken(LinkChore.READBACK)
                if self._readback:      # still failed: try again once the link is back
                    self._arm_readback()
            case Job(JobOp.POLL, SensorPoll() | LinkChore() as key):
                self._poll_taken(key)
            case _:
                raise AssertionError(f"{self.kind} bus {self.bus.name}: unknown job {job!r}")
        self._done()

    def _serve(self) -> None:
        """Run jobs in order until the link drops or stop() asks to end."""
        while True:
            try:
                job = self._jobs.get(timeout=self._tick())
            except queue.Empty:
                if not self._taking and self._jobs.empty():   # a stop that gave up waiting
                    self._stop_seen = True                     # took the stop job itself
                    return
                continue
            if job.op == JobOp.STOP:
                self._stop_seen = True
                return
            if not self._client.connected:
                self._link_down(f"connection to {self._link()} lost")
                self._finish_unsent(job)
                return
            try:
                self._run(job)
            except (ConnectionException, OSError) as exc:
                if job.op == JobOp.WRITE:
                    self.host.write_failed(job.what, raw_value(job.value),
                                           f"connection to {self._link()} lost: {exc}")
                self._link_down(f"connection to {self._link()} lost: {exc}")
                return
            finally:
                self._done()

    def _unsent_write(self, job: Job) -> None:
        """A write job dropped at stop, never run: reported failed with the value given."""
        super()._unsent_write(job._replace(value=raw_value(job.value)))

    def _run(self, job: Job) -> None:
        """Run one job on the worker thread (raises what the client raises for a lost link)."""
        match job:
            case Job(JobOp.POLL, SensorPoll(period) as key):
                self._poll_taken(key)
                self._poll(self._plans[period])
            case Job(JobOp.POLL, LinkChore.PROBE):
                self._poll_taken(LinkChore.PROBE)
                self._liveness()
            case Job(JobOp.POLL, LinkChore.READBACK):
                self._read_back()
            case Job(JobOp.POLL, LinkChore.WATCHDOG):
                self._poll_taken(LinkChore.WATCHDOG)
                self._beat()
            case Job(JobOp.WRITE, str(device), QueuedWrite() as write):
                self._write_point(self._points[device], write)
            case _:
                raise AssertionError(f"{self.kind} bus {self.bus.name}: unknown job {job!r}")
