"""serial_line - the serial driver (kind ``serial``): pyserial port, line or binary protocol.

The port is opened with ``serial.serial_for_url``, so ``url`` may be a device path
(``/dev/ttyUSB0``, a pty slave such as ``/dev/pts/7``), ``socket://127.0.0.1:5000`` (a TCP
serial server) or ``loop://``; ``chcos-direct://NAME`` is the in-process line of virtual time
(:mod:`drivers.serial_direct`: no thread, the peer's bytes handled inside its write, the
commands written in the caller's thread, probes on the kernel clock), which the simulated
instrument of a virtual cell is on. A reader thread reads and decodes; a writer thread sends
actuator commands, so :meth:`SerialDriver.write` never blocks. When the port goes away
(read/write error, socket closed, open fails) every device is ``host.fail``-ed and the reader
reopens it with a backoff doubling from ``reconnect_min`` to ``reconnect_max`` seconds; on
success the devices are ``host.recover``-ed.

Bus options:

- ``url`` (required), ``baudrate`` (int, default 9600), ``poll`` (read timeout s, default 0.01;
  only for ports without a file descriptor such as ``loop://``: on a tty or ``socket://`` the
  reader sleeps in ``select`` and ``settle`` reads what has arrived itself),
  ``reconnect_min`` (default 0.05), ``reconnect_max`` (default 2.0)
- ``protocol = "line"``: ``pattern`` (required; a Python regular expression with named groups that
  must match a whole line), ``eol`` (default ``"\\n"``; a trailing ``"\\r"`` is stripped),
  ``encoding`` (default ``"ascii"``), ``max_line`` (default 1024 bytes)
- ``protocol = "binary"``: ``sync`` (required; hex bytes such as ``"AA 55"``), ``struct``
  (required; a :mod:`struct` format of the payload after the sync), ``fields`` (required; one name
  per struct item, ``"_"`` for items to ignore), ``checksum`` (``"none"`` (default), ``"sum8"`` or
  ``"xor8"``: one byte after the payload, over the payload)

Device addresses: a sensor names its value, ``{ group = "t1" }`` (line) or ``{ field = "t1" }``
(binary); a line group is a number unless the address says ``type = "text"`` (then the matched
text is delivered as it is, e.g. a linear sensor's pixel string). A number is a finite decimal
as instruments write it (``-12.5``, ``1e3``); ``nan``, ``inf``, ``1_000``, ``0x10`` and non-ASCII
digits are "malformed", and so is a binary frame whose float field is nan or infinite. An
actuator gives how a command is written: line, ``{ format = "SET M1 {value:.2f}" }``
(``str.format`` with ``value``; ``eol`` is appended); binary, ``{ struct = "<h", prefix = "10" }``
(the frame sent is sync + payload + checksum, payload = prefix bytes + the value packed with
``struct``; integer codes get the value rounded).

A line that does not match, bytes that are not a frame, a bad checksum: ``host.error(bus,
"garbage" | "malformed" | "checksum", ...)``, also counted in ``SerialDriver.error_counts``;
nothing stops the reader. A command that cannot be encoded is reported as a failed write (the
device is fine). A command that cannot be written (the port not open, the write failing or timing
out) is a failed write and ``host.fail(device)``; nothing latches: the driver then tries the port
again itself (:mod:`drivers.sendprobe`: the actuator's last command that went out, else its safe
value, backing off from ``reconnect_min`` to ``reconnect_max``), and the first command that goes
out, probe or command of any actuator, is ``host.recover`` for every actuator failed by a write;
the port open again recovers every device.
"""

from __future__ import annotations

import contextlib
import re
import struct
from collections.abc import Sequence
from typing import Any

import serial

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from drivers.base import DriverHost, not_finite
from drivers.codecs.serial import (
    BINARY_OPTIONS,
    COMMON_OPTIONS,
    INT_CODES,
    LINE_OPTIONS,
    BinaryFramer,
    LineFramer,
    check_binary_bus,
    check_line_bus,
    encode_command,
    num_ok,
    parse_hex,
    struct_of,
)
from drivers.sendprobe import ClockedSendProbe, SendProbe, safe_raw
from drivers.serial_direct import SCHEME as DIRECT_SCHEME
from drivers.serial_direct import open_end
from drivers.threaded import ThreadedDriver


class SerialDriver(ThreadedDriver):
    """Driver for kind ``serial`` (see the module docstring for options, addresses, threads)."""

    kind = "serial"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        o = bus.options
        self._binary = o["protocol"] == "binary"
        self._sync = parse_hex(str(o["sync"])) if self._binary else b""
        self._check = str(o.get("checksum", "none"))
        self._poll = float(o.get("poll", 0.01))
        self._backoff = (float(o.get("reconnect_min", 0.05)), float(o.get("reconnect_max", 2.0)))
        key = "field" if self._binary else "group"
        self._sensors: dict[str, list[str]] = {}
        for d in devices:
            if d.direction == "sensor":
                self._sensors.setdefault(str(d.address[key]), []).append(d.name)
        self._failed = False
        self._port: Any = None
        #: the last raw value of each actuator that went out (what the peer holds)
        self._last_sent: dict[str, Any] = {}
        #: the actuators whose command could not be written, tried again by the driver itself
        #: (backing off as the reconnects do)
        self.probe = SendProbe(f"{self.kind}-{bus.name}", self._probe_send, self._backoff)
        self.connects = 0

    def _framer(self) -> LineFramer | BinaryFramer:
        o = self.bus.options
        if self._binary:
            return BinaryFramer(self._sync, str(o["struct"]), list(o["fields"]), self._check)
        text = (str(d.address["group"]) for d in self.devices.values()
                if d.direction == "sensor" and d.address.get("type") == "text")
        return LineFramer(str(o["pattern"]), str(o.get("eol", "\n")),
                          str(o.get("encoding", "ascii")), int(o.get("max_line", 1024)), text)

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Options of the common part and of the chosen protocol."""
        o, key = bus.options, bus.key
        proto = o.get("protocol")
        valid = COMMON_OPTIONS + (LINE_OPTIONS if proto == "line" else BINARY_OPTIONS
                                  if proto == "binary" else ())
        errs = [f"{key}.{k}: unknown option for a {proto} serial bus; valid options: "
                f"{', '.join(valid)}" for k in o if k not in valid and proto in ("line", "binary")]
        if not isinstance(o.get("url"), str) or not o.get("url"):
            errs.append(f"{key}.url: expected a port path or pyserial URL (socket://host:port, "
                        f"loop://), got {o.get('url')!r}")
        br = o.get("baudrate", 9600)
        if not isinstance(br, int) or isinstance(br, bool) or br <= 0:
            errs.append(f"{key}.baudrate: expected bits per second > 0, got {br!r}")
        for k, lo, hi in (("poll", 0, 1), ("reconnect_min", 0, 60), ("reconnect_max", 0, 600)):
            if k in o and not num_ok(o[k], lo, hi):
                errs.append(f"{key}.{k}: expected seconds in ({lo}, {hi}], got {o[k]!r}")
        if proto == "line":
            errs += check_line_bus(key, o)
        elif proto == "binary":
            errs += check_binary_bus(key, o)
        else:
            errs.append(f"{key}.protocol: expected \"line\" or \"binary\", got {proto!r}")
        return errs

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """A sensor's group/field exists; an actuator's format/struct is usable."""
        key, a, o = f"{device.key}.address", device.address, bus.options
        proto = o.get("protocol")
        if device.direction == "sensor":
            want = "group" if proto == "line" else "field"
            allowed = (want, "type") if proto == "line" else (want,)
            errs = [f"{key}.{k}: unknown key; a {proto} sensor takes only "
                    f"{' and '.join(allowed)}" for k in a if k not in allowed]
            if a.get("type", "number") not in ("number", "text"):
                errs.append(f"{key}.type: expected \"number\" (default) or \"text\", got "
                            f"{a.get('type')!r}")
            name = a.get(want)
            try:
                fields = o.get("fields", [])
                names = (list(re.compile(str(o.get("pattern"))).groupindex) if proto == "line"
                         else [f for f in fields if f != "_"] if isinstance(fields, list) else [])
            except re.error:
                return errs            # reported by check_bus
            if name not in names:
                errs.append(f"{key}.{want}: expected one of {', '.join(map(str, names))}, "
                            f"got {name!r}")
            return errs
        if proto == "line":
            errs = [f"{key}.{k}: unknown key; a line actuator takes only format"
                    for k in a if k != "format"]
            fmt = a.get("format")
            try:
                if not isinstance(fmt, str):
                    raise TypeError(f"got {fmt!r}")
                fmt.format(value=0.0)
            except (TypeError, ValueError, KeyError, IndexError) as exc:
                errs.append(f"{key}.format: expected a str.format string using {{value}}: {exc}")
            return errs
        errs = [f"{key}.{k}: unknown key; a binary actuator takes struct and prefix"
                for k in a if k not in ("struct", "prefix")]
        try:
            st = struct_of(a.get("struct"))
            if len(st.unpack(bytes(st.size))) != 1:
                errs.append(f"{key}.struct: expected a format of exactly one item")
        except struct.error as exc:
            errs.append(f"{key}.struct: expected a struct format, got {a.get('struct')!r}: {exc}")
        try:
            parse_hex(str(a.get("prefix", "")))
        except ValueError:
            errs.append(f"{key}.prefix: expected hex bytes, got {a.get('prefix')!r}")
        return errs

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of a binary actuator's struct code (0..1 for ``?``, the integer codes'
        ranges, the largest float16/float32); None for a line actuator and for ``d``."""
        if bus.options.get("protocol") != "binary":
            return None
        fmt = str(device.address.get("struct", ""))
        code = fmt[-1:]
        if code == "?":
            return 0.0, 1.0
        if code in INT_CODES:
            bits = 8 * struct_of(fmt).size
            if code.islower():
                return float(-(1 << (bits - 1))), float((1 << (bits - 1)) - 1)
            return 0.0, float((1 << bits) - 1)
        top = {"e": 65504.0, "f": 3.4028234663852886e38}.get(code)
        return None if top is None else (-top, top)

    def command(self, device: str, value: Any) -> bytes:
        """The bytes that set actuator ``device`` to ``value``; raises :class:`BusError`."""
        try:
            return encode_command(self.bus.options, self.devices[device].address, value)
        except (struct.error, ValueError, TypeError, UnicodeEncodeError, OverflowError) as exc:
            raise BusError(f"cannot encode {device}={value!r} for serial bus "
                           f"{self.bus.name!r}: {exc}") from exc

    def start(self) -> None:
        """Start the reader (which opens the port, and reopens it) and the writer thread; on a
        direct line (``chcos-direct://``, virtual time) open it and start no thread: its bytes
        arrive in the peer's write and commands go out in the caller's (see
        :mod:`drivers.serial_direct`). Raises :class:`BusError` if the direct line is taken."""
        url = str(self.bus.options["url"])
        if url.startswith(DIRECT_SCHEME):
            try:
                end = open_end(url)
            except OSError as exc:
                raise BusError(f"bus {self.bus.name!r} ({self.bus.file} {self.bus.key}): "
                               f"{exc}") from exc
            self._synchronous = True
            self.probe = ClockedSendProbe(f"{self.kind}-{self.bus.name}", self._probe_send,
                                          self._backoff, self.host.at, self.host.now)
            self._port = end
            self.connects = 1
            framer = self._framer()
            end.set_receiver(lambda data: self._feed(framer, data))
        self._start_threads()

    def wait_open(self, timeout: float) -> bool:
        """Wait until the port is open (after start or a reconnect); False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: self._port is not None or not self._running,
                                       timeout) and self._running

    def stop(self) -> None:
        """Stop both threads and close the port. Idempotent; never raises."""
        self.probe.stop()
        self._stop_threads()
        self._close()

    # -- threads ---------------------------------------------------------------------------

    def _close(self) -> None:
        with self._cond:
            port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(OSError, serial.SerialException):
                port.close()

    def _open(self) -> Any:
        o = self.bus.options
        try:
            return serial.serial_for_url(str(o["url"]), baudrate=int(o.get("baudrate", 9600)),
                                         timeout=self._poll, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            self._down(f"cannot open {o['url']}: {exc}")
            return None

    def _read_loop(self) -> None:
        delay = self._backoff[0]
        while self._running:
            port = self._open()
            if port is None:
                self._rx.set_offline(True)
                with self._cond:
                    self._cond.wait_for(lambda: not self._running, delay)
                delay = min(delay * 2, self._backoff[1])
                continue
            delay = self._backoff[0]
            with self._cond:
                self._port = port
                self.connects += 1
                self._cond.notify_all()
            if self.connects > 1:
                self.host.stat(self.bus.name, "reconnects")
            self._rx.set_offline(False)
            self._up()
            self._pump(port, self._framer())
            self._rx.set_offline(True)
            self._close()

    def _pump(self, port: Any, framer: LineFramer | BinaryFramer) -> None:
        try:
            fd = port.fileno()
        except (AttributeError, OSError, NotImplementedError, serial.SerialException):
            fd = None
        if not isinstance(fd, int) or fd < 0:
            self._pump_polling(port, framer)
            return
        port.timeout = 0
        lost: list[str] = []

        def drain() -> None:
            self._drain_port(port, framer, lost)

        rx = self._rx
        rx.set_drain(drain)
        try:
            while rx.running and not lost:
                if rx.wait_readable(fd, 1.0):
                    with rx.lock:
                        drain()
        finally:
            rx.set_drain(None)
        if lost and self._running:
            self._down(lost[0])

    def _drain_port(self, port: Any, framer: LineFramer | BinaryFramer, lost: list[str]) -> None:
        """Read what the port holds now without blocking (port timeout 0) and hand it over;
        a read error is noted in ``lost`` for the reader to reconnect."""
        if lost:
            return
        try:
            data = port.read(65536)
        except (serial.SerialException, OSError, TypeError) as exc:
            lost.append(f"port {self.bus.options['url']} lost: {exc}")
            return
        self._feed(framer, data)

    def _pump_polling(self, port: Any, framer: LineFramer | BinaryFramer) -> None:
        while self._running:
            try:
                data = port.read(max(1, port.in_waiting))
            except (serial.SerialException, OSError, TypeError) as exc:
                if self._running:
                    self._down(f"port {self.bus.options['url']} lost: {exc}")
                return
            if not data:
                self._rx.idle()
                continue
            self._feed(framer, data)

    def _feed(self, framer: LineFramer | BinaryFramer, data: bytes) -> None:
        for kind, detail in framer.feed(data):
            try:
                self._event(kind, detail)
            except Exception as exc:  # the reader must survive any host surprise
                self._error("internal", f"delivery failed: {exc!r}")

    def _event(self, kind: str, detail: Any) -> None:
        if kind != "values":
            self._error(kind, str(detail))
            return
        self.host.stat(self.bus.name, "frames")
        for name, value in detail.items():
            for device in self._sensors.get(name, ()):
                self.host.deliver(device, value)

    def _can_send(self) -> bool:
        """At start-up a command waits for the first open attempt; while down it fails at once."""
        return self._port is not None or self._failed

    def check_value(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be sent to ``device`` (None if it can): not a finite number,
        a fraction for an integer struct code, or a value its format cannot encode."""
        if device not in self.devices:
            return None
        if (why := not_finite(value)) is not None:
            return why
        if isinstance(value, bool):
            value = int(value)
        a = self.devices[device].address
        if self._binary and str(a.get("struct", "x"))[-1:] in INT_CODES and isinstance(
                value, float) and not value.is_integer():
            return f"expected an integer for struct {a.get('struct')!r}, got {value!r}"
        try:
            self.command(device, value)
        except BusError as exc:
            return str(exc)
        return None

    def _send(self, device: str, value: Any) -> None:
        with self._cond:
            port = self._port
        try:
            data = self.command(device, value)
        except BusError as exc:     # a value that does not fit: refused, the device is fine
            self._error("range", str(exc))
            self.host.write_failed(device, value, str(exc))
            return
        try:
            self._put(port, data)
        except BusError as exc:
            with self._cond:
                last = self._last_sent.get(device)
            self.host.write_failed(device, value, str(exc))
            self.host.fail(device, str(exc))
            # no latch: the driver tries the port again itself (see drivers.sendprobe)
            self.probe.failed(device, last if last is not None else
                              safe_raw(self.devices[device]))
            return
        self.host.written(device, value)
        with self._cond:
            self._last_sent[device] = value
        self._link_works(device, "a command was written")

    def _put(self, port: Any, data: bytes) -> None:
        """Write ``data`` to ``port`` and wait until it left; raises BusError naming the port
        and the cause (not open, the write failed or timed out, the port closed under it)."""
        if port is None:
            raise BusError(f"serial port {self.bus.options['url']} is not open; command "
                           f"{data!r} not sent")
        try:
            port.write(data)
            port.flush()
        except (serial.SerialException, OSError) as exc:
            raise BusError(f"write to {self.bus.options['url']} failed: {exc}") from exc
        except (TypeError, AttributeError) as exc:
            if port.is_open:    # not the port closing under the write: a real bug
                raise
            # the reader closed the port (link lost) during the write: pyserial's socket://
            # then fails with a TypeError instead of an OSError
            raise BusError(f"write to {self.bus.options['url']} failed: the port was closed "
                           f"during the write") from exc

    def _probe_send(self, device: str, value: Any) -> str | None:
        """One probe of ``device`` (the probe's thread, see :mod:`drivers.sendprobe`): the
        command of ``value`` written as a command would be, holding the send; None if it went
        out (not reported as a write: no command asked for it), else why not."""
        def send() -> str | None:
            with self._cond:
                port = self._port
            try:
                self._put(port, self.command(device, value))
            except BusError as exc:
                return str(exc)
            self._link_works(device, f"the port took a command again (probe: {value!r} "
                                     f"re-sent)")
            return None
        return self._claimed(send)

    def _link_works(self, device: str, why: str) -> None:
        """A command of ``device`` went out: the port takes writes again, so every actuator
        failed by a write recovers (see :mod:`drivers.sendprobe`)."""
        for name in self.probe.recovered():
            self.host.recover(name, why if name == device else
                              f"a command of {device} was written: the port takes writes again")

    def _down(self, reason: str) -> None:
        with self._cond:
            was, self._failed = self._failed, True
            self._cond.notify_all()
        if not was:
            for name in self.devices:
                self.host.fail(name, f"serial bus {self.bus.name!r}: {reason}")

    def _up(self) -> None:
        with self._cond:
            was, self._failed = self._failed, False
            if was:
                self.probe.clear()               # recovered below with every device
            self._cond.notify_all()
        if was:
            for name in self.devices:
                self.host.recover(name, f"serial port {self.bus.options['url']} open again")

