"""can_raw - the raw CAN driver (kind ``can``): python-can bus, signals coded with cantools.

Bus options:

- ``interface``, ``channel``: python-can's; when left out they come from python-can's own
  configuration (``can.util.load_config``: ``CAN_INTERFACE`` / ``CAN_CHANNEL`` environment
  variables and its config files), so one map serves ``virtual`` on a laptop and ``socketcan`` at
  the cell.
- ``bitrate`` (int > 0, optional), ``fd`` (bool, default false)
- ``port``: with ``interface = "udp_multicast"`` (python-can's bus between processes on any
  machine, ``channel`` the multicast group), the UDP port; give each bus its own group and port
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
interface has no such buffer and never overruns. Actuator writes never block the caller: each
is encoded as the whole message, keeping the other signals at their last written value or else
the DBC initial value (0 if none, clipped into the signal's range), and sent. On the interfaces of
:data:`INLINE_INTERFACES` (``virtual``, ``socketcan``), without ``record``, a write that finds
nothing queued is sent at once in the caller's thread (the kernel thread) with ``timeout=0``; if
the bus cannot take it right now (transmit buffer full, ENOBUFS) or anything is queued or being
sent, it goes to the writer thread, which waits up to :data:`SEND_TIMEOUT` (0.5 s) for room
(and tries again every millisecond while SocketCAN reports ENOBUFS, on which python-can does
not wait). Other interfaces, and buses that record, always use the writer thread. Encoding or send
failures are reported with ``host.fail(device, ...)``; the next successful write of that actuator
reports ``host.recover(device)``. Bus errors are also counted in ``CanDriver.error_counts``.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from chcos.helpers import is_int
from drivers.base import DriverHost, deliver_all
from drivers.canbus import bus_config, bus_fileno, read_frames, socket_drops
from drivers.codecs.can import (
    CanCodec,
    check_address,
    checked_dbc,
    int_range,
    load_dbc,
)
from drivers.recording import LOG_SUFFIXES, Recorder
from drivers.threaded import ThreadedDriver

BUS_OPTIONS = ("interface", "channel", "bitrate", "fd", "dbc", "record", "poll", "port")

#: Interfaces whose ``send(frame, timeout=0)`` never blocks (python-can 4: ``virtual`` puts into
#: unbounded queues, ``socketcan`` selects with a zero timeout, then sends once); their writes
#: take the fast path (sent on the kernel thread). Every other interface keeps the writer thread.
INLINE_INTERFACES = frozenset({"virtual", "socketcan"})

#: Seconds the writer thread waits for room in the transmit buffer before a send fails.
SEND_TIMEOUT = 0.5
#: Seconds between the writer thread's tries while the interface reports ENOBUFS.
ENOBUFS_RETRY = 0.001


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
        #: of :attr:`sent`, the frames the writer thread sent (the rest: the fast path)
        self.sent_queued = 0
        #: the fast path's frame per actuator (see _send_now)
        self._outgoing: dict[str, can.Message] = {}
        # the batch being received (reader thread, see _end_batch)
        self._batch: list[tuple[str, Any]] = []
        self._counted = 0       # of :attr:`received`, the frames in the bus statistics

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Unknown options, types, python-can configuration, DBC and record file."""
        o = bus.options
        errs = [f"{bus.key}.{k}: unknown option for a can bus; valid options: "
                f"{', '.join(BUS_OPTIONS)}" for k in o if k not in BUS_OPTIONS]
        if "bitrate" in o and (not is_int(o["bitrate"]) or o["bitrate"] <= 0):
            errs.append(f"{bus.key}.bitrate: expected bits per second > 0, got {o['bitrate']!r}")
        if "fd" in o and not isinstance(o["fd"], bool):
            errs.append(f"{bus.key}.fd: expected true or false, got {o['fd']!r}")
        if "poll" in o and (isinstance(o["poll"], bool) or not isinstance(o["poll"], int | float)
                            or not 0 < o["poll"] <= 1):
            errs.append(f"{bus.key}.poll: expected seconds in (0, 1], got {o['poll']!r}")
        if "port" in o and (o.get("interface") != "udp_multicast" or not is_int(o["port"])
                            or not 1 <= o["port"] <= 65535):
            errs.append(f"{bus.key}.port: the UDP port of interface \"udp_multicast\" "
                        f"(1..65535), got {o['port']!r} with interface {o.get('interface')!r}")
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
            lo, hi = int_range(int(a["length"]), bool(a.get("signed", False)))
            return float(lo), float(hi)
        sig = checked_dbc(str(bus.options["dbc"])).get_message_by_name(
            a["message"]).get_signal_by_name(a["signal"])
        if sig.is_float:
            if sig.length != 32:
                return None
            rlo, rhi = -3.4028234663852886e38, 3.4028234663852886e38
        else:
            ilo, ihi = int_range(sig.length, sig.is_signed)
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
        # no file I/O on the kernel thread: a recording bus sends from its writer thread
        self._inline = cfg.get("interface") in INLINE_INTERFACES and self._recorder is None
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
                    else None, self._end_batch)

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
        """One received frame (reader thread): counted, recorded, decoded; its readings join
        the batch :meth:`_end_batch` hands over. Never raises: what fails is an ``internal``
        error."""
        if self._failed:
            self._bus_up()
        try:
            self.received += 1
            if self._recorder is not None:
                self._recorder.on_message_received(frame)
            if frame.is_error_frame:
                self._error("error-frame", "CAN error frame received")
                return
            status, result = self.codec.decode(frame)
            if status == "ok":
                assert isinstance(result, list)
                self._batch += result
            elif status != "ignore":
                self._error(status, str(result))
        except Exception as exc:  # the reader must survive any host/codec surprise
            self._error("internal", f"frame handling failed: {exc!r}")

    def _end_batch(self) -> None:
        """The frames received together are handled (on the reader thread, or under the
        reader's lock by a settle that drains itself):
        their count goes to the bus statistics and their readings to the host as one
        interrupt, in the order received (the kernel handles every queued interrupt before the
        next task step anyway, so this changes nothing a task can see, and costs one wake-up
        and one counter update per batch instead of per frame). Errors are reported as they
        are met, not held back."""
        n = self.received - self._counted
        if n:
            self._counted = self.received
            self.host.stat(self.bus.name, "frames", n)
        if self._batch:
            batch, self._batch = self._batch, []
            deliver_all(self.host, batch)

    def check_value(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for ``device`` (see :meth:`CanCodec.check`)."""
        return self.codec.check(device, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """A raw integer signal's range (see :meth:`CanCodec.accepts`)."""
        return self.codec.accepts(device)

    def _frame(self, device: str, value: Any, report: bool = True) -> can.Message | None:
        """The frame carrying ``value`` for ``device``; None if the value does not fit (then
        refused and, with ``report``, reported: the device is fine)."""
        try:
            fid, data, ext = self.codec.encode_raw(device, value)
        except BusError as exc:
            if report:
                self._unencodable(device, value, exc)
            return None
        return can.Message(arbitration_id=fid, data=data, is_extended_id=ext)

    def _unencodable(self, device: str, value: Any, exc: BusError) -> None:
        """``value`` does not fit ``device``'s signal: counted (``range``) and the write
        reported failed (the device is fine)."""
        self._error("range", str(exc))
        self.host.write_failed(device, value, str(exc))

    def _send_now(self, device: str, value: Any, report: bool = True) -> bool:
        """Fast path (the kernel thread, see drivers.threaded): send with ``timeout=0``, which
        :data:`INLINE_INTERFACES` honour without blocking; any error there (a full transmit
        buffer, ENOBUFS, the bus closing) leaves the frame to the writer thread, which tries
        again with the usual timeout and reports what still fails."""
        bus = self._bus
        if bus is None:
            return False
        try:     # self._frame(device, value, report), inlined: once per frame sent
            fid, data, ext = self.codec.encode_raw(device, value)
        except BusError as exc:
            if report:
                self._unencodable(device, value, exc)
            return report
        # one frame object per actuator, its payload replaced by the codec's (immutable) bytes:
        # the fast path's interfaces take the frame's content during send, and only one
        # fast-path send runs at a time. python-can's virtual bus deep-copies the frame for
        # every receiver - a bytes payload is copied as the same object, a bytearray by a
        # copyreg round trip of ~300 bytecode instructions - and its Message() gives each copy
        # a bytearray again; SocketCAN packs bytes(data), which takes bytes as they are
        frame = self._outgoing.get(device)
        if frame is None:
            frame = self._outgoing[device] = can.Message(arbitration_id=fid, data=data,
                                                         is_extended_id=ext)
        frame.data = data  # type: ignore[assignment]  # private frame: see above
        try:
            bus.send(frame, 0)  # (timeout 0, positional: no keyword binding per frame)
        except (can.CanError, OSError):
            return False
        self._sent(device, value, frame, report)
        return True

    def _send(self, device: str, value: Any) -> None:
        assert self._bus is not None
        frame = self._frame(device, value)
        if frame is None:
            return
        try:
            self._send_waiting(self._bus, frame)
        except (can.CanError, OSError) as exc:
            reason = f"CAN send on bus {self.bus.name!r} failed: {exc}"
            self._error("send", reason)
            self.host.write_failed(device, value, reason)
            self._write_failed.add(device)
            self.host.fail(device, reason)
            return
        self.sent_queued += 1
        self._sent(device, value, frame)

    def _send_waiting(self, bus: can.BusABC, frame: can.Message) -> None:
        """Send ``frame``, waiting up to SEND_TIMEOUT for room (writer thread): python-can
        waits for a writable socket but gives up at once on ENOBUFS (the interface's transmit
        queue full, which SocketCAN reports instead of blocking), so that is tried again every
        millisecond until the deadline or :meth:`stop`. Raises what the last try raised."""
        deadline = time.monotonic() + SEND_TIMEOUT
        while True:
            try:
                bus.send(frame, timeout=max(0.0, deadline - time.monotonic()))
                return
            except can.CanOperationError as exc:
                if exc.error_code != errno.ENOBUFS or time.monotonic() >= deadline:
                    raise
            with self._cond:
                if self._cond.wait_for(lambda: not self._running, ENOBUFS_RETRY):
                    raise can.CanOperationError(f"bus {self.bus.name!r} stopped while its "
                                                f"transmit queue was full", errno.ENOBUFS)

    def _sent(self, device: str, value: Any, frame: can.Message, report: bool = True) -> None:
        """``frame`` is on the wire: count (:attr:`sent_frames`, pulled into the bus statistics:
        no lock or host call per frame), confirm (``report``), recover, record."""
        self.sent_frames[device] += 1
        if report:
            self.host.written(device, value)
        if device in self._write_failed:
            self._write_failed.discard(device)
            self.host.recover(device, "a frame was sent")
        if self._recorder is not None:
            frame.is_rx = False
            self._recorder.on_message_received(frame)

    @property
    def sent(self) -> int:
        """Frames sent, all actuators together."""
        return sum(self.sent_frames.values())

    @property
    def sent_inline(self) -> int:
        """Of :attr:`sent`, the frames sent on the fast path (in the caller's thread)."""
        return self.sent - self.sent_queued

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
