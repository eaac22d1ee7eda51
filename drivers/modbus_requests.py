"""modbus_requests - the requests of the Modbus drivers: a poll's reads (in order on one
connection, or spread over several connections all outstanding at once) and a write, each on a
pymodbus asyncio client, with what its answer means for the devices (readings, exception answers,
no answer). :class:`ModbusRequests` holds the drivers' state and these requests; the life cycle,
the jobs and the supervision of the link are :class:`drivers.modbus_link.ModbusDriver`, the kinds
and the failure rules :mod:`drivers.modbus`.
"""

from __future__ import annotations

import asyncio
import threading
from abc import abstractmethod
from collections.abc import Sequence
from typing import Any, ClassVar

from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import DriverHost, deliver_all
from drivers.codecs.modbus import (
    EXCEPTION_TEXT,
    Point,
    ReadRequest,
    reading_of,
    value_error,
)
from drivers.health import Health
from drivers.jobs import AsyncJobDriver

READ_METHOD = {"coil": "read_coils", "discrete": "read_discrete_inputs",
               "holding": "read_holding_registers", "input": "read_input_registers"}


class ModbusRequests(AsyncJobDriver):
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
        self._first_attempt = threading.Event()
        self._answered = True      # a request was answered since the last (re)connect
        self._units_answered: set[int] = set()   # RTU: the units that did, since then
        self._connects = 0
        #: modbus-tcp with ``connections`` > 1: the extra clients a poll of several requests
        #: spreads them over (opened after the main connection answered, closed with it).
        self._lanes: list[Any] = []
        self._lanes_tried = False

    # -- to be provided by the kinds ----------------------------------------------------------

    @abstractmethod
    def _make_client(self) -> Any:
        """A new pymodbus asyncio client for this bus (called on the I/O loop)."""

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

    async def _open_lanes(self) -> list[Any]:
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
                ok = await self._lane_answers(lane)
                if not ok:
                    lane.close()
                    self.host.error(self.bus.name, "connections",
                                    f"{self.kind} bus {self.bus.name}: {self._link()} took "
                                    f"{1 + len(self._lanes)} of {want} connections; polls use "
                                    f"those")
                    break
                self._lanes.append(lane)
        return [self._client, *self._lanes]

    async def _lane_answers(self, lane: Any) -> bool:
        """Connect the extra client ``lane`` and read one entry of the first device on it;
        True if that was answered (data or an exception answer)."""
        p = next(iter(self._points.values()))
        try:
            if not (await lane.connect() and lane.connected):
                return False
            self.host.stat(self.bus.name, "requests")
            await getattr(lane, READ_METHOD[p.table])(p.address, count=1, device_id=p.unit)
        except (ModbusException, OSError):
            return False
        return bool(lane.connected)

    async def _poll(self, plan: Sequence[ReadRequest]) -> None:
        """Run the requests of one poll: in order on one connection, or - several requests and
        ``connections`` > 1 - spread over the connections, all of them outstanding at once (each
        connection runs its share in order; pymodbus' client has one request in flight per
        connection). Every request reports its own failures; a lost connection ends the poll
        with :class:`ConnectionException` once every request is answered or failed."""
        batch: list[tuple[str, Any]] = []
        try:
            clients = await self._open_lanes() if len(plan) > 1 else [self._client]
            if len(clients) == 1:
                for request in plan:
                    await self._read(request, self._client, batch)
                return
            n = min(len(clients), len(plan))

            async def share(i: int) -> None:
                for request in plan[i::n]:
                    await self._read(request, clients[i], batch)

            results = await asyncio.gather(*(share(i) for i in range(n)),
                                           return_exceptions=True)
            for res in results:
                if isinstance(res, BaseException):
                    raise res
        finally:   # the poll's readings as one interrupt, before a lost link fails them
            deliver_all(self.host, batch)

    async def _read(self, r: ReadRequest, c: Any, batch: list[tuple[str, Any]]) -> None:
        """Run one read request on client ``c``; its readings go to ``batch`` (delivered at the
        end of the poll), its failures to the host at once."""
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
            if self._health.has_causes(p.device):
                self._health.clear(p.device, "exception", f"{r.describe()} answered")
            batch.append((p.device, value))

    async def _write_point(self, p: Point, value: Any) -> None:
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
            regs = p.encode(value)
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
