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
- ``record``: a log file (``.log``/``.asc``/``.blf``...) receiving every frame received (with
  ``filter``, only the map's ids) and sent
- ``poll``: the reader's receive timeout in seconds (default 0.005) on interfaces it cannot wait
  on without receiving; it bounds :meth:`settle` there. On SocketCAN (``select`` on the socket)
  and python-can's ``virtual`` interface (its receive queue) the reader sleeps until a frame is
  there and :meth:`settle` drains the bus itself, so ``poll`` is not used
- ``filter`` (bool, default true): open the bus with receive filters on the ids of the messages
  that carry a sensor signal, less ``ignore_ids`` (:func:`drivers.canbus.can_filters`; on
  SocketCAN in the kernel): frames of other ids never reach chcos
- ``ignore_ids``: ids and ranges (``["0x700-0x77F", 0x80]``) another node owns: never warned
  about, counted as ``ignored-id``
- ``unknown_ids``: ``ignore`` | ``warn`` (default) | ``fail``, see :class:`UnknownIds`
- ``message``: ``[[bus.message]]`` tables, one per DBC message that needs more than the DBC says
  (:mod:`drivers.codecs.can_e2e`): ``cycle_time`` (default the DBC's ``GenMsgCycleTime``),
  ``counter``, ``checksum``; ``counter``, ``crc``, ``checksum`` as a bus option or address key
  are refused, naming where they belong
- ``interface = "chcos-direct"``: the in-process direct bus of virtual time
  (:mod:`drivers.can_direct`), which a virtual cell's simulated ECU is on; the driver then runs
  in the synchronous mode of :mod:`drivers.threaded` (no thread: frames handled inside the
  peer's send, commands sent in the caller's thread, probes on the kernel clock)

Device addresses, one of two forms:

- DBC: ``{ message = "Temps", signal = "T1" }`` (names from the DBC file)
- raw: ``{ id = 0x101, start = 0, length = 16, byte_order = "little_endian", signed = false,
  dlc = 8, extended = false }`` (``start`` is the DBC start bit; ``byte_order``, ``signed``,
  ``dlc``, ``extended`` are optional with these defaults). Raw signals are unscaled integers.
  Raw devices that share an id form one message and must agree on ``dlc`` and ``extended``.

Received frames are decoded on the reader thread: a frame of a sensor message is decoded and every
sensor signal in it delivered (of a multiplexed message, the signals its multiplexer selects; a
multiplexer value the DBC does not list is counted as ``unknown-mux``); a frame whose id carries
only actuator signals is ignored (another node, or a replayed log, sends it); a frame of any other
id is counted (``unknown-id``, or ``ignored-id`` for ``ignore_ids``) and handled by
``unknown_ids``: reported once per :data:`REPORT_PERIOD` with the count, as a warning or (``fail``)
a bus error. A frame of the wrong length is ``host.error(bus, "wrong-length")``, one cantools
cannot decode ``"undecodable"``; either fails its message's sensors after :data:`BAD_FRAMES` in a
row (at the first if the message never had a well-formed frame) until a well-formed one comes.
A frame whose declared checksum or rolling counter is wrong is ``"checksum"`` / ``"counter"``,
not delivered, and fails its message's sensors after :data:`BAD_FRAMES` in a row the same way.
An error frame (SocketCAN's ``CAN_ERR_FLAG`` frames, or the direct bus's alike) is
``"error-frame"`` and tells the controller's state (:mod:`drivers.codecs.can_errors`, shown in
:meth:`CanDriver.status`): error-passive is an ``"error-passive"`` bus error, bus-off
(``"bus-off"``) fails every device of the bus until the restart (actuators then, sensors with
their next frame). A remote frame (a data request, which chcos does not answer) is
``"remote-frame"``. On a real-time kernel clock, on the interfaces of :data:`WALL_STAMPED`, each
reading carries its frame's receive time (the kernel's stamp on SocketCAN,
:func:`drivers.canbus.receive_time`) to the host, and a reading older than its sensor's
``stale_after`` on arrival is counted (``stale-on-arrival``) and not delivered.
On SocketCAN, frames the kernel dropped because the socket's receive buffer was full are
counted as ``lost`` in the bus counts and reported as ``"overrun"`` errors with the number lost
(the socket's drop count, read with ``SO_MEMINFO``: the count ``SO_RXQ_OVFL`` reports, which
python-can's receive does not ask for), also summed in ``CanDriver.overrun_lost``; the first
overrun is reported at once, later ones once per :data:`REPORT_PERIOD` with their sum;
python-can's ``virtual`` interface has no such buffer and never overruns. See docs/can-faults.md.

Actuator writes never block the caller: each
is encoded as the whole message, keeping the other signals at their last written value or else
the DBC initial value (0 if none, clipped into the signal's range), and sent. On the interfaces of
:data:`INLINE_INTERFACES` (``virtual``, ``socketcan``), without ``record``, a write that finds
nothing queued is sent at once in the caller's thread (the kernel thread) with ``timeout=0``; if
the bus cannot take it right now (transmit buffer full, ENOBUFS) or anything is queued or being
sent, it goes to the writer thread, which waits up to :data:`SEND_TIMEOUT` (0.5 s) for room
(and tries again every millisecond while SocketCAN reports ENOBUFS, on which python-can does
not wait). Other interfaces, and buses that record, always use the writer thread. A value that
cannot be encoded is reported as a failed write (the device is fine). A frame that cannot be sent
(the transmit queue still full after SEND_TIMEOUT, the bus error-passive or off, the interface
down) is a failed write and fails the actuator (``host.fail``); nothing latches: the driver then
tries the link again itself (:mod:`drivers.sendprobe`: the actuator's last value sent, else its
safe value, backing off over :data:`PROBE_BACKOFF`), and the first frame that
goes out on the bus, probe or command of any actuator, reports ``host.recover`` for every
actuator failed by a send. Bus errors are also counted in
``CanDriver.error_counts``.

A message with actuators and a cycle time is chcos' own cyclic message (:mod:`drivers.can_cyclic`):
a command goes to its cycle, which repeats the last one every period (on kernel timers under a
virtual clock, else through python-can's ``send_periodic``: the broadcast manager on SocketCAN);
every frame sent carries its message's counter and checksum.
"""

from __future__ import annotations

import contextlib
import enum
import errno
import functools
import logging
import re
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import can

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.devices.status import CyclicStatus, DriverStatus
from chcos.errors import BusError
from chcos.helpers import is_int
from drivers.base import DriverHost, deliver_all, host_clock_virtual
from drivers.can_cyclic import ClockedCycle, Cycle, PeriodicCycle
from drivers.can_direct import INTERFACE as DIRECT_INTERFACE
from drivers.can_direct import DirectBus
from drivers.canbus import (
    SocketcanReceive,
    StampClock,
    Tally,
    bus_config,
    bus_fileno,
    can_filters,
    in_ranges,
    parse_ids,
    read_frames,
    socket_drops,
)
from drivers.codecs.can import (
    CanCodec,
    Decoded,
    FrameFault,
    Ignored,
    Rejected,
    check_address,
    checked_dbc,
    int_range,
    limits_beyond,
    load_dbc,
)
from drivers.codecs.can_e2e import cycle_of, parse_messages
from drivers.codecs.can_errors import ControllerState, ControllerStatus, decode_error_frame
from drivers.recording import LOG_SUFFIXES, Recorder
from drivers.sendprobe import ClockedSendProbe, SendProbe, safe_raw
from drivers.threaded import ThreadedDriver

BUS_OPTIONS = ("interface", "channel", "bitrate", "fd", "dbc", "record", "poll", "filter",
               "ignore_ids", "unknown_ids", "port", "message")
#: Bus keys that would declare counters or checksums: refused by ``check`` with the reason.
REFUSED_OPTIONS = ("counter", "crc", "checksum")

log = logging.getLogger("chcos.drivers.can")


#: Signal names that usually are a rolling counter or a checksum (opendbc's, AUTOSAR's).
_LOOKS_PROTECTED = re.compile(r"(?i)(counter|checksum|chksum|crc|alive|rolling)")


def _dbc_message(bus: BusSpec, device: DeviceSpec) -> Any:
    """The DBC message of a valid ``{message, signal}`` device, or None (raw form, no DBC)."""
    if "message" not in device.address or not isinstance(bus.options.get("dbc"), str):
        return None
    try:
        return checked_dbc(bus.options["dbc"]).get_message_by_name(device.address["message"])
    except (BusError, KeyError):
        return None


class UnknownIds(enum.Enum):
    """What a frame with an id of no device does (bus option ``unknown_ids``)."""

    IGNORE = "ignore"   # counted (``unknown-id`` in the bus counts) only
    WARN = "warn"       # counted, and one aggregated warning per period
    FAIL = "fail"       # counted, and one bus error per period: the run is unhealthy


#: Malformed frames of a message in a row (wrong length, undecodable) that fail its sensors;
#: a message that never had a well-formed frame fails them at the first.
BAD_FRAMES = 3
#: Seconds between two aggregated reports of unknown ids (wall time).
REPORT_PERIOD = 10.0
#: Frames received further apart than this (seconds) go to the host as separate deliveries,
#: each with its own receive time; closer ones share the oldest one's.
AT_SPREAD = 0.001

#: Interfaces whose ``send(frame, timeout=0)`` never blocks (python-can 4: ``virtual`` puts into
#: unbounded queues, ``socketcan`` selects with a zero timeout, then sends once); their writes
#: take the fast path (sent on the kernel thread). Every other interface keeps the writer thread.
INLINE_INTERFACES = frozenset({"virtual", "socketcan"})

#: Interfaces whose ``Message.timestamp`` is wall-clock time (``time.time()``'s epoch): on
#: SocketCAN the kernel's receive stamp, on ``virtual`` the sender's. Elsewhere (hardware time
#: stamps with their own epoch) readings are stamped when the driver takes them.
WALL_STAMPED = frozenset({"socketcan", "virtual"})

#: Frames taken in one batch from which the reader asks the socket for its drop count even
#: when the frames' own count did not grow (see ``CanDriver._check_overrun``).
BACKLOG = 32

#: Seconds the writer thread waits for room in the transmit buffer before a send fails.
SEND_TIMEOUT = 0.5
#: Seconds between the writer thread's tries while the interface reports ENOBUFS.
ENOBUFS_RETRY = 0.001
#: Seconds between two probes of an actuator whose frame could not be sent: the first pause,
#: doubled after each failed probe up to the second (see drivers.sendprobe)
PROBE_BACKOFF = (0.05, 1.0)


class CanDriver(ThreadedDriver):
    """Driver for kind ``can`` (see the module docstring for options, addresses and threads)."""

    kind = "can"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self.codec = CanCodec(bus, devices)
        o = bus.options
        self._poll = float(o.get("poll", 0.005))
        self._filter = bool(o.get("filter", True))
        self._ignore, _ = parse_ids(o.get("ignore_ids", []), f"{bus.key}.ignore_ids")
        self._unknown = UnknownIds(o.get("unknown_ids", "warn"))
        self._tally = Tally(self._report_unknown, REPORT_PERIOD)
        self._overruns = Tally(self._report_overrun, REPORT_PERIOD, examples=1)
        self._virtual: bool | None = None
        self._stamps = StampClock(host.now)
        self._stale_after = {d.name: d.stale_after for d in devices
                             if d.direction == "sensor" and d.stale_after is not None}
        #: the filters the bus was opened with (None: every frame is received)
        self.filters: list[Any] | None = None
        #: frames whose readings were older than their sensor's stale_after when received
        #: (not delivered), per device
        self.stale_on_arrival: Counter[str] = Counter()
        #: frames of ids no device uses, and of ids in ignore_ids, that reached the driver
        self.unknown_ids = 0
        self.ignored_ids = 0
        # malformed frames: in a row per message; messages with a good frame; failed messages
        self._bad: dict[tuple[int, bool], int] = {}
        self._good_seen: set[tuple[int, bool]] = set()
        self._bad_failed: set[tuple[int, bool]] = set()
        self._pending_stats: Counter[tuple[str, str]] = Counter()
        self._batch_at: float | None = None
        self._failed = False
        self._bus: can.BusABC | None = None
        self._drops_seen: int | None = None
        #: Frames the kernel dropped because the socket's receive buffer was full (SocketCAN).
        self.overrun_lost = 0
        self._recorder: Recorder | None = None
        #: the last raw value of each actuator that went out (what the peer holds)
        self._last_sent: dict[str, Any] = {}
        #: the actuators whose frame could not be sent, tried again by the driver itself
        self.probe = SendProbe(f"{self.kind}-{bus.name}", self._probe_send, PROBE_BACKOFF)
        self.received = 0
        self._taken_at_check = 0   # :attr:`received` at the last look for overruns
        #: of :attr:`sent`, the frames the writer thread sent (the rest: the fast path)
        self.sent_queued = 0
        #: the fast path's frame per actuator (see _send_now)
        self._outgoing: dict[str, can.Message] = {}
        # the batch being received (reader thread, see _end_batch)
        self._batch: list[tuple[str, Any]] = []
        #: the messages chcos sends cyclically, by (id, extended): their period, the actuator
        #: their frames count under; their cycles from their first command on
        self._cyclic: dict[tuple[int, bool], float] = {}
        self._cyclic_owner: dict[tuple[int, bool], str] = {}
        for d in devices:
            if d.direction == "actuator":
                key = self.codec.key_of(d.name)
                period = self.codec.cycle(*key)
                if period is not None:
                    self._cyclic[key] = period
                    self._cyclic_owner.setdefault(key, d.name)
        self._cycles_any = bool(self._cyclic)
        self._cycles: dict[tuple[int, bool], Cycle] = {}
        self._cycle_down: set[tuple[int, bool]] = set()
        self._clocked = False       # the host's clock is virtual: cycles on kernel timers
        #: the controller's state as its error frames tell it
        self.controller = ControllerStatus()
        self._counted = 0       # of :attr:`received`, the frames in the bus statistics

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Unknown options, types, python-can configuration, DBC and record file."""
        o = bus.options
        errs = [f"{bus.key}.{k}: unknown option for a can bus; valid options: "
                f"{', '.join(BUS_OPTIONS)}" for k in o
                if k not in BUS_OPTIONS and k not in REFUSED_OPTIONS]
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
        errs += [f"{bus.key}.{k}: unknown option for a can bus: a rolling counter or a checksum "
                 f"is declared per message, in a [[bus.message]] table (name, counter, "
                 f"checksum = {{ signal, algorithm }})" for k in REFUSED_OPTIONS if k in o]
        if "message" in o:
            if not isinstance(o.get("dbc"), str):
                errs.append(f"{bus.key}.message: [[bus.message]] describes DBC messages; the "
                            f"bus needs the option dbc")
            else:
                try:
                    dbc = checked_dbc(o["dbc"])
                except BusError:
                    dbc = None            # reported above
                if dbc is not None:
                    errs += parse_messages(o, bus.key, dbc)[1]
        if "filter" in o and not isinstance(o["filter"], bool):
            errs.append(f"{bus.key}.filter: expected true or false, got {o['filter']!r}")
        if "ignore_ids" in o:
            errs += parse_ids(o["ignore_ids"], f"{bus.key}.ignore_ids")[1]
        if "unknown_ids" in o and o["unknown_ids"] not in [u.value for u in UnknownIds]:
            errs.append(f"{bus.key}.unknown_ids: expected one of "
                        f"{', '.join(u.value for u in UnknownIds)}, got {o['unknown_ids']!r}")
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
    def check_devices(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[
            tuple[DeviceSpec, str]]:
        """A device whose message id is in the bus's ``ignore_ids``."""
        ranges, bad = parse_ids(bus.options.get("ignore_ids", []), f"{bus.key}.ignore_ids")
        if bad or not ranges:
            return []
        dbc = None
        if isinstance(bus.options.get("dbc"), str):
            try:
                dbc = checked_dbc(bus.options["dbc"])
            except BusError:
                return []
        out = []
        for d in devices:
            a = d.address
            try:
                if "message" in a:
                    if dbc is None:
                        continue           # reported by check_device
                    fid = int(dbc.get_message_by_name(a["message"]).frame_id)
                else:
                    fid = int(a["id"])
            except (KeyError, AttributeError, TypeError, ValueError):
                continue                   # reported by check_device
            if in_ranges(fid, ranges):
                out.append((d, f"{d.key}.address: id 0x{fid:X} is in {bus.key}.ignore_ids: "
                               f"the device's frames would be ignored"))
        return out

    @classmethod
    def poll_period(cls, bus: BusSpec, device: DeviceSpec) -> float | None:
        """A DBC sensor's message cycle (the map's cycle_time, else the DBC's): ``chcos check``
        warns when ``stale_after`` is shorter. None for raw and event-driven messages."""
        msg = _dbc_message(bus, device)
        if msg is None:
            return None
        return cycle_of(parse_messages(bus.options, bus.key, None)[0].get(msg.name), msg)

    @classmethod
    def check_warnings(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[str]:
        """Sensor messages with no cycle time whose sensors have no ``stale_after`` (silence
        never makes them stale), sensor signals whose DBC limits reach past what their bits
        carry, and signals of a message chcos sends that look like a counter or checksum the
        map does not declare."""
        specs = parse_messages(bus.options, bus.key, None)[0]
        out: list[str] = []
        quiet: dict[str, list[str]] = {}
        sent: set[str] = set()
        for d in devices:
            msg = _dbc_message(bus, d)
            if msg is None:
                continue
            if d.direction == "actuator":
                sent.add(msg.name)
                continue
            if cycle_of(specs.get(msg.name), msg) is None and d.stale_after is None:
                quiet.setdefault(msg.name, []).append(d.name)
            beyond = limits_beyond(msg.get_signal_by_name(d.address["signal"]))
            if beyond:
                out.append(f"{d.key}.address.signal: {beyond}: a reading there cannot come")
        out += [f"message: {name} has no cycle time (GenMsgCycleTime, or cycle_time in "
                f"[[bus.message]]) and its sensor(s) {', '.join(devs)} no stale_after: a silent "
                f"sender never makes them stale" for name, devs in quiet.items()]
        for name in sorted(sent):
            spec = specs.get(name)
            declared = {spec.counter, spec.checksum and spec.checksum.signal} if spec else set()
            for sig in checked_dbc(str(bus.options["dbc"])).get_message_by_name(name).signals:
                if sig.name not in declared and _LOOKS_PROTECTED.search(sig.name):
                    out.append(f"message: {name}.{sig.name} looks like a rolling counter or "
                               f"checksum; undeclared, chcos sends it unchanged, which a "
                               f"receiver checking it rejects (declare it in [[bus.message]])")
        return out

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
        # receive times only where the frame's stamp is known to be wall-clock time
        virtual = host_clock_virtual(self.host)
        self._virtual = virtual if cfg.get("interface") in WALL_STAMPED else None
        if self._filter:
            ids = [(i, e) for i, e in self.codec.sensor_ids() if not in_ranges(i, self._ignore)]
            self.filters = cfg["can_filters"] = can_filters(
                [i for i, e in ids if not e], [i for i, e in ids if e])
        self._synchronous = cfg.get("interface") == DIRECT_INTERFACE
        self._clocked = virtual is True
        if self._clocked:    # the reports' periods on the kernel clock too
            self._tally.now = self._overruns.now = self.host.now
        try:
            self._bus = can.Bus(**cfg)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"{where}: cannot open {cfg.get('interface')} channel "
                           f"{cfg.get('channel')!r}: {exc}") from exc
        if isinstance(self._bus, DirectBus):   # the direct hand-off: frames come to _direct
            self._bus.set_receiver(self._direct)
            self.probe = ClockedSendProbe(f"{self.kind}-{self.bus.name}", self._probe_send,
                                          PROBE_BACKOFF, self.host.at, self.host.now)
        if "record" in self.bus.options:
            try:
                self._recorder = Recorder(self.bus.options["record"], str(cfg.get("channel")))
            except BusError:
                self._bus.shutdown()
                raise
        # no file I/O on the kernel thread: a recording bus sends from its writer thread (but
        # the direct bus has no other thread: a recording one records there)
        self._inline = self._synchronous or (cfg.get("interface") in INLINE_INTERFACES
                                             and self._recorder is None)
        self._start_threads()

    def stop(self) -> None:
        """Stop the threads, close the bus and the record file, report what the aggregated
        warnings still count. Idempotent; never raises."""
        self.probe.stop()
        for cycle in self._cycles.values():
            cycle.stop()
        self._stop_threads()
        self._tally.flush()
        self._overruns.flush()
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
        receiver = SocketcanReceive(self._bus) if SocketcanReceive.usable(self._bus) else None
        read_frames(self._rx, self._bus, self._poll, self._receive, self._bus_down,
                    functools.partial(self._check_overrun, sock, receiver)
                    if self._drops_seen is not None else None, self._end_batch, receiver)
        if self._drops_seen is not None:       # what was dropped after the last frame taken
            self._check_overrun(sock, None)

    def _check_overrun(self, sock: Any, receiver: SocketcanReceive | None) -> None:
        """Report the frames the kernel dropped since the last look (reader thread). With a
        ``receiver`` the count the last frame carried tells, and the socket is asked only when
        that count grew or the batch was long (:data:`BACKLOG`: the socket had backed up, the
        only time it drops; frames dropped after the last one queued show only there), so
        frames that come one by one cost no extra call; without one, the socket is asked."""
        taken, self._taken_at_check = self.received - self._taken_at_check, self.received
        drops = receiver.drops if receiver is not None else None
        if drops is None or taken >= BACKLOG or (self._drops_seen is not None
                                                and drops > self._drops_seen):
            drops = socket_drops(sock)
        if drops is None or self._drops_seen is None or drops <= self._drops_seen:
            return
        lost, self._drops_seen = drops - self._drops_seen, drops
        self.overrun_lost += lost
        self.host.stat(self.bus.name, "lost", lost)
        self._overruns.add("overrun", f"kernel drop count {drops}", lost)

    def _report_overrun(self, kind: str, n: int, examples: list[str]) -> None:
        """One aggregated report of frames the kernel dropped (a bus error)."""
        self._error(kind, f"{n} frame(s) lost on bus {self.bus.name!r}: the socket's receive "
                          f"buffer overflowed ({examples[-1] if examples else 'no drop count'})")

    def _direct(self, frame: can.Message) -> None:
        """A frame from the direct bus (the sender's thread: the kernel's): handled as the
        reader would, and handed over at once."""
        self._receive(frame)
        self._end_batch()

    def _controller(self, frame: can.Message) -> None:
        """An error frame (SocketCAN's, or the direct bus's alike): counted (``error-frame``),
        and the state it tells taken: entering error-passive is a bus error
        (``error-passive``); bus-off fails every device of the bus with that reason
        (``bus-off``); the restart out of it recovers the actuators (the device table then
        writes their safe values first) and the sensors with their next frame."""
        report = decode_error_frame(frame.arbitration_id, bytes(frame.data))
        self._error("error-frame", f"CAN error frame: {report.what}")
        was = self.controller.state
        new = self.controller.take(report)
        if new is None:
            return
        self.host.stat(self.bus.name, f"controller-{new.value}")
        if new is ControllerState.BUS_OFF:
            self._error("bus-off", f"the controller is bus-off ({report.what})")
            self._off_bus(f"CAN bus {self.bus.name!r} is bus-off ({report.what})")
        elif new is ControllerState.ERROR_PASSIVE:
            self._error("error-passive", f"the controller is error-passive ({report.what})")
        elif was is ControllerState.BUS_OFF:
            self._on_bus_again(f"the controller restarted ({report.what})")

    def _off_bus(self, reason: str) -> None:
        """The controller is off the bus: every device fails with ``reason``; nothing is
        probed (no frame can go out until the restart)."""
        self._failed = True
        if self._batch:
            self._end_batch()
        for name in self.devices:
            self.host.fail(name, reason)

    def _on_bus_again(self, why: str) -> None:
        """The controller is back on the bus: the actuators recover now (what failed them was
        the bus), the sensors with their next frame (:meth:`_bus_up`)."""
        self.probe.clear()
        for name, spec in self.devices.items():
            if spec.direction == "actuator":
                self.host.recover(name, why)
        for fid, ext in self.codec.sensor_ids():
            self.codec.reset_counter(fid, ext)   # the senders' counters went on meanwhile

    def status(self) -> DriverStatus:
        """The controller's state (``bus_state``: error-active / error-warning / error-passive
        / bus-off, the TX and RX error counters its last error frame gave, error frames,
        error-passive and bus-off episodes, restarts) and chcos' cyclic messages (``cyclic``:
        message, period, started, frames sent by a clocked cycle)."""
        cyclic = tuple(CyclicStatus(self.codec.message_name(*key), period, key in self._cycles,
                                    getattr(self._cycles.get(key), "sent", None))
                       for key, period in self._cyclic.items())
        return DriverStatus(bus_state=self.controller.as_state(), cyclic=cyclic)

    def _receive(self, frame: can.Message) -> None:
        """One received frame (reader thread): counted, recorded, decoded; its readings join
        the batch :meth:`_end_batch` hands over. An error frame tells the controller's state
        (:meth:`_controller`). Never raises: what fails is an ``internal`` error."""
        try:
            self.received += 1
            if self._recorder is not None:
                self._recorder.on_message_received(frame)
            if frame.is_error_frame:
                self._controller(frame)
                return
            if self._failed:
                if self.controller.on_bus():     # bus-off, and no restart frame was seen
                    self._on_bus_again("a frame was received after bus-off")
                self._bus_up()
            match self.codec.decode(frame):
                case Decoded(readings):
                    key = (frame.arbitration_id, bool(frame.is_extended_id))
                    if key not in self._good_seen or self._bad:
                        self._well_formed(key)
                    if readings:
                        self._add(readings, frame)
                case Rejected(FrameFault.UNKNOWN_ID):
                    self._unknown_id(frame)
                case Rejected(FrameFault.UNKNOWN_MUX):
                    self._pending_stats[FrameFault.UNKNOWN_MUX.value, ""] += 1
                case Rejected(FrameFault.WRONG_LENGTH | FrameFault.UNDECODABLE
                              | FrameFault.CHECKSUM | FrameFault.COUNTER as fault, detail):
                    key = (frame.arbitration_id, bool(frame.is_extended_id))
                    self._error(fault.value, detail)
                    for dev in self.codec.sensors_of(*key):
                        self._pending_stats[f"rejected-{fault.value}", dev] += 1
                    self._malformed(key, fault.value, detail)
                case Rejected(fault, detail):
                    self._error(fault.value, detail)
                case Ignored():
                    pass
        except Exception as exc:  # the reader must survive any host/codec surprise
            self._error("internal", f"frame handling failed: {exc!r}")

    def _add(self, readings: list[tuple[str, Any]], frame: can.Message) -> None:
        """Readings of one frame join the batch (reader thread). On a real kernel clock each
        is judged by the frame's receive time stamp: a reading older than its sensor's
        ``stale_after`` is counted (``stale-on-arrival``) and not delivered; frames received
        more than :data:`AT_SPREAD` apart are delivered separately, each batch with its oldest
        receive time."""
        at: float | None = None
        if self._virtual is False:
            at, age = self._stamps.place(frame.timestamp)
            stale = self._stale_after
            if stale and any(age > stale.get(dev, age) for dev, _ in readings):
                for dev, _ in readings:
                    if age > stale.get(dev, age):
                        self.stale_on_arrival[dev] += 1
                        self._pending_stats["stale-on-arrival", dev] += 1
                readings = [(d, v) for d, v in readings if not age > stale.get(d, age)]
                if not readings:
                    return
            if self._batch and (self._batch_at is None or at - self._batch_at > AT_SPREAD):
                self._end_batch()
        if not self._batch:
            self._batch_at = at
        self._batch += readings

    def _unknown_id(self, frame: can.Message) -> None:
        """A frame with an id of no device (reader thread): in ``ignore_ids`` only counted
        (``ignored-id``), else counted (``unknown-id``) and handled by ``unknown_ids``."""
        fid = frame.arbitration_id
        if self._ignore and in_ranges(fid, self._ignore):
            self.ignored_ids += 1
            self._pending_stats["ignored-id", ""] += 1
            return
        self.unknown_ids += 1
        self._pending_stats["unknown-id", ""] += 1
        if self._unknown is not UnknownIds.IGNORE:
            self._tally.add("unknown-id", f"0x{fid:X}")

    def _report_unknown(self, kind: str, n: int, examples: list[str]) -> None:
        """One aggregated report of ids of no device (see :class:`drivers.canbus.Tally`): a
        warning, or with ``unknown_ids = "fail"`` a bus error."""
        text = (f"{n} frame(s) with an id of no device ({', '.join(examples)}"
                f"{', ...' if n > len(examples) else ''}) since the last report; name them "
                f"in {self.bus.key}.ignore_ids if another node owns them")
        if self._unknown is UnknownIds.FAIL:
            self._error(kind, text)
        else:
            log.warning("bus %s: %s: %s", self.bus.name, kind, text)

    def _malformed(self, key: tuple[int, bool], kind: str, detail: str) -> None:
        """A malformed frame of a sensor message (reader thread): after :data:`BAD_FRAMES` in a
        row, or at the first if the message never had a well-formed frame, its sensors fail
        (their readings of earlier frames are handed over first)."""
        n = self._bad[key] = self._bad.get(key, 0) + 1
        if key in self._bad_failed or (n < BAD_FRAMES and key in self._good_seen):
            return
        sensors = self.codec.sensors_of(*key)
        if any(dev in sensors for dev, _ in self._batch):
            self._end_batch()              # their earlier readings go before the failure
        self._bad_failed.add(key)
        name = self.codec.message_name(*key)
        why = (f"{n} malformed frame(s) of {name} in a row" if key in self._good_seen
               else f"only malformed frames of {name} received")
        for dev in sensors:
            self.host.fail(dev, f"CAN bus {self.bus.name!r}: {why} (last: {kind}: {detail})")

    def _well_formed(self, key: tuple[int, bool]) -> None:
        """A well-formed frame of a sensor message: its malformed count restarts, and sensors
        its malformed frames failed recover."""
        self._good_seen.add(key)
        self._bad.pop(key, None)
        if key in self._bad_failed:
            self._bad_failed.discard(key)
            for dev in self.codec.sensors_of(*key):
                self.host.recover(dev, f"a well-formed frame of {self.codec.message_name(*key)}"
                                       f" received")

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
        if self._pending_stats:
            pending, self._pending_stats = self._pending_stats, Counter()
            for (key, dev), k in pending.items():
                self.host.stat(self.bus.name, key, k, dev)
        if self._batch:
            batch, self._batch = self._batch, []
            deliver_all(self.host, batch, at=self._batch_at)

    def check_value(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for ``device`` (see :meth:`CanCodec.check`)."""
        return self.codec.check(device, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """A raw integer signal's range (see :meth:`CanCodec.accepts`)."""
        return self.codec.accepts(device)

    def _unencodable(self, device: str, value: Any, exc: BusError) -> None:
        """``value`` does not fit ``device``'s signal: counted (``range``) and the write
        reported failed (the device is fine)."""
        self._error("range", str(exc))
        self.host.write_failed(device, value, str(exc))

    def _send_now(self, device: str, value: Any, report: bool = True) -> bool:
        """Fast path (the kernel thread, see drivers.threaded): send with ``timeout=0``, which
        :data:`INLINE_INTERFACES` honour without blocking; any error there (a full transmit
        buffer, ENOBUFS, the bus closing) leaves the frame to the writer thread, which tries
        again with the usual timeout and reports what still fails. A command of a cyclic
        message goes to its cycle instead (:meth:`_to_cycle`)."""
        bus = self._bus
        if bus is None:
            return False
        try:     # as _frame, but the frame object is the actuator's own (below)
            fid, data, ext = self.codec.encode_raw(device, value)
        except BusError as exc:
            if report:
                self._unencodable(device, value, exc)
            return report
        if self._cycles_any and (fid, ext) in self._cyclic:
            return self._to_cycle(device, value, (fid, ext), data, report)
        data = self.codec.stamp(fid, ext, data)
        # one frame object per actuator, its payload replaced by the codec's (immutable) bytes:
        # the fast path's interfaces take the frame's content during send, and only one
        # fast-path send runs at a time. python-can's virtual bus deep-copies the frame for
        # every receiver - a bytes payload is copied as the same object, a bytearray by a
        # copyreg round trip - and its Message() gives each copy a bytearray again; SocketCAN
        # packs bytes(data), which takes bytes as they are; the direct bus's receivers take
        # it during the send and keep nothing
        frame = self._outgoing.get(device)
        if frame is None:
            frame = self._outgoing[device] = can.Message(arbitration_id=fid, data=data,
                                                         is_extended_id=ext)
        frame.data = data  # type: ignore[assignment]  # private frame: see above
        try:
            bus.send(frame, 0)  # timeout 0: never blocks (see INLINE_INTERFACES)
        except (can.CanError, OSError) as exc:
            if self._synchronous and report:   # no writer thread to try again: failed now
                self._send_failure(device, value, exc)
                return True
            return False
        self._sent(device, value, frame, report)
        return True

    def _send_direct(self, device: str, value: Any) -> None:
        """Synchronous mode (the direct bus): the fast path reports every outcome itself."""
        self._send_now(device, value)

    def _send(self, device: str, value: Any) -> None:
        assert self._bus is not None
        try:
            fid, data, ext = self.codec.encode_raw(device, value)
        except BusError as exc:
            self._unencodable(device, value, exc)
            return
        if (fid, ext) in self._cyclic:
            self._to_cycle(device, value, (fid, ext), data, True)
            return
        frame = can.Message(arbitration_id=fid, data=self.codec.stamp(fid, ext, data),
                            is_extended_id=ext)
        try:
            self._send_waiting(self._bus, frame)
        except (can.CanError, OSError) as exc:
            self._send_failure(device, value, exc)
            return
        self.sent_queued += 1
        self._sent(device, value, frame)

    def _send_failure(self, device: str, value: Any, exc: Exception) -> None:
        """A command's frame could not be sent: reported, the actuator failed and probed."""
        reason = f"CAN send on bus {self.bus.name!r} failed: {exc}"
        self._error("send", reason)
        self.host.write_failed(device, value, reason)
        self.host.fail(device, reason)
        self._send_failed(device)

    # -- cyclic messages (drivers.can_cyclic) ----------------------------------------------

    def _to_cycle(self, device: str, value: Any, key: tuple[int, bool], data: bytes,
                  report: bool) -> bool:
        """A command of a cyclic message: the message's cycle holds the new payload (started
        by its first command, sending a frame at once) and sends it with every frame from now
        on; confirmed (``report``) once the cycle holds it. False, nothing done, if the cycle
        cannot take it (then the caller reports the failure)."""
        cycle = self._cycles.get(key)
        try:
            if cycle is None:
                cycle = self._cycles[key] = self._new_cycle(key)
            cycle.update(data)
        except (can.CanError, OSError, ValueError) as exc:
            if report:
                self._send_failure(device, value, exc)
                return True
            return False
        self._last_sent[device] = value
        if report:
            self.host.written(device, value)
        return True

    def _new_cycle(self, key: tuple[int, bool]) -> Cycle:
        """The cycle of message ``key``: on kernel timers when the host's clock is virtual,
        else python-can's periodic sender of the interface (see drivers.can_cyclic)."""
        period = self._cyclic[key]
        assert self._bus is not None
        if self._clocked:
            return ClockedCycle(period, functools.partial(self._cycle_frame, key),
                                self.host.at, self.host.now,
                                lambda: self.controller.state is ControllerState.BUS_OFF)
        return PeriodicCycle(self._bus, period, functools.partial(self._cycle_frames, key))

    def _cycle_frame(self, key: tuple[int, bool], data: bytes) -> bool:
        """One frame of a clocked cycle (the kernel thread): stamped, sent without waiting,
        counted under the message's first actuator; True if it went out. A frame the bus does
        not take is a ``send`` error (once per outage: the cycle keeps trying)."""
        bus = self._bus
        if bus is None:
            return False
        fid, ext = key
        frame = can.Message(arbitration_id=fid, data=self.codec.stamp(fid, ext, data),
                            is_extended_id=ext)
        owner = self._cyclic_owner[key]
        try:
            bus.send(frame, 0)
        except (can.CanError, OSError) as exc:
            if key not in self._cycle_down:
                self._cycle_down.add(key)
                self._error("send", f"cyclic {self.codec.message_name(fid, ext)} on bus "
                                    f"{self.bus.name!r} not sent: {exc}")
            return False
        self._cycle_down.discard(key)
        self.sent_frames[owner] += 1
        if self.probe.any_failed:
            self._link_works(owner, "a cyclic frame was sent")
        if self._recorder is not None:
            frame.is_rx = False
            self._recorder.on_message_received(frame)
        return True

    def _cycle_frames(self, key: tuple[int, bool], data: bytes) -> list[can.Message]:
        """The frames of a periodic send task of message ``key`` holding ``data``: one per
        counter value in counter order (the checksum of each computed), one without a
        counter."""
        fid, ext = key
        prot = self.codec.protection(fid, ext)
        payloads = [data] if prot is None else [prot.stamp(data, c) for c in range(prot.modulo)]
        return [can.Message(arbitration_id=fid, data=p, is_extended_id=ext) for p in payloads]

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
        self._last_sent[device] = value
        if report:
            self.host.written(device, value)
        if self.probe.any_failed:
            self._link_works(device, "a frame was sent")
        if self._recorder is not None:
            frame.is_rx = False
            self._recorder.on_message_received(frame)

    def _probe_send(self, device: str, value: Any) -> str | None:
        """One probe of ``device`` (the probe's thread, see :mod:`drivers.sendprobe`): the
        frame of ``value`` sent as a command would be, holding the send; None if it went out
        (counted in :attr:`sent_frames`, recorded; not reported as a write: no command asked
        for it), else why not. On success the actuator counts as written again."""
        def send() -> str | None:
            bus = self._bus
            if bus is None:
                return f"CAN bus {self.bus.name!r} is closed"
            try:
                fid, data, ext = self.codec.encode_raw(device, value)
                if (fid, ext) in self._cyclic:    # the cycle sends it: one frame now
                    return (None if self._cycle_frame((fid, ext), data) else
                            f"cyclic {self.codec.message_name(fid, ext)} not sent")
                frame = can.Message(arbitration_id=fid, data=self.codec.stamp(fid, ext, data),
                                    is_extended_id=ext)
                if self._synchronous:
                    bus.send(frame, 0)
                else:
                    self._send_waiting(bus, frame)
            except (BusError, can.CanError, OSError) as exc:
                return f"CAN send on bus {self.bus.name!r} failed: {exc}"
            self.sent_frames[device] += 1
            if self._recorder is not None:
                frame.is_rx = False
                self._recorder.on_message_received(frame)
            self._link_works(device, f"the bus took a frame again (probe: {value!r} re-sent)")
            return None
        return self._claimed(send)

    def _send_failed(self, device: str) -> None:
        """Actuator ``device`` failed on the link (its send, or the bus's receive): no latch,
        the driver tries the link again itself (see :mod:`drivers.sendprobe`)."""
        with self._lock:
            last = self._last_sent.get(device)
        self.probe.failed(device, last if last is not None else safe_raw(self.devices[device]))

    def _link_works(self, device: str, why: str) -> None:
        """A frame of ``device`` went out (under the send's claim): the bus takes frames again,
        so every actuator failed by a send recovers (see :mod:`drivers.sendprobe`)."""
        for name in self.probe.recovered():
            self.host.recover(name, why if name == device else
                              f"a frame of {device} went out: the bus takes frames again")

    @property
    def sent(self) -> int:
        """Frames sent, all actuators together."""
        return sum(self.sent_frames.values())

    @property
    def sent_inline(self) -> int:
        """Of :attr:`sent`, the frames sent on the fast path (in the caller's thread)."""
        return self.sent - self.sent_queued

    def _bus_down(self, reason: str) -> None:
        """A receive error (the interface down, the controller bus-off): every device fails;
        the sensors recover with the next frame received, the actuators also with the next
        frame that goes out, which the driver sends itself (a bus with actuators only may never
        receive a frame again)."""
        if not self._failed:
            self._failed = True
            for name in self.devices:
                self.host.fail(name, f"CAN bus {self.bus.name!r} receive failed: {reason}")
            for name, spec in self.devices.items():
                if spec.direction == "actuator":
                    self._send_failed(name)

    def _bus_up(self) -> None:
        if self._failed:
            self._failed = False
            bad = {d for key in self._bad_failed for d in self.codec.sensors_of(*key)}
            for name in self.devices:
                if name not in bad:        # malformed frames keep those failed
                    self.host.recover(name, "frames received again")
