"""modbus - the ``modbus-tcp`` and ``modbus-rtu`` bus drivers, on pymodbus's asyncio client.

Bus options:

* ``modbus-tcp``: ``host`` (required), ``port`` (default 502).
* ``modbus-rtu``: ``port`` (required: a serial device, or a pyserial URL such as
  ``socket://127.0.0.1:5020``), ``baudrate`` (19200), ``parity`` (``N``/``E``/``O``), ``stopbits``
  (1/2), ``bytesize`` (7/8).
* both: ``timeout`` (s per request, 1.0), ``retries`` (1), ``reconnect_delay`` (s, 0.1; doubled
  after each failed attempt up to ``reconnect_delay_max``, 5.0), ``poll_period`` (s, 0.1; on a
  bus with no sensor: the period of the liveness probe, 1.0).

Device address: ``{unit = 1, table = coil|discrete|holding|input, address, type, word_order =
big|little, poll_period}``; ``type`` is ``bool`` for coils and discrete inputs (the default there)
and one of ``int16 uint16 int32 uint32 float32 float64`` for registers (default ``uint16``).
Sensors are polled every ``poll_period`` of the kernel clock (the ``host.every`` callback only
enqueues); each poll groups the contiguous addresses of one unit and table into one request.
Actuators (coils and holding registers) are written without blocking the caller. All requests run
in order on an asyncio loop in the driver's own thread; values are converted with pymodbus's
``convert_from_registers``/``convert_to_registers``.

Failures: when the connection cannot be made or is lost, every device of the bus fails with the
reason and the driver reconnects with backoff. A reconnect is not health: on ``modbus-tcp`` the
devices recover only once a request is answered (a probe read right after the connect; a server
that accepts connections but does not answer - frozen, SIGSTOPped - keeps them failed); on
``modbus-rtu`` an opened port fails the devices (cause ``link``) until a first request is
answered, so a line whose slave is silent from the start never shows them OK. A bus with only
actuators reads the first actuator's first entry every ``poll_period`` (default 1 s) as a
liveness probe, so a dead server fails the devices without waiting for a write and its return
is noticed (and the safe values written) without one. An exception
response fails the devices of that request (code and meaning in the reason) until a later request
for them succeeds. A request timeout counts as a lost link on ``modbus-tcp`` (the connection is
closed and re-made), and on ``modbus-rtu`` fails only the devices of that request (one unit of the
line not answering). Every write is confirmed (``host.written`` once the server answered it) or
reported failed (``host.write_failed``: exception answer, no answer, link down, dropped at stop);
a value the register type cannot hold is refused before it is queued (:meth:`check_value`).
Statistics (``host.stat``/``host.error``): ``requests``, ``reconnects``; errors ``timeout``,
``exception-<code>``, ``disconnected``, ``malformed``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import math
import threading
from abc import abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeGuard

from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerRTU, FramerType

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from drivers.base import Driver, DriverHost
from drivers.health import Health

DT = ModbusClientMixin.DATATYPE
REGISTER_TYPES: dict[str, Any] = {"int16": DT.INT16, "uint16": DT.UINT16, "int32": DT.INT32,
                                  "uint32": DT.UINT32, "float32": DT.FLOAT32,
                                  "float64": DT.FLOAT64}
#: What each type can carry on the wire (float32: its largest finite value).
RAW_RANGE: dict[str, tuple[float, float]] = {
    "bool": (0, 1), "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
    "float32": (-3.4028234663852886e38, 3.4028234663852886e38)}
TABLES = ("coil", "discrete", "holding", "input")
WRITABLE = ("coil", "holding")
READ_METHOD = {"coil": "read_coils", "discrete": "read_discrete_inputs",
               "holding": "read_holding_registers", "input": "read_input_registers"}
ADDRESS_KEYS = ("unit", "table", "address", "type", "word_order", "poll_period")
PROBE_PERIOD = 1.0   # s between liveness probes of an actuator-only bus without poll_period
COMMON_OPTIONS = ("timeout", "retries", "reconnect_delay", "reconnect_delay_max", "poll_period")
MAX_REGISTERS = 125     # per read request (Modbus application protocol, function 3/4)
MAX_BITS = 2000         # per read request (function 1/2)
EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "server device failure", 5: "acknowledge", 6: "server device busy",
                  8: "memory parity error", 10: "gateway path unavailable",
                  11: "gateway target device failed to respond"}


def _is_number(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


@dataclass(frozen=True)
class Point:
    """One device's place in the Modbus data model."""

    device: str
    unit: int
    table: str
    address: int
    type: str
    word_order: Literal["big", "little"]

    @property
    def size(self) -> int:
        """Entries it spans: 1 bit, or its register count."""
        return 1 if self.type == "bool" else int(REGISTER_TYPES[self.type].value[1])

    def decode(self, entries: Sequence[Any]) -> Any:
        """The value from its own slice of a response's bits or registers."""
        if self.type == "bool":
            return bool(entries[0])
        return ModbusClientMixin.convert_from_registers(list(entries), REGISTER_TYPES[self.type],
                                                        self.word_order)


@dataclass(frozen=True)
class ReadRequest:
    """One read of ``count`` entries of one unit and table, and the points it serves."""

    unit: int
    table: str
    address: int
    count: int
    points: tuple[Point, ...]

    def describe(self) -> str:
        """``unit 1 holding 10..13`` - for failure reasons."""
        return f"unit {self.unit} {self.table} {self.address}..{self.address + self.count - 1}"


def plan_reads(points: Sequence[Point]) -> list[ReadRequest]:
    """Group points into as few requests as possible: contiguous (or overlapping) addresses of the
    same unit and table, within the protocol's per-request limit."""
    out: list[ReadRequest] = []
    cur: list[Point] = []
    end = 0
    for p in sorted(points, key=lambda p: (p.unit, p.table, p.address)):
        limit = MAX_BITS if p.table in ("coil", "discrete") else MAX_REGISTERS
        if cur and p.unit == cur[0].unit and p.table == cur[0].table and p.address <= end \
                and max(end, p.address + p.size) - cur[0].address <= limit:
            cur.append(p)
            end = max(end, p.address + p.size)
            continue
        if cur:
            out.append(ReadRequest(cur[0].unit, cur[0].table, cur[0].address,
                                   end - cur[0].address, tuple(cur)))
        cur, end = [p], p.address + p.size
    if cur:
        out.append(ReadRequest(cur[0].unit, cur[0].table, cur[0].address, end - cur[0].address,
                               tuple(cur)))
    return out


def point_of(device: DeviceSpec) -> Point:
    """The :class:`Point` of a validated device."""
    a = device.address
    table = str(a["table"])
    default = "bool" if table in ("coil", "discrete") else "uint16"
    order: Literal["big", "little"] = "little" if a.get("word_order") == "little" else "big"
    return Point(device.name, int(a.get("unit", 1)), table, int(a["address"]),
                 str(a.get("type", default)), order)


def check_address(bus: BusSpec, device: DeviceSpec) -> list[str]:
    """Errors of a Modbus device address (shared by both kinds)."""
    k = f"{device.key}.address"
    a = device.address
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(ADDRESS_KEYS)}"
            for key in a if key not in ADDRESS_KEYS]
    unit = a.get("unit", 1)
    if not (_is_int(unit) and 0 <= unit <= 247):
        errs.append(f"{k}.unit: expected a Modbus device id 0..247, got {unit!r}")
    table = a.get("table")
    if table not in TABLES:
        errs.append(f"{k}.table: expected one of {', '.join(TABLES)}, got {table!r}")
        return errs
    if device.direction == "actuator" and table not in WRITABLE:
        errs.append(f"{k}.table: {table} is read-only; an actuator needs coil or holding")
    bits = table in ("coil", "discrete")
    typ = a.get("type", "bool" if bits else "uint16")
    typ = typ if isinstance(typ, str) else repr(typ)
    size = 1
    if bits and typ != "bool":
        errs.append(f"{k}.type: a {table} holds one bit; expected \"bool\", got {typ!r}")
    elif not bits and typ not in REGISTER_TYPES:
        errs.append(f"{k}.type: expected one of {', '.join(REGISTER_TYPES)} for a {table} "
                    f"register, got {typ!r}")
    elif not bits:
        size = int(REGISTER_TYPES[typ].value[1])
    address = a.get("address")
    if not (_is_int(address) and 0 <= address <= 0x10000 - size):
        errs.append(f"{k}.address: expected an integer 0..{0x10000 - size} (a {typ} spans {size} "
                    f"entr{'y' if size == 1 else 'ies'}), got {address!r}")
    if a.get("word_order", "big") not in ("big", "little"):
        errs.append(f"{k}.word_order: expected \"big\" or \"little\", got {a['word_order']!r}")
    pp = a.get("poll_period")
    if pp is not None and not (_is_number(pp) and pp > 0):
        errs.append(f"{k}.poll_period: expected a number of seconds > 0, got {pp!r}")
    return errs


def check_common(bus: BusSpec, own: Sequence[str]) -> list[str]:
    """Errors of the options both kinds share, and of keys neither knows."""
    k = bus.key
    o = bus.options
    valid = (*own, *COMMON_OPTIONS)
    errs = [f"{k}.{key}: unknown option for a {bus.kind} bus; valid options: {', '.join(valid)}"
            for key in o if key not in valid]
    for key in ("timeout", "reconnect_delay", "reconnect_delay_max", "poll_period"):
        if key in o and not (_is_number(o[key]) and o[key] > 0):
            errs.append(f"{k}.{key}: expected a number of seconds > 0, got {o[key]!r}")
    if "retries" in o and not (_is_int(o["retries"]) and o["retries"] >= 0):
        errs.append(f"{k}.retries: expected an integer >= 0, got {o['retries']!r}")
    return errs


class _ModbusDriver(Driver):
    """What both Modbus kinds share: polling, writes, link supervision; subclasses make the
    client and describe the link."""

    kind: ClassVar[str] = ""
    confirms_writes = True
    numeric_only = True
    #: A request timeout means the link is gone (TCP: the server or its connection hangs) rather
    #: than one unit not answering (RTU: the other units on the line may still answer).
    timeout_is_link_loss: ClassVar[bool] = False

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._health = Health(host)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._jobs: asyncio.Queue[tuple[str, Any, Any]] | None = None
        self._stop_seen = False
        self._client: Any = None
        self._connected = False
        self._idle = threading.Condition()
        self._pending = 0
        self._polls_queued: set[float | str] = set()
        self._plans: dict[float, list[ReadRequest]] = {}
        self._points: dict[str, Point] = {}
        self._first_attempt = threading.Event()
        self._answered = True      # a request was answered since the last (re)connect
        self._units_answered: set[int] = set()   # RTU: the units that did, since then
        self._connects = 0

    # -- to be provided by the kinds ----------------------------------------------------------

    @abstractmethod
    def _make_client(self) -> Any:
        """A new pymodbus asyncio client for this bus (called on the I/O loop)."""

    @abstractmethod
    def _link(self) -> str:
        """Where the bus goes (``host:port``, the serial port), for failure reasons."""

    def _unanswered(self, request: str) -> tuple[str, str]:
        """The error class (``timeout``, and for RTU also ``crc``/``framing``) and the reason
        why the last request got no valid answer; the caller counts it as a bus error."""
        return "timeout", "no response"

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
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_until_complete, args=(self._main(),),
                                        name=f"{self.kind}-{self.bus.name}", daemon=True)
        self._thread.start()
        timeout = float(self.bus.options.get("timeout", 1.0))
        self._first_attempt.wait(timeout + 2.0)
        for period in self._plans:
            self.host.every(period, functools.partial(self._request_poll, period))
        if not self._plans and self._points:     # actuators only: nothing read would notice
            self.host.every(float(self.bus.options.get("poll_period", PROBE_PERIOD)),
                            self._request_probe)

    def _request_probe(self) -> None:
        """Enqueue one liveness probe of an actuator-only bus (at most one queued)."""
        with self._idle:
            if "probe" in self._polls_queued:
                return
            self._polls_queued.add("probe")
        self._submit("probe", None, None)

    def stop(self) -> None:
        """Stop the I/O thread and close the connection. Idempotent; never raises."""
        loop, thread = self._loop, self._thread
        self._loop = self._thread = None
        if loop is not None and thread is not None:
            jobs = self._jobs
            if jobs is not None:
                with contextlib.suppress(RuntimeError):
                    loop.call_soon_threadsafe(jobs.put_nowait, ("stop", None, None))
            thread.join(timeout=5.0)
            with contextlib.suppress(Exception):
                loop.close()
        with self._idle:
            self._pending = 0
            self._idle.notify_all()

    # -- kernel side --------------------------------------------------------------------------

    def check_value(self, device: str, value: Any) -> str | None:
        """Why raw ``value`` does not fit the device's coil or register type (None if it does):
        a coil takes 0/1, an integer type an integer within its range, a float type a finite
        number within its range. Nothing is rounded here."""
        p = self._points.get(device) or (point_of(self.devices[device])
                                         if device in self.devices else None)
        if p is None:
            return None
        return value_error(p.type, value)

    def write(self, device: str, value: Any) -> None:
        """Queue ``value`` for actuator ``device``; never blocks. An unknown device or a sensor is
        reported through ``host.error``; a write that cannot be queued through
        ``host.write_failed``."""
        dev = self.devices.get(device)
        if dev is None or dev.direction != "actuator":
            self.host.error(self.bus.name, "unknown-device",
                            f"write to {device!r}: not an actuator of {self.kind} bus "
                            f"{self.bus.name}")
            return
        if self._loop is None or not self._submit("write", self._points[device], value):
            why = f"{self.kind} bus {self.bus.name} is not running"
            self.host.error(self.bus.name, "stopped", f"write {value!r} to {device} dropped: "
                                                      f"{why}", device)
            self.host.write_failed(device, value, why)
            return

    def settle(self, timeout: float) -> bool:
        """Wait until no request is queued or in flight and every result is delivered."""
        with self._idle:
            return self._idle.wait_for(lambda: self._pending == 0, timeout)

    def _request_poll(self, period: float) -> None:
        with self._idle:
            if period in self._polls_queued:
                return
            self._polls_queued.add(period)
        self._submit("poll", period, None)

    def _submit(self, op: str, what: Any, value: Any) -> bool:
        loop, jobs = self._loop, self._jobs
        if loop is None or jobs is None:
            return False
        with self._idle:
            self._pending += 1
        try:
            loop.call_soon_threadsafe(jobs.put_nowait, (op, what, value))
        except RuntimeError:  # loop closed by a concurrent stop()
            self._done()
            return False
        return True

    def _done(self) -> None:
        with self._idle:
            self._pending = max(0, self._pending - 1)
            if self._pending == 0:
                self._idle.notify_all()

    # -- I/O thread ---------------------------------------------------------------------------

    async def _main(self) -> None:
        self._jobs = asyncio.Queue()
        o = self.bus.options
        delay = first = float(o.get("reconnect_delay", 0.1))
        most = float(o.get("reconnect_delay_max", 5.0))
        try:
            self._client = self._make_client()
            while not self._stop_seen:
                ok = await self._client.connect()
                if ok and self._client.connected:
                    self._connects += 1
                    if self._connects > 1:
                        self.host.stat(self.bus.name, "reconnects")
                    self._link_up()
                    if self.timeout_is_link_loss and not await self._probe():
                        self._first_attempt.set()
                        await self._backoff(delay)
                        delay = min(delay * 2, most)
                        self._client.close()
                        continue
                    delay = first
                    self._first_attempt.set()
                    await self._serve()
                else:
                    self._link_down(f"cannot connect to {self._link()}")
                    self._first_attempt.set()
                    await self._backoff(delay)
                    delay = min(delay * 2, most)
                self._client.close()
        finally:
            self._first_attempt.set()
            if self._client is not None:
                self._client.close()

    async def _backoff(self, delay: float) -> None:
        """Wait ``delay`` seconds (or until stop), completing jobs that arrive meanwhile."""
        assert self._jobs is not None
        loop = asyncio.get_running_loop()
        deadline = loop.time() + delay
        while not self._stop_seen and (left := deadline - loop.time()) > 0:
            try:
                job = await asyncio.wait_for(self._jobs.get(), left)
            except TimeoutError:
                return
            self._finish_unsent(job)

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
        the devices of the ``unit`` that answered (the others stay failed until theirs does)."""
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

    async def _probe(self) -> bool:
        """Right after a connect: read one entry of the first device; True if answered (the
        link is up), False (link down, devices still failed) if not."""
        p = next(iter(self._points.values()), None)
        if p is None:
            return True
        self.host.stat(self.bus.name, "requests")
        try:
            await getattr(self._client, READ_METHOD[p.table])(p.address, count=1,
                                                              device_id=p.unit)
        except (ModbusException, OSError) as exc:
            self.host.error(self.bus.name, "timeout", f"probe of {self._link()} after connect: "
                                                      f"no answer: {exc}")
            self._link_down(f"{self._link()} accepted the connection but sent no response: {exc}")
            return False
        self._answer(p.unit)
        return True

    async def _liveness(self) -> None:
        """The periodic probe of an actuator-only bus: read the first actuator's first entry.
        An answer (data or an exception) means the server is there; none is a lost link on
        ``modbus-tcp`` (raises ConnectionException: reconnect, probe, recovery) and on
        ``modbus-rtu`` fails the devices (cause ``link``) until a request is answered."""
        p = next(iter(self._points.values()))
        where = f"{self.kind} bus {self.bus.name} probe of unit {p.unit} {p.table} {p.address}"
        self.host.stat(self.bus.name, "requests")
        try:
            await getattr(self._client, READ_METHOD[p.table])(p.address, count=1,
                                                              device_id=p.unit)
        except ModbusIOException as exc:
            kind, what = self._unanswered(where)
            self.host.error(self.bus.name, kind, f"{where}: {what}: {exc}")
            if not self._client.connected or self.timeout_is_link_loss:
                raise ConnectionException(f"no response to the probe: {exc}") from exc
            self._answered = False
            self._units_answered.discard(p.unit)
            for name, q in self._points.items():
                if q.unit == p.unit:
                    self._health.fail(name, "link", f"{where}: no answer: {what}")
            return
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
        assert self._jobs is not None
        while not self._jobs.empty():
            self._finish_unsent(self._jobs.get_nowait())

    def _finish_unsent(self, job: tuple[str, Any, Any]) -> None:
        op, what, value = job
        if op == "stop":
            self._stop_seen = True
            return
        if op == "write":
            why = (f"{self.kind} bus {self.bus.name} is not connected to {self._link()}"
                   if not self._stop_seen else f"{self.kind} bus {self.bus.name} stopped")
            self.host.error(self.bus.name, "disconnected",
                            f"write {value!r} to {what.device} dropped: {why}", what.device)
            self.host.write_failed(what.device, value, why)
        elif op == "poll":
            with self._idle:
                self._polls_queued.discard(what)
        elif op == "probe":
            with self._idle:
                self._polls_queued.discard("probe")
        self._done()

    async def _serve(self) -> None:
        """Run jobs in order until the link drops or stop() asks to end."""
        assert self._jobs is not None
        while True:
            job = await self._jobs.get()
            if job[0] == "stop":
                self._stop_seen = True
                return
            if not self._client.connected:
                self._link_down(f"connection to {self._link()} lost")
                self._finish_unsent(job)
                return
            try:
                await self._run(job)
            except ConnectionException as exc:
                if job[0] == "write":
                    self.host.write_failed(job[1].device, job[2], f"connection to "
                                                                  f"{self._link()} lost: {exc}")
                self._link_down(f"connection to {self._link()} lost: {exc}")
                return
            finally:
                self._done()

    async def _run(self, job: tuple[str, Any, Any]) -> None:
        op, what, value = job
        if op == "poll":
            with self._idle:
                self._polls_queued.discard(what)
            for request in self._plans[what]:
                await self._read(request)
        elif op == "probe":
            with self._idle:
                self._polls_queued.discard("probe")
            await self._liveness()
        else:
            await self._write(what, value)

    async def _read(self, r: ReadRequest) -> None:
        c = self._client
        self.host.stat(self.bus.name, "requests")
        try:
            resp = await getattr(c, READ_METHOD[r.table])(r.address, count=r.count,
                                                          device_id=r.unit)
        except ModbusIOException as exc:
            kind, what = self._unanswered(r.describe())
            for p in r.points:
                self.host.error(self.bus.name, kind, f"{r.describe()}: {what}: {exc}", p.device)
            if not c.connected or self.timeout_is_link_loss:
                raise ConnectionException(f"no response: {exc}") from exc
            for p in r.points:
                self._health.fail(p.device, "exception", f"{self.kind} bus {self.bus.name} "
                                  f"{r.describe()} (device {p.device}): {what}")
            return
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
        self._answer(r.unit)
        entries = resp.bits if r.table in ("coil", "discrete") else resp.registers
        for p in r.points:
            off = p.address - r.address
            try:
                value = reading_of(p, entries[off:off + p.size])
            except (ModbusException, IndexError, ValueError) as exc:
                self.host.error(self.bus.name, "malformed",
                                f"{r.describe()} answer for {p.device}: {exc}")
                continue
            self._health.clear(p.device, "exception", f"{r.describe()} answered")
            self.host.deliver(p.device, value)

    async def _write(self, p: Point, value: Any) -> None:
        c = self._client
        why = value_error(p.type, value)
        if why is not None:
            self.host.error(self.bus.name, "range", f"write {value!r} to {p.device}: {why}",
                            p.device)
            self.host.write_failed(p.device, value, why)
            return
        if p.table == "coil":
            call = c.write_coil(p.address, bool(value), device_id=p.unit)
        else:
            regs = ModbusClientMixin.convert_to_registers(_coerce(p.type, value),
                                                          REGISTER_TYPES[p.type], p.word_order)
            call = (c.write_register(p.address, regs[0], device_id=p.unit) if len(regs) == 1
                    else c.write_registers(p.address, regs, device_id=p.unit))
        where = f"{self.kind} bus {self.bus.name} unit {p.unit} {p.table} {p.address}"
        self.host.stat(self.bus.name, "requests", device=p.device)
        try:
            resp = await call
        except ModbusIOException as exc:
            kind, what = self._unanswered(where)
            self.host.error(self.bus.name, kind, f"{where}: write not answered: {what}: {exc}",
                            p.device)
            if not c.connected or self.timeout_is_link_loss:
                raise ConnectionException(f"no response: {exc}") from exc
            self.host.write_failed(p.device, value, f"{where}: write not answered: {exc}")
            self._health.fail(p.device, "exception", f"{where} (device {p.device}): write not "
                                                     f"answered: {exc}")
            return
        if resp.isError():
            code = int(getattr(resp, "exception_code", 0))
            text = (f"{where} (device {p.device}): write refused with exception code "
                    f"{code} ({EXCEPTION_TEXT.get(code, 'unknown')})")
            self.host.error(self.bus.name, f"exception-{code}", text, p.device)
            self.host.write_failed(p.device, value, text)
            self._health.fail(p.device, "exception", text)
            self._answer(p.unit)       # after the new cause: no OK in between
            return
        self._answer(p.unit)
        self.host.written(p.device, value)
        self._health.clear(p.device, "exception", f"{where}: write answered")


INT_RANGES = {"int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
              "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1)}
FLOAT_MAX = {"float32": 3.4028234663852886e38, "float64": 1.7976931348623157e308}


def value_error(type_: str, value: Any) -> str | None:
    """Why ``value`` cannot be written to a point of ``type_`` exactly (None if it can)."""
    if isinstance(value, bool):
        value = int(value)
    if not _is_number(value):
        return f"expected a number for a {type_} address, got {value!r}"
    if value != value or value in (float("inf"), float("-inf")):
        return f"expected a finite number for a {type_} address, got {value!r}"
    if type_ == "bool":
        return None if value in (0, 1) else f"expected 0 or 1 for a coil, got {value!r}"
    if type_ in FLOAT_MAX:
        return (None if abs(value) <= FLOAT_MAX[type_] else
                f"expected a {type_} value within +-{FLOAT_MAX[type_]:g}, got {value!r}")
    lo, hi = INT_RANGES[type_]
    if isinstance(value, float) and not value.is_integer():
        return f"expected an integer for a {type_} register, got {value!r}"
    if not lo <= value <= hi:
        return f"expected a {type_} value {lo}..{hi}, got {value!r}"
    return None


def reading_of(p: Point, entries: Sequence[Any]) -> Any:
    """The value of ``p`` from its slice of an answer. Raises ValueError (or pymodbus'
    ModbusException, IndexError) if the entries are too few or a float is nan or infinite: such
    a value is reported as malformed, never delivered."""
    if len(entries) < p.size:
        raise IndexError(f"{len(entries)} entries for a {p.type}, expected {p.size}")
    value = p.decode(entries)
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{p.type} registers {list(entries)} hold {value}, not a finite number")
    return value


def _rtu_answer_size(head: bytes) -> int | None:
    """The length of an RTU answer starting with ``head`` (unit, function...), None if it
    cannot be told yet or the function is not one chcos asks."""
    if len(head) < 2:
        return None
    fc = head[1]
    if fc & 0x80:
        return 5                                    # unit, fc|0x80, exception code, CRC
    if fc in (1, 2, 3, 4):
        return 3 + head[2] + 2 if len(head) >= 3 else None
    if fc in (5, 6, 15, 16):
        return 8
    return None


def classify_rtu_answer(request: bytes, received: bytes) -> tuple[str, str]:
    """Why ``received`` is no valid answer to the RTU ``request``: ``("timeout", ...)`` for
    silence, ``("crc", ...)`` for a whole frame of the right unit and function whose CRC is
    wrong, ``("framing", ...)`` for a truncated answer or bytes that are no answer (junk)."""
    if not received:
        return "timeout", "no response (silence)"
    unit, fc = (request[0], request[1]) if len(request) >= 2 else (-1, -1)
    head = received
    if head[0] == unit and (len(head) < 2 or head[1] & 0x7F == fc):
        size = _rtu_answer_size(head)
        if size is not None and len(head) >= size:
            frame = head[:size]
            crc = FramerRTU.compute_CRC(frame[:-2])
            if crc.to_bytes(2, "big") != frame[-2:]:
                return "crc", (f"answer {frame.hex()} fails its CRC (expected "
                               f"{crc:04x}, got {frame[-2:].hex()})")
        if size is None or len(head) < size:
            return "framing", (f"truncated answer {head.hex()} ({len(head)} of "
                               f"{size if size is not None else '?'} bytes)")
    return "framing", f"{len(received)} bytes that are no answer: {received[:32].hex()}"


def _coerce(type_: str, value: Any) -> int | float:
    """``value`` as the Python number pymodbus packs for ``type_`` (integers are rounded)."""
    if type_.startswith("float"):
        return float(value)
    if isinstance(value, float):
        return round(value)  # raises OverflowError/ValueError for inf/nan
    return int(value)


class ModbusTcpDriver(_ModbusDriver):
    """``modbus-tcp``: a Modbus TCP server at ``host:port``."""

    kind = "modbus-tcp"
    timeout_is_link_loss = True

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of ``host``, ``port`` and the common options."""
        errs = check_common(bus, ("host", "port"))
        o: Mapping[str, Any] = bus.options
        if not (isinstance(o.get("host"), str) and o["host"]):
            errs.append(f"{bus.key}.host: expected a host name or address, got "
                        f"{o.get('host')!r}")
        port = o.get("port", 502)
        if not (_is_int(port) and 1 <= port <= 65535):
            errs.append(f"{bus.key}.port: expected a TCP port 1..65535, got {port!r}")
        return errs

    def _make_client(self) -> Any:
        o = self.bus.options
        return AsyncModbusTcpClient(str(o["host"]), port=int(o.get("port", 502)),
                                    timeout=float(o.get("timeout", 1.0)),
                                    retries=int(o.get("retries", 1)), reconnect_delay=0,
                                    name=self.bus.name)

    def _link(self) -> str:
        return f"{self.bus.options['host']}:{self.bus.options.get('port', 502)}"


class ModbusRtuDriver(_ModbusDriver):
    """``modbus-rtu``: Modbus RTU on a serial line (or a pyserial URL such as socket://)."""

    kind = "modbus-rtu"

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of the serial options and the common options."""
        errs = check_common(bus, ("port", "baudrate", "parity", "stopbits", "bytesize"))
        o: Mapping[str, Any] = bus.options
        k = bus.key
        if not (isinstance(o.get("port"), str) and o["port"]):
            errs.append(f"{k}.port: expected a serial port (/dev/ttyUSB0, socket://host:port), "
                        f"got {o.get('port')!r}")
        if not (_is_int(o.get("baudrate", 19200)) and o.get("baudrate", 19200) > 0):
            errs.append(f"{k}.baudrate: expected an integer > 0, got {o.get('baudrate')!r}")
        if o.get("parity", "N") not in ("N", "E", "O"):
            errs.append(f"{k}.parity: expected \"N\", \"E\" or \"O\", got {o.get('parity')!r}")
        if o.get("stopbits", 1) not in (1, 2) or isinstance(o.get("stopbits"), bool):
            errs.append(f"{k}.stopbits: expected 1 or 2, got {o.get('stopbits')!r}")
        if o.get("bytesize", 8) not in (7, 8) or isinstance(o.get("bytesize"), bool):
            errs.append(f"{k}.bytesize: expected 7 or 8, got {o.get('bytesize')!r}")
        return errs

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._tx = b""                  # the last request frame sent
        self._rx = bytearray()          # every byte received since it was sent
        self._rx_buffer = b""           # pymodbus' receive buffer as last seen
        #: Requests that got no valid answer, by class: crc, framing (junk or a truncated
        #: answer), timeout (silence). Each is also reported through ``host.error``.
        self.unanswered: dict[str, int] = {}

    def _trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus' packet hook (I/O thread): keeps the request and the bytes of its answer."""
        if sending:
            self._tx, self._rx, self._rx_buffer = bytes(data), bytearray(), b""
        else:
            prev = self._rx_buffer
            self._rx += data[len(prev):] if data.startswith(prev) else data
            self._rx_buffer = bytes(data)
        return data

    def _unanswered(self, request: str) -> tuple[str, str]:
        """Classify the bytes that came back for the last request (none: timeout; a frame of
        the right unit and function, long enough, failing its CRC: crc; anything else:
        framing) and count the class."""
        kind, why = classify_rtu_answer(self._tx, bytes(self._rx))
        self.unanswered[kind] = self.unanswered.get(kind, 0) + 1
        return kind, why

    def _make_client(self) -> Any:
        o = self.bus.options
        return AsyncModbusSerialClient(str(o["port"]), framer=FramerType.RTU,
                                       trace_packet=self._trace,
                                       baudrate=int(o.get("baudrate", 19200)),
                                       parity=str(o.get("parity", "N")),
                                       stopbits=int(o.get("stopbits", 1)),
                                       bytesize=int(o.get("bytesize", 8)),
                                       timeout=float(o.get("timeout", 1.0)),
                                       retries=int(o.get("retries", 1)), reconnect_delay=0,
                                       name=self.bus.name)

    def _link(self) -> str:
        return str(self.bus.options["port"])
