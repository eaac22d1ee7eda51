"""driver - the ``modbus-tcp`` and ``modbus-rtu`` bus drivers: each a :class:`drivers.base.Driver`
that owns one :class:`ModbusBus`, the composition of the parts of the package:

* the typed options and the plan made of them once (:mod:`drivers.modbus.config`),
* the job queue with its paced polls (:mod:`drivers.jobqueue`),
* the link and units supervision (:mod:`drivers.modbus.link`),
* the jobs and what their answers mean (:mod:`drivers.modbus.requests`),
* the engine that runs them - a worker thread over TCP, a serial port or an in-process slave
  on wall time, or the kernel thread against an in-process slave on a virtual clock
  (:mod:`drivers.modbus.engine`, :mod:`drivers.modbus.transport`).

Sensors are polled every ``poll_period`` of the kernel clock (each poll groups the contiguous
addresses of one unit and table into one request); actuators are written without blocking the
caller and every write is confirmed (``host.written`` once the device answered it; a broadcast
once it was sent) or reported failed (``host.write_failed``, with the reason). What each fault
does: ``docs/modbus-faults.md``.
"""

from __future__ import annotations

import enum
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError, ConfigError
from drivers.base import Driver, DriverHost, host_clock_virtual, not_finite
from drivers.codecs.modbus import RAW_RANGE, STRING, accepted, value_error
from drivers.codecs.modbus_direct import lookup
from drivers.codecs.modbus_options import (
    ModbusAddress,
    RtuOptions,
    TcpOptions,
    point_of,
)
from drivers.health import Health
from drivers.jobqueue import JobQueue, Poll
from drivers.modbus.checks import device_errors, line_warnings, parse_device
from drivers.modbus.config import (
    BusPlan,
    build_plan,
    dead_unit_backoff,
    dead_unit_first,
    sensor_period,
)
from drivers.modbus.engine import (
    Job,
    KernelEngine,
    ThreadEngine,
    Timing,
)
from drivers.modbus.link import Link, Units
from drivers.modbus.requests import JobRun, ModbusRequests, QueuedWrite
from drivers.modbus.transactions import read_request
from drivers.modbus.transport import (
    DirectTransport,
    RtuTransport,
    TcpTransport,
    Transport,
)
from drivers.reports import Reports


@dataclass(frozen=True)
class SensorPoll:
    """The paced poll of the sensors polled every ``period`` seconds."""

    period: float


class Chore(enum.Enum):
    """The driver's jobs beside the sensor polls."""

    #: a request to the units no poll reads (their actuators only), so a lost link is noticed
    PROBE = "probe"
    #: the next value of the bus's watchdog register
    WATCHDOG = "watchdog"
    #: read each write-failed actuator back: an answer ends its write failure
    READBACK = "readback"


class ModbusBus:
    """One Modbus bus's parts, composed (see the module doc). ``kind`` names the driver's."""

    def __init__(self, kind: str, bus: BusSpec, devices: Sequence[DeviceSpec],
                 host: DriverHost, options: TcpOptions | RtuOptions) -> None:
        _validate(kind, devices)
        self.kind = kind
        self.bus = bus
        self.host = host
        self.options = options
        self.plan: BusPlan = build_plan(options, devices)
        self.name = f"{kind} bus {bus.name}"
        self.health = Health(host)
        self.reports = Reports(host, bus.name)
        distinct = sum(len(plan) for plan in self.plan.polls.values()) + len(self.plan.probed)
        self.link = Link(host, bus.name, self.name, options.link(), self.health,
                         self.plan.points, per_unit=self.plan.serial, distinct=distinct)
        self.units = Units(self.name, self.health, self.plan.points, dead_unit_backoff(options),
                           dead_unit_first(options), self.plan.units,
                           guard=options.timeout if self.plan.serial else 0.0,
                           line_guard=(options.guard_after_silence()
                                       if isinstance(options, RtuOptions) else 0.0))
        slave = lookup(options.direct) if options.direct else None
        if options.direct and slave is None:
            raise BusError(f"{self.name} ({bus.file}): {bus.key}.direct: no in-process "
                           f"simulated slave named {options.direct!r}")
        on_kernel = slave is not None and host_clock_virtual(host) is True
        self._readback_armed = False
        self._readback_lock = threading.Lock()
        self.queue: JobQueue[Job] = JobQueue(host, bus.name, self._wake)
        timing = Timing.of(options, getattr(options, "turnaround", 0.0))
        parallel = isinstance(options, TcpOptions) and options.connections > 1
        self.engine: KernelEngine | ThreadEngine
        if on_kernel:
            assert slave is not None
            self.engine = KernelEngine(self.name, host, self.queue, self.link, self.units, self,
                                       slave, timing, self.plan.line)
        else:
            self.engine = ThreadEngine(self.name, host, self.queue, self.link, self.units, self,
                                       self._transport(slave, parallel), timing,
                                       f"{kind}-{bus.name}")
        self.requests = ModbusRequests(host, bus.name, self.name, self.plan, self.health,
                                       self.link, self.units, self.reports, parallel,
                                       self.engine.clock, self._arm_readback)

    def _transport(self, slave: Any, parallel: bool) -> Transport:
        o = self.options
        if slave is not None:
            return DirectTransport(slave, o.direct)
        if isinstance(o, TcpOptions):
            first = next((p for p in self.plan.points.values()), None)
            probe = (read_request(first.unit, first.table, first.address, 1, "lane probe")
                     if first is not None else None)
            return TcpTransport(o.host, o.port, o.timeout, o.connections if parallel else 1,
                                probe, self._late, self._lanes_refused)
        assert self.plan.line is not None
        return RtuTransport(o.port, self.plan.line, self._late_frames)

    def _wake(self) -> None:
        engine = getattr(self, "engine", None)
        if isinstance(engine, KernelEngine):
            engine.wake()

    # ---- life cycle -------------------------------------------------------------------------
    @property
    def settles(self) -> bool:
        """False when the jobs run on the kernel thread (see :mod:`drivers.modbus.engine`)."""
        return not isinstance(self.engine, KernelEngine)

    def start(self) -> None:
        """Connect (or make the first attempt) and pace the polls."""
        self.engine.start()
        for period in self.plan.polls:
            self.queue.poll_every(SensorPoll(period), period)
        wd = self.plan.watchdog
        if wd is not None:
            self.queue.poll_every(Chore.WATCHDOG, wd.period)
        if self.plan.probed:      # units with actuators only: nothing read would notice
            self.queue.poll_every(Chore.PROBE, self.options.probe_period())

    def stop(self) -> None:
        """Stop the engine; the writes not sent are reported failed."""
        self.engine.stop()
        self.reports.flush()

    def write(self, device: str, value: Any) -> bool:
        """Queue a write of ``device`` stamped with its unit's epoch; False if the bus does not
        take it (stopping)."""
        return self.queue.submit(QueuedWrite(device, value, self.requests.epoch(device)))

    # ---- Jobs (the engine's view of the driver) ---------------------------------------------
    def run(self, job: Poll | QueuedWrite) -> JobRun:
        """The requests of ``job``."""
        match job:
            case QueuedWrite():
                return self.requests.write(job)
            case Poll(SensorPoll(period)):
                return self.requests.poll(self.plan.polls[period])
            case Poll(Chore.PROBE):
                return self.requests.probe()
            case Poll(Chore.WATCHDOG):
                return self.requests.beat()
            case Poll(Chore.READBACK):
                return self._read_back()
        raise AssertionError(f"{self.name}: unknown job {job!r}")

    def drop(self, job: Poll | QueuedWrite, why: str) -> None:
        """A job completed without I/O: a write is reported failed; the read-back is armed
        again while an actuator is left."""
        if isinstance(job, QueuedWrite):
            self.host.error(self.bus.name, "disconnected",
                            f"write {job.value!r} to {job.device} dropped: {why}", job.device)
            self.host.write_failed(job.device, job.value, why)
        elif job == Poll(Chore.READBACK):
            self._readback_done()

    def contact(self) -> JobRun | None:
        """TCP: a probe read right after a connect (a server that accepts and never answers is
        a lost link); a serial line has none (its units answer one by one)."""
        return self.requests.contact() if isinstance(self.options, TcpOptions) else None

    # ---- the read-back of write-failed actuators ----------------------------------------------
    def _arm_readback(self) -> None:
        """Queue the read-back one ``poll_period`` from now, unless it is armed already."""
        with self._readback_lock:
            if self._readback_armed or not self.queue.taking:
                return
            self._readback_armed = True
        period = self.options.sensor_period()
        self.host.at(round(self.host.now() + period, 9), self._readback_due)

    def _readback_due(self) -> None:
        if not self.queue.submit(Poll(Chore.READBACK)):
            with self._readback_lock:
                self._readback_armed = False

    def _read_back(self) -> JobRun:
        try:
            yield from self.requests.read_back()
        finally:
            self._readback_done()

    def _readback_done(self) -> None:
        with self._readback_lock:
            self._readback_armed = False
        if self.requests.readback:
            self._arm_readback()

    # ---- counts -------------------------------------------------------------------------------
    def _late(self) -> None:
        self.link.alive()
        self.host.stat(self.bus.name, "late-answers")

    def _late_frames(self, n: int) -> None:
        self.host.stat(self.bus.name, "late-answers", n)

    def _lanes_refused(self, took: int, wanted: int) -> None:
        self.host.error(self.bus.name, "connections",
                        f"{self.name}: {self.options.link()} took {took} of {wanted} "
                        f"connections; polls use those")

    # ---- the kernel side --------------------------------------------------------------------
    def check_value(self, device: str, value: Any) -> str | None:
        """Why raw ``value`` does not fit the device's coil or register type (None if it
        does); a value with a scale factor is checked once the factor is read."""
        p = self.plan.points.get(device)
        if p is None:
            return None
        if p.scale_factor is not None:
            return not_finite(value)
        return value_error(p.type, value, p.count)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """What the device's coil or register type holds (None with a scale factor)."""
        p = self.plan.points.get(device)
        if p is None or p.scale_factor is not None:
            return None
        return accepted(p.type)


def _validate(kind: str, devices: Sequence[DeviceSpec]) -> None:
    """Check the devices built in code (those a map check parsed are valid); raises
    ConfigError naming every bad key."""
    errors = [e for d in devices if not isinstance(d.addr, ModbusAddress)
              for e in parse_device(kind, d)[1]]
    if errors:
        raise ConfigError("; ".join(errors))


# ---- the two kinds --------------------------------------------------------------------------
class ModbusTcpDriver(Driver):
    """``modbus-tcp``: a Modbus TCP server (a device or a gateway) at ``host:port``."""

    kind = "modbus-tcp"
    confirms_writes = True
    numeric_only = True
    Options: ClassVar[type | None] = TcpOptions
    Address: ClassVar[type | None] = ModbusAddress

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.modbus = ModbusBus(self.kind, bus, devices, host, self.bus_options(bus, TcpOptions))

    @classmethod
    def parse_device(cls, bus: BusSpec, device: DeviceSpec) -> tuple[Any, list[str]]:
        """The typed address, and the rules of the device and kind."""
        return parse_device(cls.kind, device)

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """The errors of :meth:`parse_device`."""
        return parse_device(cls.kind, device)[1]

    @classmethod
    def check_devices(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[
            tuple[DeviceSpec, str]]:
        """See :func:`drivers.modbus.checks.device_errors`."""
        return device_errors(bus, cls.bus_options(bus, TcpOptions), devices)

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of the address's type (None for float64, text or a scale factor)."""
        return _encodable(device)

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """The sensor's ``poll_period``, else the bus's, else 0.1 s."""
        return sensor_period(cls.bus_options(bus, TcpOptions), device)

    def start(self) -> None:
        """Connect and poll (see :class:`ModbusBus`); on the kernel thread nothing is in
        flight between two interrupts (``settles`` False: the kernel waits for nothing)."""
        self.modbus.start()
        self.settles = self.modbus.settles
        self._running = True

    def stop(self) -> None:
        """Stop the engine; idempotent, never raises."""
        self._running = False
        self.modbus.stop()

    def settle(self, timeout: float) -> bool:
        """See :meth:`drivers.modbus.engine.ThreadEngine.settle`."""
        return self.modbus.engine.settle(timeout)

    def flush(self, timeout: float) -> bool:
        """See :meth:`drivers.modbus.engine.ThreadEngine.flush`."""
        return self.modbus.engine.flush(timeout)

    def _write(self, device: str, value: Any) -> None:
        if not self.modbus.write(device, value):
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")

    def check_value(self, device: str, value: Any) -> str | None:
        """See :meth:`ModbusBus.check_value`."""
        return self.modbus.check_value(device, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """See :meth:`ModbusBus.accepts`."""
        return self.modbus.accepts(device)

    @property
    def unanswered(self) -> dict[str, int]:
        """Requests that got no usable answer, by cause."""
        return dict(self.modbus.requests.unanswered)


class ModbusRtuDriver(Driver):
    """``modbus-rtu``: Modbus RTU on a serial line (or a pyserial URL such as socket://)."""

    kind = "modbus-rtu"
    confirms_writes = True
    numeric_only = True
    Options: ClassVar[type | None] = RtuOptions
    Address: ClassVar[type | None] = ModbusAddress

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.modbus = ModbusBus(self.kind, bus, devices, host, self.bus_options(bus, RtuOptions))

    @classmethod
    def parse_device(cls, bus: BusSpec, device: DeviceSpec) -> tuple[Any, list[str]]:
        """The typed address, and the rules of the device and kind."""
        return parse_device(cls.kind, device)

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """The errors of :meth:`parse_device`."""
        return parse_device(cls.kind, device)[1]

    @classmethod
    def check_devices(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[
            tuple[DeviceSpec, str]]:
        """See :func:`drivers.modbus.checks.device_errors`."""
        return device_errors(bus, cls.bus_options(bus, RtuOptions), devices)

    @classmethod
    def check_warnings(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[str]:
        """See :func:`drivers.modbus.checks.line_warnings`."""
        return line_warnings(cls.bus_options(bus, RtuOptions), devices)

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of the address's type (None for float64, text or a scale factor)."""
        return _encodable(device)

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """The sensor's ``poll_period``, else the bus's, else 0.1 s."""
        return sensor_period(cls.bus_options(bus, RtuOptions), device)

    def start(self) -> None:
        """Open the port and poll (see :class:`ModbusBus`); on the kernel thread nothing is in
        flight between two interrupts (``settles`` False: the kernel waits for nothing)."""
        self.modbus.start()
        self.settles = self.modbus.settles
        self._running = True

    def stop(self) -> None:
        """Stop the engine; idempotent, never raises."""
        self._running = False
        self.modbus.stop()

    def settle(self, timeout: float) -> bool:
        """See :meth:`drivers.modbus.engine.ThreadEngine.settle`."""
        return self.modbus.engine.settle(timeout)

    def flush(self, timeout: float) -> bool:
        """See :meth:`drivers.modbus.engine.ThreadEngine.flush`."""
        return self.modbus.engine.flush(timeout)

    def _write(self, device: str, value: Any) -> None:
        if not self.modbus.write(device, value):
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")

    def check_value(self, device: str, value: Any) -> str | None:
        """See :meth:`ModbusBus.check_value`."""
        return self.modbus.check_value(device, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """See :meth:`ModbusBus.accepts`."""
        return self.modbus.accepts(device)

    @property
    def unanswered(self) -> dict[str, int]:
        """Requests that got no usable answer, by cause."""
        return dict(self.modbus.requests.unanswered)


def _encodable(device: DeviceSpec) -> tuple[float, float] | None:
    p = point_of(device)
    if p.scale_factor is not None or p.type == STRING:
        return None
    return RAW_RANGE.get(p.type)
