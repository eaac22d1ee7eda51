"""can_raw - the raw CAN driver (kind ``can``): python-can bus, signals coded with cantools.

Bus options:

- ``interface``, ``channel``: python-can's; when left out they come from python-can's own
  configuration (``can.util.load_config``: ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment
  variables and its config files), so one map serves ``virtual`` on a laptop and ``socketcan`` at
  the cell.
- ``bitrate`` (int > 0, optional), ``fd`` (bool, default false)
- ``dbc``: a DBC file (relative to the map file); needed for ``{message, signal}`` addresses
- ``record``: a log file (``.log``/``.asc``/``.blf``...) receiving every frame received and sent
- ``poll``: the reader's receive timeout in seconds (default 0.005) on interfaces it cannot wait
  on without receiving; it bounds :meth:`settle` there. On SocketCAN (``select`` on the socket)
  and python-can's ``virtual`` interface (its receive queue) the reader sleeps until a frame is
  there and :meth:`settle` drains the bus itself, so ``poll`` is not used

Device addresses, one of two forms:

- DBC: ``{ message = "Temps", signal = "T1" }`` (names from the DBC file)
- raw: ``{ id = 0x101, start = 0, length = 16, byte_order = "little_endian", signed = false,
  dlc = 8, extended = false }`` (``start`` is the DBC start bit; ``byte_order``, ``signed``,
  ``dlc``, ``extended`` are optional with these defaults). Raw signals are unscaled integers.
  Raw devices that share an id form one message and must agree on ``dlc`` and ``extended``.

Received frames are decoded on the reader thread: a frame of a sensor message is decoded and every
sensor signal in it delivered; a frame whose id carries only actuator signals is ignored (another
node, or a replayed log, sends it); any other id is ``host.error(bus, "unknown-id")``, a frame of
the wrong length ``"wrong-length"``, one cantools cannot decode ``"undecodable"``, an error frame
``"error-frame"``, a remote frame (a data request, which chcos does not answer) ``"remote-frame"``.
On SocketCAN, frames the kernel dropped because the socket's receive buffer was full are
``"overrun"`` with the number lost (the socket's drop count, read with ``SO_MEMINFO``, the count
``SO_RXQ_OVFL`` reports), also summed in ``CanDriver.overrun_lost``; python-can's ``virtual``
interface has no such buffer and never overruns. Actuator writes are queued to a writer thread
(the caller never blocks); it
encodes the whole message, keeping the other signals at their last written value or else the
DBC initial value (0 if none, clipped into the signal's range), and sends it. Encoding or send
failures are reported with ``host.fail(device, ...)``; the next successful write of that actuator
reports ``host.recover(device)``. Bus errors are also counted in ``CanDriver.error_counts``.
"""

from __future__ import annotations

import contextlib
import functools
import math
import queue
import socket
import struct
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeGuard

import can
import cantools
from cantools.database.can import Message as DbcMessage
from cantools.database.can import Signal as DbcSignal

from chcos.devices import parsecache
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from drivers.base import DriverHost, not_finite
from drivers.recording import LOG_SUFFIXES, Recorder
from drivers.threaded import ReaderThread, ThreadedDriver

BUS_OPTIONS = ("interface", "channel", "bitrate", "fd", "dbc", "record", "poll")
DBC_KEYS = ("message", "signal")
RAW_KEYS = ("id", "start", "length", "byte_order", "signed", "dlc", "extended")
BYTE_ORDERS = ("little_endian", "big_endian")


def _int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def load_dbc(path: str) -> Any:
    """Load a DBC file with cantools (once per device-map load, see
    :mod:`chcos.devices.parsecache`);
    raises :class:`BusError` naming the file."""
    try:
        return parsecache.cached("dbc", path, None, lambda: cantools.database.load_file(
            path, database_format="dbc", strict=True))
    except (OSError, cantools.database.errors.Error, ValueError) as exc:
        raise BusError(f"DBC file {path}: cannot be loaded: {exc}") from exc


def checked_dbc(path: str) -> Any:
    """:func:`load_dbc` for the map checks (``check_device``, ``encodable``): inside a
    :func:`chcos.devices.parsecache.scope` (``chcos check``, a device-map load) one parse per file,
    however many devices use it. The result may be shared: read it, never change it. Raises
    :class:`BusError` naming the file."""
    return load_dbc(path)


def _int_range(length: int, signed: bool) -> tuple[int, int]:
    if signed:
        return -(1 << (length - 1)), (1 << (length - 1)) - 1
    return 0, (1 << length) - 1


def bus_config(options: Mapping[str, Any]) -> dict[str, Any]:
    """python-can's configuration for this bus: the map's options over ``can.util.load_config``.

    Raises :class:`BusError` if python-can's configuration names no usable interface."""
    given = {k: options[k] for k in ("interface", "channel", "bitrate", "fd") if k in options}
    try:
        cfg = dict(can.util.load_config(config=given))
    except (can.CanInterfaceNotImplementedError, ValueError) as exc:
        raise BusError(f"python-can configuration: {exc}") from exc
    if cfg.get("channel") is None:
        raise BusError("python-can configuration gives no channel (set channel or CAN_CHANNEL)")
    return cfg


def _initial(sig: Any) -> float:
    init = sig.initial if sig.initial is not None else 0
    if sig.minimum is not None and init < sig.minimum:
        init = sig.minimum
    if sig.maximum is not None and init > sig.maximum:
        init = sig.maximum
    return float(init)


@dataclass
class _Frame:
    """One message this driver codes: the cantools message and which device each signal is."""

    message: Any
    sensors: dict[str, str] = field(default_factory=dict)     # signal name -> device
    actuators: dict[str, str] = field(default_factory=dict)   # signal name -> device
    values: dict[str, float] = field(default_factory=dict)    # last written (actuator side)


class CanCodec:
    """Maps devices to DBC/raw signals; decodes received frames, encodes actuator frames.

    Pure (no bus). Built from checked specs; raises :class:`BusError` if the DBC file is unusable.
    """

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec]) -> None:
        dbc = load_dbc(str(bus.options["dbc"])) if "dbc" in bus.options else None
        self._by_id: dict[tuple[int, bool], _Frame] = {}
        self._by_device: dict[str, tuple[_Frame, str]] = {}
        raw_groups: dict[int, list[DeviceSpec]] = {}
        for d in devices:
            if "message" in d.address:
                if dbc is None:
                    raise BusError(f"{d.file} {d.key}: a DBC address needs the bus option dbc")
                msg = dbc.get_message_by_name(d.address["message"])
                self._attach(msg, d, d.address["signal"])
            else:
                raw_groups.setdefault(int(d.address["id"]), []).append(d)
        for fid, group in raw_groups.items():
            a0 = group[0].address
            sigs = [DbcSignal(d.name, int(d.address["start"]), int(d.address["length"]),
                              byte_order=d.address.get("byte_order", "little_endian"),
                              is_signed=bool(d.address.get("signed", False))) for d in group]
            msg = DbcMessage(fid, f"raw_0x{fid:X}", int(a0.get("dlc", 8)), sigs,
                             is_extended_frame=bool(a0.get("extended", False)), strict=False)
            for d in group:
                self._attach(msg, d, d.name)

    def _attach(self, msg: Any, device: DeviceSpec, signal: str) -> None:
        key = (msg.frame_id, bool(msg.is_extended_frame))
        fr = self._by_id.get(key)
        if fr is None:
            fr = _Frame(msg, values={s.name: _initial(s) for s in msg.signals})
            self._by_id[key] = fr
        side = fr.sensors if device.direction == "sensor" else fr.actuators
        side[signal] = device.name
        self._by_device[device.name] = (fr, signal)

    def decode(self, frame: can.Message) -> tuple[str, list[tuple[str, Any]] | str]:
        """Classify and decode ``frame``: ``("ok", [(device, value)...])``, ``("ignore", why)``,
        or ``(error_kind, detail)`` with error_kind in remote-frame, unknown-id, wrong-length,
        undecodable."""
        if frame.is_remote_frame:
            return "remote-frame", (f"remote frame (a data request) for id "
                                    f"0x{frame.arbitration_id:X}, dlc {frame.dlc}: chcos does "
                                    f"not answer remote requests")
        fr = self._by_id.get((frame.arbitration_id, bool(frame.is_extended_id)))
        if fr is None:
            return "unknown-id", f"frame id 0x{frame.arbitration_id:X} is in no device's message"
        if not fr.sensors:
            return "ignore", "actuator message"
        if len(frame.data) != fr.message.length:
            return "wrong-length", (f"frame id 0x{frame.arbitration_id:X} ({fr.message.name}) "
                                    f"has {len(frame.data)} bytes, expected {fr.message.length}")
        try:
            vals = fr.message.decode(bytes(frame.data), decode_choices=False)
        except (cantools.database.DecodeError, ValueError, KeyError) as exc:
            return "undecodable", f"frame id 0x{frame.arbitration_id:X}: {exc}"
        out = [(dev, vals[sig]) for sig, dev in fr.sensors.items()]
        for dev, v in out:
            if isinstance(v, float) and not math.isfinite(v):
                return "undecodable", (f"frame id 0x{frame.arbitration_id:X}: signal of {dev} "
                                       f"is {v}, not a finite number")
        return "ok", out

    def check(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for actuator ``device`` (None if it can): not a
        finite number, outside the signal's range or bit width, a fraction for a raw (non-DBC)
        integer signal. Nothing is remembered."""
        item = self._by_device.get(device)
        if item is None:
            return None
        fr, sig = item
        if (why := not_finite(value)) is not None:
            return why
        if isinstance(value, bool):
            value = int(value)
        signal = fr.message.get_signal_by_name(sig)
        if (fr.message.name.startswith("raw_0x") and not signal.is_float
                and isinstance(value, float) and not value.is_integer()):
            return f"expected an integer for raw signal {sig} ({signal.length} bits), got {value!r}"
        values = dict(fr.values)
        values[sig] = value
        try:
            fr.message.encode(values, strict=True)
            if fr.message.name.startswith("raw_0x"):
                lo = -(1 << (signal.length - 1)) if signal.is_signed else 0
                hi = ((1 << (signal.length - 1)) - 1 if signal.is_signed
                      else (1 << signal.length) - 1)
                if not signal.is_float and not lo <= value <= hi:
                    return f"expected {lo}..{hi} for raw signal {sig}, got {value!r}"
        except (cantools.database.EncodeError, ValueError, KeyError, OverflowError) as exc:
            return f"cannot encode into {fr.message.name}: {exc}"
        return None

    def encode(self, device: str, value: Any) -> can.Message:
        """The frame that sets actuator ``device`` to ``value``, other signals unchanged.

        Raises :class:`BusError` if ``device`` is unknown or the value cannot be encoded (outside
        the DBC signal's range or bit width); the remembered values are then unchanged."""
        try:
            fr, sig = self._by_device[device]
        except KeyError:
            raise BusError(f"{device!r} is not a device of this CAN bus") from None
        values = dict(fr.values)
        values[sig] = value
        try:
            data = fr.message.encode(values, strict=True)
        except (cantools.database.EncodeError, ValueError, KeyError, OverflowError) as exc:
            raise BusError(f"cannot encode {device}={value!r} into {fr.message.name}: {exc}") \
                from exc
        fr.values = values
        return can.Message(arbitration_id=fr.message.frame_id, data=data,
                           is_extended_id=bool(fr.message.is_extended_frame))


def check_address(bus: BusSpec, device: DeviceSpec, dbc: Any) -> list[str]:
    """Errors of one device address on a ``can`` bus (``dbc`` is the loaded DBC or None)."""
    key = f"{device.key}.address"
    a = device.address
    if "message" in a or "signal" in a:
        errs = [f"{key}.{k}: unknown key in a DBC address; valid keys: {', '.join(DBC_KEYS)}"
                for k in a if k not in DBC_KEYS]
        msg_name, sig_name = a.get("message"), a.get("signal")
        if not isinstance(msg_name, str) or not isinstance(sig_name, str):
            return [*errs, f"{key}: expected message and signal names (strings), "
                           f"got {dict(a)!r}"]
        if dbc is None:
            return [*errs, f"{key}.message: a DBC address needs the bus option dbc "
                           f"({bus.key}.dbc); or use the raw form {{id, start, length}}"]
        try:
            msg = dbc.get_message_by_name(msg_name)
        except KeyError:
            names = ", ".join(m.name for m in dbc.messages)
            return [*errs, f"{key}.message: no message {msg_name!r} in {bus.options['dbc']}; "
                           f"expected one of: {names}"]
        if sig_name not in [s.name for s in msg.signals]:
            return [*errs, f"{key}.signal: no signal {sig_name!r} in message {msg_name}; "
                           f"expected one of: {', '.join(s.name for s in msg.signals)}"]
        return errs
    errs = [f"{key}.{k}: unknown key; valid keys: {', '.join(DBC_KEYS)} (DBC form) or "
            f"{', '.join(RAW_KEYS)} (raw form)" for k in a if k not in RAW_KEYS]
    if not a:
        return [f"{key}: expected {{message, signal}} (DBC) or {{id, start, length}} (raw)"]
    ext = a.get("extended", False)
    fid = a.get("id")
    if not isinstance(ext, bool):
        errs.append(f"{key}.extended: expected true or false, got {ext!r}")
    if not _int(fid) or not 0 <= fid <= (0x1FFFFFFF if ext is True else 0x7FF):
        errs.append(f"{key}.id: expected a CAN id 0..{'0x1FFFFFFF' if ext is True else '0x7FF'}"
                    f", got {fid!r}")
    dlc = a.get("dlc", 8)
    if not _int(dlc) or not 0 < dlc <= 64:
        errs.append(f"{key}.dlc: expected a frame length 1..64 bytes, got {dlc!r}")
        dlc = 8
    start, length = a.get("start"), a.get("length")
    if not _int(start) or not 0 <= start < dlc * 8:
        errs.append(f"{key}.start: expected a start bit 0..{dlc * 8 - 1}, got {start!r}")
    if not _int(length) or not 1 <= length <= 64:
        errs.append(f"{key}.length: expected a bit length 1..64, got {length!r}")
    if a.get("byte_order", "little_endian") not in BYTE_ORDERS:
        errs.append(f"{key}.byte_order: expected one of {', '.join(BYTE_ORDERS)}, "
                    f"got {a.get('byte_order')!r}")
    if not isinstance(a.get("signed", False), bool):
        errs.append(f"{key}.signed: expected true or false, got {a.get('signed')!r}")
    return errs


def bus_fileno(bus: can.BusABC) -> int | None:
    """The bus's file descriptor if its interface has one (SocketCAN), else None."""
    try:
        fd = bus.fileno()
    except (NotImplementedError, OSError, AttributeError):
        return None
    return fd if isinstance(fd, int) and fd >= 0 else None


def _readiness(rx: ReaderThread, bus: can.BusABC) -> Callable[[float], bool] | None:
    """How the reader can wait until a frame is there without taking it: ``select`` on the
    bus's file descriptor (SocketCAN), or the receive queue of python-can's ``virtual``
    interface; None for interfaces with neither (then the reader polls)."""
    fd = bus_fileno(bus)
    if fd is not None:
        return functools.partial(rx.wait_readable, fd)
    q = getattr(bus, "queue", None)
    if isinstance(q, queue.Queue):
        def wait(timeout: float) -> bool:
            with q.not_empty:   # the queue's own condition; q.queue is its deque
                return q.not_empty.wait_for(lambda: len(q.queue) > 0, timeout)
        return wait
    return None


SO_MEMINFO = 55          # Linux <asm-generic/socket.h>: the socket's memory info, u32[9]
SK_MEMINFO_DROPS = 8     # ... whose last entry is sk_drops, the frames the kernel dropped


def socket_drops(sock: Any) -> int | None:
    """How many packets the kernel dropped on ``sock`` because its receive buffer was full (the
    count ``SO_RXQ_OVFL`` reports), or None where the OS does not tell."""
    try:
        raw = sock.getsockopt(socket.SOL_SOCKET, SO_MEMINFO, 4 * (SK_MEMINFO_DROPS + 1))
    except (OSError, AttributeError, TypeError):
        return None
    if not isinstance(raw, bytes) or len(raw) < 4 * (SK_MEMINFO_DROPS + 1):
        return None
    return int(struct.unpack_from(f"={SK_MEMINFO_DROPS + 1}I", raw)[SK_MEMINFO_DROPS])


def read_frames(rx: ReaderThread, bus: can.BusABC, poll: float,
                on_frame: Callable[[can.Message], None], on_error: Callable[[str], None],
                after_drain: Callable[[], None] | None = None) -> None:
    """The read loop of a CAN driver's :class:`ReaderThread`: every frame received goes to
    ``on_frame`` (which must not raise), a receive error to ``on_error`` (then a pause of 0.1 s).
    Where it can wait for a frame without taking it (SocketCAN's file descriptor, the
    ``virtual`` interface's queue) it drains without blocking under the reader's lock, and the
    reader's settle drains itself; elsewhere it receives with timeout ``poll`` and reports empty
    receives (see :mod:`drivers.threaded`). ``after_drain`` runs after each batch drained (the
    CAN driver reads the socket's drop count there)."""
    wait = _readiness(rx, bus)
    if wait is None:
        while rx.running:
            try:
                frame = bus.recv(poll)
            except (can.CanError, OSError) as exc:
                on_error(str(exc))
                rx.pause(0.1)
                continue
            if frame is None:
                rx.idle()
            else:
                on_frame(frame)
        return

    def drain(limit: int = 0) -> bool:
        n = 0
        while limit <= 0 or n < limit:
            try:
                frame = bus.recv(0)
            except (can.CanError, OSError) as exc:
                on_error(str(exc))
                return False
            if frame is None:
                break
            n += 1
            on_frame(frame)
        return True

    rx.set_drain(drain)
    while rx.running:
        if wait(0.05):
            with rx.lock:
                ok = drain(64)
                if after_drain is not None:
                    after_drain()
            if not ok:
                rx.pause(0.1)


class CanDriver(ThreadedDriver):
    """Driver for kind ``can`` (see the module docstring for options, addresses and threads)."""

    kind = "can"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.codec = CanCodec(bus, devices)
        self._poll = float(bus.options.get("poll", 0.005))
        self._failed = False
        self._bus: can.BusABC | None = None
        self._drops_seen: int | None = None
        #: Frames the kernel dropped because the socket's receive buffer was full (SocketCAN).
        self.overrun_lost = 0
        self._recorder: Recorder | None = None
        self._write_failed: set[str] = set()
        self.received = 0
        self.sent = 0

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Unknown options, types, python-can configuration, DBC and record file."""
        o = bus.options
        errs = [f"{bus.key}.{k}: unknown option for a can bus; valid options: "
                f"{', '.join(BUS_OPTIONS)}" for k in o if k not in BUS_OPTIONS]
        if "bitrate" in o and (not _int(o["bitrate"]) or o["bitrate"] <= 0):
            errs.append(f"{bus.key}.bitrate: expected bits per second > 0, got {o['bitrate']!r}")
        if "fd" in o and not isinstance(o["fd"], bool):
            errs.append(f"{bus.key}.fd: expected true or false, got {o['fd']!r}")
        if "poll" in o and (isinstance(o["poll"], bool) or not isinstance(o["poll"], int | float)
                            or not 0 < o["poll"] <= 1):
            errs.append(f"{bus.key}.poll: expected seconds in (0, 1], got {o['poll']!r}")
        for k in ("interface", "channel"):
            if k in o and not isinstance(o[k], str | int):
                errs.append(f"{bus.key}.{k}: expected a string, got {o[k]!r}")
        try:
            bus_config(o)
        except BusError as exc:
            errs.append(f"{bus.key}.interface: expected interface and channel in the map or in "
                        f"python-can's configuration (CAN_INTERFACE / CAN_CHANNEL, can.conf); "
                        f"{exc}")
        if "dbc" in o:
            if not isinstance(o["dbc"], str):
                errs.append(f"{bus.key}.dbc: expected a DBC file path, got {o['dbc']!r}")
            else:
                try:
                    load_dbc(o["dbc"])
                except BusError as exc:
                    errs.append(f"{bus.key}.dbc: {exc}")
        rec = o.get("record")
        if rec is not None and (not isinstance(rec, str)
                                or Path(rec).suffix.lower() not in LOG_SUFFIXES):
            errs.append(f"{bus.key}.record: expected a log file ending in "
                        f"{', '.join(LOG_SUFFIXES)}, got {rec!r}")
        return errs

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """The address is a valid DBC {message, signal} or raw {id, start, length...}."""
        dbc = None
        if isinstance(bus.options.get("dbc"), str):
            try:
                dbc = checked_dbc(bus.options["dbc"])
            except BusError:
                return []          # reported once, by check_bus
        return check_address(bus, device, dbc)

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """What the signal can carry: a raw address's integer range from its length and
        signedness; a DBC signal's raw range (integer, or float32; None for float64) through
        the DBC's scale and offset, within the DBC's minimum and maximum."""
        a = device.address
        if "message" not in a:
            lo, hi = _int_range(int(a["length"]), bool(a.get("signed", False)))
            return float(lo), float(hi)
        sig = checked_dbc(str(bus.options["dbc"])).get_message_by_name(
            a["message"]).get_signal_by_name(a["signal"])
        if sig.is_float:
            if sig.length != 32:
                return None
            rlo, rhi = -3.4028234663852886e38, 3.4028234663852886e38
        else:
            ilo, ihi = _int_range(sig.length, sig.is_signed)
            rlo, rhi = float(ilo), float(ihi)
        ends = sorted((rlo * sig.scale + sig.offset, rhi * sig.scale + sig.offset))
        lo_, hi_ = ends
        if sig.minimum is not None:
            lo_ = max(lo_, float(sig.minimum))
        if sig.maximum is not None:
            hi_ = min(hi_, float(sig.maximum))
        return lo_, hi_

    def start(self) -> None:
        """Open the python-can bus (and the record file), start reader and writer threads.

        Raises :class:`BusError` if python-can cannot open the bus or the record file fails."""
        where = f"bus {self.bus.name!r} ({self.bus.file} {self.bus.key})"
        try:
            cfg = bus_config(self.bus.options)
        except BusError as exc:
            raise BusError(f"{where}: {exc}") from exc
        try:
            self._bus = can.Bus(**cfg)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"{where}: cannot open {cfg.get('interface')} channel "
                           f"{cfg.get('channel')!r}: {exc}") from exc
        if "record" in self.bus.options:
            try:
                self._recorder = Recorder(self.bus.options["record"], str(cfg.get("channel")))
            except BusError:
                self._bus.shutdown()
                raise
        self._start_threads()

    def stop(self) -> None:
        """Stop the threads, close the bus and the record file. Idempotent; never raises."""
        self._stop_threads()
        if self._bus is not None:
            with contextlib.suppress(can.CanError, OSError):
                self._bus.shutdown()
            self._bus = None
        if self._recorder is not None:
            self._recorder.stop()

    # -- threads ---------------------------------------------------------------------------

    def _read_loop(self) -> None:
        assert self._bus is not None
        sock = getattr(self._bus, "socket", None) if bus_fileno(self._bus) is not None else None
        self._drops_seen = socket_drops(sock) if sock is not None else None
        read_frames(self._rx, self._bus, self._poll, self._receive, self._bus_down,
                    functools.partial(self._check_overrun, sock) if self._drops_seen is not None
                    else None)

    def _check_overrun(self, sock: Any) -> None:
        """Report the frames the kernel dropped since the last look (reader thread)."""
        drops = socket_drops(sock)
        if drops is None or self._drops_seen is None or drops <= self._drops_seen:
            return
        lost, self._drops_seen = drops - self._drops_seen, drops
        self.overrun_lost += lost
        self._error("overrun", f"{lost} frame(s) lost on bus {self.bus.name!r}: the socket's "
                               f"receive buffer overflowed (kernel drop count {drops})")

    def _receive(self, frame: can.Message) -> None:
        self._bus_up()
        try:
            self._handle(frame)
        except Exception as exc:  # the reader must survive any host/codec surprise
            self._error("internal", f"frame handling failed: {exc!r}")

    def _handle(self, frame: can.Message) -> None:
        self.received += 1
        self.host.stat(self.bus.name, "frames")
        if self._recorder is not None:
            self._recorder.on_message_received(frame)
        if frame.is_error_frame:
            self._error("error-frame", "CAN error frame received")
            return
        status, result = self.codec.decode(frame)
        if status == "ok":
            assert isinstance(result, list)
            for device, value in result:
                self.host.deliver(device, value)
        elif status != "ignore":
            self._error(status, str(result))

    def check_value(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for ``device`` (see :meth:`CanCodec.check`)."""
        return self.codec.check(device, value)

    def _send(self, device: str, value: Any) -> None:
        assert self._bus is not None
        try:
            frame = self.codec.encode(device, value)
        except BusError as exc:    # a value that does not fit: refused, the device is fine
            self._error("range", str(exc))
            self.host.write_failed(device, value, str(exc))
            return
        try:
            self._bus.send(frame, timeout=0.5)
        except (can.CanError, OSError) as exc:
            reason = f"CAN send on bus {self.bus.name!r} failed: {exc}"
            self._error("send", reason)
            self.host.write_failed(device, value, reason)
            self._write_failed.add(device)
            self.host.fail(device, reason)
            return
        self.sent += 1
        self.host.stat(self.bus.name, "frames-sent", device=device)
        self.host.written(device, value)
        if device in self._write_failed:
            self._write_failed.discard(device)
            self.host.recover(device, "a frame was sent")
        if self._recorder is not None:
            frame.is_rx = False
            self._recorder.on_message_received(frame)

    def _bus_down(self, reason: str) -> None:
        if not self._failed:
            self._failed = True
            for name in self.devices:
                self.host.fail(name, f"CAN bus {self.bus.name!r} receive failed: {reason}")

    def _bus_up(self) -> None:
        if self._failed:
            self._failed = False
            for name in self.devices:
                self.host.recover(name, "frames received again")
