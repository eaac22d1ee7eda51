"""modbus - the ``modbus-tcp`` and ``modbus-rtu`` bus drivers, on pymodbus' synchronous clients.

Bus options:

* ``modbus-tcp``: ``host`` (required), ``port`` (default 502), ``connections`` (1..16, default 1):
  how many TCP connections a poll of several requests may spread them over, all outstanding at
  once (pymodbus' client has one request in flight per connection; a server that takes fewer
  connections is polled over those it takes).
* ``modbus-rtu``: ``port`` (required: a serial device, or a pyserial URL such as
  ``socket://127.0.0.1:5020``), ``baudrate`` (19200), ``parity`` (``N``/``E``/``O``), ``stopbits``
  (1/2), ``bytesize`` (7/8), ``dead_unit_backoff`` (the most poll periods between two tries of
  a unit that stopped answering; see :func:`drivers.modbus_link.dead_unit_backoff`). Every
  request waits for 3.5 characters of silence on the line (:class:`SerialClient`).
* both: ``timeout`` (s per request, 1.0), ``retries`` (1), ``reconnect_delay`` (s, 0.1; doubled
  after each failed attempt up to ``reconnect_delay_max``, 5.0; from the shutdown flush on,
  ``reconnect_delay`` each time), ``poll_period`` (s, 0.1; on a bus with no sensor: the period
  of the liveness probe, 1.0), ``watchdog`` (``{unit, table, address, period, value}``: a
  register written every period for the PLC's comm-loss logic).

What each bus does under faults, and what to set on the PLC: ``docs/modbus-faults.md``.

Device address: ``{unit = 1, table = coil|discrete|holding|input, address, type, word_order =
ABCD|CDAB|BADC|DCBA (big = ABCD, little = CDAB), poll_period}``; ``type`` is ``bool`` for
coils and discrete inputs (the default there) and one of ``int16 uint16 int32 uint32 float32
float64`` for registers (default ``uint16``).
Sensors are polled every ``poll_period`` of the kernel clock, paced by the polls (a bus slower
than the period is polled back to back, counted ``polls-late``; see :mod:`drivers.jobs`; the
kernel timer only enqueues); each poll groups the contiguous addresses of one unit and table into
one request.
Actuators (coils and holding registers) are written without blocking the caller. Jobs (a poll, a
write, a probe) run in order on the driver's own worker thread, on pymodbus' synchronous client
(``ModbusTcpClient``; for RTU :class:`SerialClient`, ``ModbusSerialClient`` with a receive that
waits for the port instead of polling it); within a poll of several requests on ``modbus-tcp``
with ``connections`` > 1 the requests are outstanding at once, spread over the connections, each
extra connection's share on a thread of its own (a pool of the driver); values are packed and
unpacked by :mod:`drivers.codecs.modbus` as pymodbus'
``convert_from_registers``/``convert_to_registers`` do.

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
for them succeeds. A write that fails while its unit is there (an exception answer; on
``modbus-rtu`` also no answer) fails the actuator (cause ``write``) and the driver reads the
actuator's own coil or registers back every ``poll_period`` by itself: data, or exception 1/2/3
(the entry cannot be read), ends the failure; busy, acknowledge and silence do not. Commands to
the failed actuator are refused meanwhile (Devtab names the status), so recovery never waits for
one; after it Devtab writes the safe value first.
A request timeout counts as a lost link on ``modbus-tcp`` (the connection is closed and
re-made), and on ``modbus-rtu`` fails every device of that unit, actuators too (cause
``unit``; the other units of the line are not touched) until the unit answers again; its
requests are thinned out meanwhile (:class:`drivers.codecs.modbus.UnitBackoff`) and a write
queued for it before it stopped answering is not sent. Every write is confirmed
(``host.written`` once the server answered it) or reported failed (``host.write_failed``:
exception answer, no answer, malformed answer, link down, unit failed since it was queued,
dropped at stop); a value the register type cannot hold is refused before it is queued
(:meth:`check_value`). Statistics (``host.stat``/``host.error``): ``requests``,
``reconnects``, ``connect-failed``, ``watchdog``; errors ``timeout``, ``exception-<code>``,
``disconnected``, ``malformed``, ``not-sent``.

This module holds the two kinds; what they share (polling, writes, link supervision) is
:class:`drivers.modbus_link.ModbusDriver` (life cycle, jobs, link supervision) on
:class:`drivers.modbus_requests.ModbusRequests` (the reads and writes; a poll's readings go to the
host as one interrupt), the pure data model (read planning, register packing, value checks, RTU
answer classification) :mod:`drivers.codecs.modbus`.
"""

from __future__ import annotations

import fcntl
import select
import struct
import termios
import time
from collections.abc import Mapping, Sequence
from typing import Any

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException
from pymodbus.framer import FramerType

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.helpers import is_int
from drivers.base import DriverHost
from drivers.codecs.modbus import (
    READ_REQUEST_BYTES,
    LineTiming,
    answer_bytes,
    classify_rtu_answer,
    plan_reads,
    point_of,
)
from drivers.modbus_link import (
    MAX_CONNECTIONS,
    ModbusDriver,
    check_common,
    dead_unit_backoff,
)


class SerialClient(ModbusSerialClient):
    """pymodbus' synchronous serial client with the receive of its asyncio serial transport.
    pymodbus' own synchronous receive polls ``in_waiting`` every four character times (1 ms at
    least) until the count stops growing: a sleep or two per answer on a serial line or pty
    (204 against 1,363 reads/s over a pty here), and on a ``socket://`` port, where pyserial's
    ``in_waiting`` says only whether something can be read (0 or 1), one byte per poll (about
    100 reads/s). This receive waits (up to the timeout) until the port can be read and takes
    every byte it holds; pymodbus' framer gathers the frame from the chunks, as it did on the
    asyncio transport. A port without a file descriptor (``rfc2217://``, ``loop://``) keeps
    pymodbus' receive."""

    def __init__(self, port: str, *, line: LineTiming, **kwargs: Any) -> None:
        super().__init__(port, **kwargs)
        #: the line's timing: the silence kept before every request
        self.line = line
        #: when the line last went quiet (the last byte received, a receive that timed out, the
        #: end of a request sent) on ``time.monotonic``
        self._quiet_from = 0.0

    def send(self, request: bytes, addr: tuple[Any, ...] | None = None) -> int:
        """Send ``request`` once the line has been silent for 3.5 characters (t3.5, from the
        last byte received or the timeout that ended a wait): every slave on the line takes the
        silence as the end of the previous frame. Raises ConnectionException as pymodbus'."""
        wait = self._quiet_from + self.line.silence - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        sent = int(super().send(request, addr))
        self._quiet_from = time.monotonic() + len(request) * self.line.char_time
        return sent

    def recv(self, size: int | None) -> bytes:
        """The bytes the port holds once it can be read; ``b""`` after ``timeout`` s of silence.
        Raises ConnectionException (and closes the port) when the peer closed or the port
        failed."""
        data = self._recv(size)
        self._quiet_from = time.monotonic()
        return data

    def _recv(self, size: int | None) -> bytes:
        port = self.socket
        if size is not None or port is None:
            return bytes(super().recv(size))
        try:
            fd = port.fileno()
        except (OSError, ValueError, AttributeError):   # no descriptor to wait on
            return bytes(super().recv(size))
        try:
            if not select.select([fd], [], [], self.comm_params.timeout_connect)[0]:
                return b""
            waiting = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0"))[0]
            # readable with nothing to read: the peer closed (pyserial raises for that)
            return bytes(port.read(max(waiting, 1)))
        except (OSError, ValueError):
            self.socket = None                  # as pymodbus' close(): the port is gone
            port.close()
            raise ConnectionException(str(self)) from None


def line_timing(bus: BusSpec) -> LineTiming:
    """The timing of a ``modbus-rtu`` bus's line, from its serial options."""
    o = bus.options
    return LineTiming(int(o.get("baudrate", 19200)), int(o.get("bytesize", 8)),
                      str(o.get("parity", "N")), int(o.get("stopbits", 1)))


class ModbusTcpDriver(ModbusDriver):
    """``modbus-tcp``: a Modbus TCP server at ``host:port``."""

    kind = "modbus-tcp"
    timeout_is_link_loss = True

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of ``host``, ``port`` and the common options."""
        errs = check_common(bus, ("host", "port", "connections"))
        o: Mapping[str, Any] = bus.options
        if not (isinstance(o.get("host"), str) and o["host"]):
            errs.append(f"{bus.key}.host: expected a host name or address, got "
                        f"{o.get('host')!r}")
        port = o.get("port", 502)
        if not (is_int(port) and 1 <= port <= 65535):
            errs.append(f"{bus.key}.port: expected a TCP port 1..65535, got {port!r}")
        n = o.get("connections", 1)
        if not (is_int(n) and 1 <= n <= MAX_CONNECTIONS):
            errs.append(f"{bus.key}.connections: expected an integer 1..{MAX_CONNECTIONS} (TCP "
                        f"connections a poll may use at once), got {n!r}")
        return errs

    def _connections(self) -> int:
        return int(self.bus.options.get("connections", 1))

    def _make_client(self) -> Any:
        o = self.bus.options
        return ModbusTcpClient(str(o["host"]), port=int(o.get("port", 502)),
                               timeout=float(o.get("timeout", 1.0)),
                               retries=int(o.get("retries", 1)), name=self.bus.name)

    def _link(self) -> str:
        return f"{self.bus.options['host']}:{self.bus.options.get('port', 502)}"


class ModbusRtuDriver(ModbusDriver):
    """``modbus-rtu``: Modbus RTU on a serial line (or a pyserial URL such as socket://)."""

    kind = "modbus-rtu"

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of the serial options and the common options."""
        errs = check_common(bus, ("port", "baudrate", "parity", "stopbits", "bytesize",
                                  "dead_unit_backoff"))
        o: Mapping[str, Any] = bus.options
        k = bus.key
        if not (isinstance(o.get("port"), str) and o["port"]):
            errs.append(f"{k}.port: expected a serial port (/dev/ttyUSB0, socket://host:port), "
                        f"got {o.get('port')!r}")
        if not (is_int(o.get("baudrate", 19200)) and o.get("baudrate", 19200) > 0):
            errs.append(f"{k}.baudrate: expected an integer > 0, got {o.get('baudrate')!r}")
        if o.get("parity", "N") not in ("N", "E", "O"):
            errs.append(f"{k}.parity: expected \"N\", \"E\" or \"O\", got {o.get('parity')!r}")
        if o.get("stopbits", 1) not in (1, 2) or isinstance(o.get("stopbits"), bool):
            errs.append(f"{k}.stopbits: expected 1 or 2, got {o.get('stopbits')!r}")
        if o.get("bytesize", 8) not in (7, 8) or isinstance(o.get("bytesize"), bool):
            errs.append(f"{k}.bytesize: expected 7 or 8, got {o.get('bytesize')!r}")
        if "dead_unit_backoff" in o and not (is_int(o["dead_unit_backoff"])
                                             and o["dead_unit_backoff"] >= 1):
            errs.append(f"{k}.dead_unit_backoff: expected an integer >= 1 (the most poll "
                        f"periods between two tries of a unit that does not answer), got "
                        f"{o['dead_unit_backoff']!r}")
        return errs

    @classmethod
    def check_warnings(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[str]:
        """A ``timeout`` the line's timing defeats: shorter than the longest exchange (request,
        answer and the silence after each, at the line's baud rate) - that answer never arrives
        in time - or, with several units, a try of the dead ones (``timeout`` x (``retries`` +
        1) each) longer than the poll period - the live units miss polls at each try."""
        o = bus.options
        line = line_timing(bus)
        timeout = float(o.get("timeout", 1.0))
        points = [point_of(d) for d in devices]
        reads = plan_reads([p for p, d in zip(points, devices, strict=True)
                            if d.direction == "sensor"])
        longest = max([line.exchange_time(READ_REQUEST_BYTES, answer_bytes(r)) for r in reads]
                      + [line.exchange_time(READ_REQUEST_BYTES + 2 * p.size + 1, 8)
                         for p, d in zip(points, devices, strict=True)
                         if d.direction == "actuator"], default=0.0)
        out = []
        if longest > timeout:
            out.append(f"timeout: {timeout:g} s is shorter than the longest exchange on the "
                       f"line ({longest * 1e3:.1f} ms at {line.baudrate} baud with the 3.5-"
                       f"character silences): that answer can never arrive in time")
        units = {p.unit for p in points}
        cost = timeout * (int(o.get("retries", 1)) + 1)
        periods = [float(d.address.get("poll_period", o.get("poll_period", 0.1)))
                   for d in devices if d.direction == "sensor"]
        period = min(periods, default=float(o.get("poll_period", 1.0)))
        if len(units) > 1 and cost * (len(units) - 1) > period:
            out.append(f"timeout: a unit that does not answer holds the line {cost:g} s per try "
                       f"(timeout x (retries + 1)), {len(units) - 1} such unit(s) "
                       f"{cost * (len(units) - 1):g} s, longer than the poll period "
                       f"{period:g} s: while units are dead the live ones miss polls at each "
                       f"try (a dead unit is tried at most every {dead_unit_backoff(bus)} poll "
                       f"periods, dead_unit_backoff)")
        return out

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._tx = b""                  # the last request frame sent
        self._rx_bytes = bytearray()    # every byte received since it was sent
        self._rx_buffer = b""           # pymodbus' receive buffer as last seen
        #: Requests that got no valid answer, by class: crc, framing (junk or a truncated
        #: answer), timeout (silence). Each is also reported through ``host.error``.
        self.unanswered: dict[str, int] = {}

    def _trace(self, sending: bool, data: bytes) -> bytes:
        """pymodbus' packet hook (worker thread): keeps the request and the bytes of its answer.
        The synchronous client calls it with each request frame sent (``sending``) and, after
        every chunk received, with its receive buffer (the bytes not yet taken as a frame)."""
        if sending:
            self._tx, self._rx_bytes, self._rx_buffer = bytes(data), bytearray(), b""
        else:
            prev = self._rx_buffer
            self._rx_bytes += data[len(prev):] if data.startswith(prev) else data
            self._rx_buffer = bytes(data)
        return data

    def _unanswered(self, request: str) -> tuple[str, str]:
        """Classify the bytes that came back for the last request (none: timeout; a frame of
        the right unit and function, long enough, failing its CRC: crc; anything else:
        framing) and count the class."""
        kind, why = classify_rtu_answer(self._tx, bytes(self._rx_bytes))
        self.unanswered[kind] = self.unanswered.get(kind, 0) + 1
        return kind, why

    def _make_client(self) -> Any:
        o = self.bus.options
        return SerialClient(str(o["port"]), line=line_timing(self.bus), framer=FramerType.RTU,
                            trace_packet=self._trace,
                            baudrate=int(o.get("baudrate", 19200)),
                            parity=str(o.get("parity", "N")), stopbits=int(o.get("stopbits", 1)),
                            bytesize=int(o.get("bytesize", 8)),
                            timeout=float(o.get("timeout", 1.0)),
                            retries=int(o.get("retries", 1)), name=self.bus.name)

    def _link(self) -> str:
        return str(self.bus.options["port"])
