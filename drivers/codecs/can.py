"""can - the pure codec of the ``can`` bus: DBC loading, the mapping of devices onto DBC or raw
signals, frame decoding and encoding, and the checks of a device address. No I/O (no python-can):
frames are :class:`CanFrame` values or anything with the same attributes (a ``can.Message``).
Used by the CAN driver (:mod:`drivers.can_raw`) and by the simulated CAN nodes.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import cantools
from cantools.database.can import Message as DbcMessage
from cantools.database.can import Signal as DbcSignal

from chcos.devices import parsecache
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from chcos.helpers import is_int
from drivers.base import not_finite
from drivers.codecs.can_e2e import (
    CounterCheck,
    MessageSpec,
    Protection,
    cycle_of,
    parse_messages,
)

DBC_KEYS = ("message", "signal")
RAW_KEYS = ("id", "start", "length", "byte_order", "signed", "dlc", "extended")
BYTE_ORDERS = ("little_endian", "big_endian")
#: Address keys that would declare an alive counter or a checksum: refused by ``check``, which
#: points at the message's ``[[bus.message]]`` table, where they are declared.
UNSUPPORTED_KEYS = ("counter", "crc", "checksum")


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


def int_range(length: int, signed: bool) -> tuple[int, int]:
    if signed:
        return -(1 << (length - 1)), (1 << (length - 1)) - 1
    return 0, (1 << length) - 1


def _initial(sig: Any) -> float:
    init = sig.initial if sig.initial is not None else 0
    if sig.minimum is not None and init < sig.minimum:
        init = sig.minimum
    if sig.maximum is not None and init > sig.maximum:
        init = sig.maximum
    return float(init)


class FrameFault(enum.StrEnum):
    """Why a received frame gives no readings: the error class it is counted under."""

    REMOTE_FRAME = "remote-frame"    # a data request: chcos does not answer remote requests
    UNKNOWN_ID = "unknown-id"        # in no device's message
    WRONG_LENGTH = "wrong-length"    # not the message's length
    UNDECODABLE = "undecodable"      # the DBC cannot decode it, or a signal is not finite
    UNKNOWN_MUX = "unknown-mux"      # a multiplexer value the DBC does not list
    CHECKSUM = "checksum"            # the message's checksum signal is wrong
    COUNTER = "counter"              # the message's rolling counter did not follow the last


@dataclass(frozen=True, slots=True)
class Decoded:
    """A well-formed frame's readings, ``(device, value)`` in signal order (of a multiplexed
    message only the sensors its multiplexer selects, possibly none)."""

    readings: list[tuple[str, Any]]


@dataclass(frozen=True, slots=True)
class Ignored:
    """A frame of a known message that carries no sensor (an actuator message): not an error."""

    why: str


@dataclass(frozen=True, slots=True)
class Rejected:
    """A frame that gives no readings, with its class and a text naming the frame."""

    fault: FrameFault
    detail: str


#: What :meth:`CanCodec.decode` makes of a received frame.
DecodeResult = Decoded | Ignored | Rejected


class FrameLike(Protocol):
    """What the codec reads of a received frame (a ``can.Message`` has it)."""

    arbitration_id: int
    is_extended_id: bool
    is_remote_frame: bool
    dlc: int
    data: Any


@dataclass(frozen=True)
class CanFrame:
    """A data frame to send (or a received one): id, payload, extended id; the attribute
    names are python-can's, so ``can.Message(**dataclasses.asdict(frame))`` builds it."""

    arbitration_id: int
    data: bytes
    is_extended_id: bool = False

    @property
    def is_remote_frame(self) -> bool:
        """A CanFrame is always a data frame."""
        return False

    @property
    def dlc(self) -> int:
        """The payload length."""
        return len(self.data)


@dataclass
class _Frame:
    """One message this driver codes: the cantools message and which device each signal is."""

    message: Any
    sensors: dict[str, str] = field(default_factory=dict)     # signal name -> device
    actuators: dict[str, str] = field(default_factory=dict)   # signal name -> device
    values: dict[str, float] = field(default_factory=dict)    # last written (actuator side)
    #: a raw message whose signals are all whole little-endian bytes: (signal, first byte,
    #: bytes, signed) each, coded with int.from_bytes / to_bytes instead of cantools
    #: (the same values, without cantools' per-frame work); None for every other message
    whole_bytes: tuple[tuple[str, int, int, bool], ...] | None = None
    #: for a whole-byte message: the payload of :attr:`values` (None until known); a write
    #: replaces its signal's bytes in it (each device's slot is in ``CanCodec._by_device``)
    data: bytes | None = None
    #: for a whole-byte message with sensors: (device, first byte, bytes, signed) of each
    #: sensor signal, in the message's signal order (what decode reads, nothing looked up)
    reads: tuple[tuple[str, int, int, bool], ...] | None = None
    #: the one sensor signal of a whole-byte message that has one: (device, first byte, bytes,
    #: signed, whether it is the whole payload); decode then builds no list comprehension
    read1: tuple[str, int, int, bool, bool] | None = None
    #: the message's length, id and frame format, read once (cantools' are properties)
    length: int = 0
    frame_id: int = 0
    extended: bool = False
    multiplexed: bool = False
    #: what the map says of the message ([[bus.message]]), None if nothing
    spec: MessageSpec | None = None
    #: its counter and checksum (None: neither), the next counter to send, the receive check
    protection: Protection | None = None
    tx_counter: int = 0
    rx_counter: CounterCheck | None = None
    #: seconds between two frames (the map's cycle_time, else the DBC's), None: event-driven
    cycle: float | None = None

    def __post_init__(self) -> None:
        self.multiplexed = bool(self.message.is_multiplexed())
        self.length = int(self.message.length)
        self.frame_id = int(self.message.frame_id)
        self.extended = bool(self.message.is_extended_frame)


def _whole_bytes(msg: Any) -> tuple[tuple[str, int, int, bool], ...] | None:
    """The whole-byte plan of a raw message (see :attr:`_Frame.whole_bytes`), or None."""
    plan = []
    for sig in msg.signals:
        if (sig.byte_order != "little_endian" or sig.is_float or sig.start % 8
                or sig.length % 8 or sig.scale != 1 or sig.offset != 0
                or sig.start // 8 + sig.length // 8 > msg.length):
            return None
        plan.append((sig.name, sig.start // 8, sig.length // 8, bool(sig.is_signed)))
    return tuple(plan)


def _encode_whole(plan: tuple[tuple[str, int, int, bool], ...], values: dict[str, Any],
                  length: int) -> bytes | None:
    """``values`` packed by a whole-byte plan; None when one of them is not an integer that
    fits (cantools then encodes, and explains what does not fit)."""
    data = bytearray(length)
    for sig, o, n, sg in plan:
        v = values[sig]
        if isinstance(v, float):
            if not v.is_integer():
                return None
            v = int(v)
        elif not isinstance(v, int):
            return None
        try:
            data[o:o + n] = int(v).to_bytes(n, "little", signed=sg)
        except OverflowError:
            return None
    return bytes(data)


class CanCodec:
    """Maps devices to DBC/raw signals; decodes received frames, encodes actuator frames.

    Pure (no bus). Built from checked specs; raises :class:`BusError` if the DBC file is unusable.
    """

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec]) -> None:
        dbc = load_dbc(str(bus.options["dbc"])) if "dbc" in bus.options else None
        #: what the map says of its DBC messages (checked already: errors are not repeated)
        self.specs: dict[str, MessageSpec] = (parse_messages(bus.options, bus.key, dbc)[0]
                                              if dbc is not None else {})
        self._by_id: dict[tuple[int, bool], _Frame] = {}
        #: device -> its message, signal name, and in a whole-byte message its slot (first
        #: byte, bytes, signed, whether it is the whole payload), else None
        self._by_device: dict[str, tuple[_Frame, str, tuple[int, int, bool, bool] | None]] = {}
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
                self._attach(msg, d, d.name, from_dbc=False)
            fr = self._by_id[(fid, bool(a0.get("extended", False)))]
            fr.whole_bytes = _whole_bytes(msg)
            if fr.whole_bytes is not None:
                fr.data = _encode_whole(fr.whole_bytes, fr.values, msg.length)
                fr.reads = tuple((dev, o, n, sg) for sig, o, n, sg in fr.whole_bytes
                                 if (dev := fr.sensors.get(sig)) is not None) or None
                if fr.reads is not None and len(fr.reads) == 1:
                    dev, o, n, sg = fr.reads[0]
                    fr.read1 = (dev, o, n, sg, o == 0 and n == fr.length)
                if fr.data is not None:   # signals are named after their devices here
                    for sig, o, n, sg in fr.whole_bytes:
                        self._by_device[sig] = (fr, sig, (o, n, sg, o == 0 and n == fr.length))
        #: raw (non-DBC) integer actuator -> the range its signal carries: all check() asks
        #: of a value besides being an integer (no trial encode); also what accepts() gives
        self._raw_ranges: dict[str, tuple[int, int]] = {}
        for d in devices:
            if "message" not in d.address and d.direction != "sensor":
                self._raw_ranges[d.name] = int_range(int(d.address["length"]),
                                                     bool(d.address.get("signed", False)))

    def _attach(self, msg: Any, device: DeviceSpec, signal: str, from_dbc: bool = True) -> None:
        key = (msg.frame_id, bool(msg.is_extended_frame))
        fr = self._by_id.get(key)
        if fr is None:
            fr = _Frame(msg, values={s.name: _initial(s) for s in msg.signals})
            self._by_id[key] = fr
            if from_dbc:
                spec = fr.spec = self.specs.get(msg.name)
                fr.cycle = cycle_of(spec, msg)
                if spec is not None and (spec.counter or spec.checksum):
                    fr.protection = Protection(msg, spec)
                    fr.rx_counter = CounterCheck(fr.protection.modulo)
        side = fr.sensors if device.direction == "sensor" else fr.actuators
        side[signal] = device.name
        self._by_device[device.name] = (fr, signal, None)

    def sensor_ids(self) -> list[tuple[int, bool]]:
        """``(id, extended)`` of every message with a sensor signal: what the driver receives."""
        return sorted(k for k, fr in self._by_id.items() if fr.sensors)

    def sensors_of(self, can_id: int, extended: bool) -> list[str]:
        """The sensor devices of the message with ``can_id`` (none for an unknown id)."""
        fr = self._by_id.get((can_id, extended))
        return [] if fr is None else list(fr.sensors.values())

    def message_name(self, can_id: int, extended: bool) -> str:
        """The name of the message with ``can_id`` (the DBC's, or ``raw_0x..``)."""
        fr = self._by_id.get((can_id, extended))
        return f"0x{can_id:X}" if fr is None else str(fr.message.name)

    def decode(self, frame: FrameLike) -> DecodeResult:
        """Classify and decode ``frame``: its readings (:class:`Decoded`), :class:`Ignored` (an
        actuator message), or :class:`Rejected` with the :class:`FrameFault` it is counted
        under."""
        if frame.is_remote_frame:
            return Rejected(FrameFault.REMOTE_FRAME,
                            f"remote frame (a data request) for id 0x{frame.arbitration_id:X}, "
                            f"dlc {frame.dlc}: chcos does not answer remote requests")
        # (id, True) and (id, 1) are the same key: python-can's flag needs no bool()
        fr = self._by_id.get((frame.arbitration_id, frame.is_extended_id))
        if fr is None:
            return Rejected(FrameFault.UNKNOWN_ID,
                            f"frame id 0x{frame.arbitration_id:X} is in no device's message")
        if not fr.sensors:
            return Ignored("actuator message")
        data = frame.data
        if len(data) != fr.length:
            return Rejected(FrameFault.WRONG_LENGTH,
                            f"frame id 0x{frame.arbitration_id:X} ({fr.message.name}) has "
                            f"{len(data)} bytes, expected {fr.length}")
        prot = fr.protection
        if prot is not None and (fault := self._unprotected(fr, prot, bytes(data))) is not None:
            return fault
        one = fr.read1
        if one is not None:    # one raw whole-byte sensor signal: the int cantools would give
            dev, o, n, sg, whole = one
            return Decoded([(dev, int.from_bytes(data if whole else data[o:o + n], "little",
                                                 signed=sg))])
        reads = fr.reads
        if reads is not None:  # raw whole-byte signals: the ints cantools would give
            return Decoded([(dev, int.from_bytes(data[o:o + n], "little", signed=sg))
                            for dev, o, n, sg in reads])
        try:
            vals = fr.message.decode(bytes(frame.data), decode_choices=False)
        except (cantools.database.DecodeError, ValueError, KeyError) as exc:
            if fr.multiplexed and "multiplexer id" in str(exc):
                return Rejected(FrameFault.UNKNOWN_MUX,
                                f"frame id 0x{frame.arbitration_id:X} ({fr.message.name}): {exc}")
            return Rejected(FrameFault.UNDECODABLE, f"frame id 0x{frame.arbitration_id:X}: {exc}")
        # a multiplexed message gives only the signals its multiplexer selects in this frame
        out = [(dev, vals[sig]) for sig, dev in fr.sensors.items() if sig in vals]
        for dev, v in out:
            if isinstance(v, float) and not math.isfinite(v):
                return Rejected(FrameFault.UNDECODABLE,
                                f"frame id 0x{frame.arbitration_id:X}: signal of {dev} is {v}, "
                                f"not a finite number")
        return Decoded(out)

    @staticmethod
    def _unprotected(fr: _Frame, prot: Protection, data: bytes) -> Rejected | None:
        """Why a received frame of a message with a counter or checksum is not to be trusted
        (:class:`Rejected`, ``checksum`` or ``counter``), None if it is. A wrong checksum says
        nothing of the counter, which is then not taken."""
        counter, why = prot.check(data)
        name = fr.message.name
        if why:
            return Rejected(FrameFault.CHECKSUM, f"frame id 0x{fr.frame_id:X} ({name}): {why}")
        if counter is not None and fr.rx_counter is not None:
            why = fr.rx_counter.next(counter)
            if why:
                return Rejected(FrameFault.COUNTER, f"frame id 0x{fr.frame_id:X} ({name}): "
                                                    f"{why}")
        return None

    def key_of(self, device: str) -> tuple[int, bool]:
        """``(id, extended)`` of the message carrying ``device``. Raises KeyError."""
        fr = self._by_device[device][0]
        return fr.frame_id, fr.extended

    def cycle(self, can_id: int, extended: bool) -> float | None:
        """Seconds between two frames of the message with ``can_id`` (the map's cycle_time,
        else the DBC's GenMsgCycleTime); None when event-driven or unknown."""
        fr = self._by_id.get((can_id, extended))
        return None if fr is None else fr.cycle

    def actuators_of(self, can_id: int, extended: bool) -> list[str]:
        """The actuator devices of the message with ``can_id`` (none for an unknown id)."""
        fr = self._by_id.get((can_id, extended))
        return [] if fr is None else list(fr.actuators.values())

    def protection(self, can_id: int, extended: bool) -> Protection | None:
        """The counter and checksum of the message with ``can_id`` (None: neither)."""
        fr = self._by_id.get((can_id, extended))
        return None if fr is None else fr.protection

    def stamp(self, can_id: int, extended: bool, data: bytes) -> bytes:
        """``data`` of the message with ``can_id`` ready to send: its counter set to the next
        value (counted as sent) and its checksum computed; unchanged for a message without
        either. Call once per frame that goes on the wire."""
        fr = self._by_id.get((can_id, extended))
        prot = None if fr is None else fr.protection
        if prot is None or fr is None:
            return data
        counter = fr.tx_counter
        fr.tx_counter = (counter + 1) % prot.modulo
        return prot.stamp(data, counter)

    def reset_counter(self, can_id: int, extended: bool) -> None:
        """Forget the last counter received of the message with ``can_id`` (its sender
        restarted: the next frame only sets the base again)."""
        fr = self._by_id.get((can_id, extended))
        if fr is not None and fr.rx_counter is not None:
            fr.rx_counter.reset()

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """What :meth:`check` accepts for ``device`` without a trial encode: a raw (non-DBC)
        integer actuator's range, integers only; None for a DBC signal (scale, offset, its
        minimum and maximum: :meth:`check` decides)."""
        accept = self._raw_ranges.get(device)
        return None if accept is None else (float(accept[0]), float(accept[1]), True)

    def check(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for actuator ``device`` (None if it can): not a
        finite number, outside the signal's range or bit width, a fraction for a raw (non-DBC)
        integer signal. Nothing is remembered."""
        item = self._by_device.get(device)
        if item is None:
            return None
        fr, sig, _ = item
        if (why := not_finite(value)) is not None:
            return why
        if isinstance(value, bool):
            value = int(value)
        accept = self._raw_ranges.get(device)
        if accept is not None:     # a raw signal: an unscaled integer of its bit width
            bits = fr.message.get_signal_by_name(sig).length
            if isinstance(value, float) and not value.is_integer():
                return f"expected an integer for raw signal {sig} ({bits} bits), got {value!r}"
            if not accept[0] <= value <= accept[1]:
                return (f"expected {accept[0]}..{accept[1]} for raw signal {sig} ({bits} bits), "
                        f"got {value!r}")
            return None
        values = dict(fr.values)
        values[sig] = value
        try:
            fr.message.encode(selected(fr, values, sig), strict=True)
        except (cantools.database.EncodeError, ValueError, KeyError, OverflowError) as exc:
            return f"cannot encode into {fr.message.name}: {exc}"
        return None

    def encode(self, device: str, value: Any) -> CanFrame:
        """The frame that sets actuator ``device`` to ``value``, other signals unchanged.

        Raises :class:`BusError` if ``device`` is unknown or the value cannot be encoded (outside
        the DBC signal's range or bit width); the remembered values are then unchanged."""
        return CanFrame(*self.encode_raw(device, value))

    def held(self, device: str) -> tuple[int, bytes, bool]:
        """The frame of ``device``'s message with every signal at its held value (the last
        written, else the DBC's initial value), as :meth:`encode_raw` returns it. Raises
        KeyError for an unknown device."""
        fr, sig, _ = self._by_device[device]
        data = bytes(fr.message.encode(selected(fr, dict(fr.values), sig), strict=False))
        return fr.frame_id, data, fr.extended

    def encode_unchecked(self, device: str, value: Any) -> tuple[int, bytes, bool]:
        """As :meth:`encode_raw`, checked only against what the signal's bits carry, not the
        DBC's minimum and maximum (a simulated node sending what the DBC's limits exclude).
        Raises :class:`BusError` when the bits cannot carry ``value``."""
        fr, sig, _ = self._by_device[device]
        s = fr.message.get_signal_by_name(sig)
        cap = capacity(s)
        if (why := not_finite(value)) is not None:
            raise BusError(f"{device}: {why}")
        if cap is not None and not cap[0] - 1e-9 <= value <= cap[1] + 1e-9:
            raise BusError(f"{device}: {value!r} is outside what signal {sig} carries "
                           f"([{cap[0]:g}, {cap[1]:g}])")
        values = dict(fr.values)
        values[sig] = value
        try:
            data = bytes(fr.message.encode(selected(fr, values, sig), strict=False))
        except (cantools.database.EncodeError, ValueError, KeyError, OverflowError) as exc:
            raise BusError(f"cannot encode {device}={value!r} into {fr.message.name}: {exc}") \
                from exc
        fr.values = values
        if fr.whole_bytes is not None:
            fr.data = data
        return fr.frame_id, data, fr.extended

    def encode_raw(self, device: str, value: Any) -> tuple[int, bytes, bool]:
        """:meth:`encode`'s frame as ``(id, payload, extended)``, without building a
        :class:`CanFrame` (the driver's send path). Raises as :meth:`encode`."""
        try:
            fr, sig, slot = self._by_device[device]
        except KeyError:
            raise BusError(f"{device!r} is not a device of this CAN bus") from None
        if slot is not None:    # a whole-byte message: replace the signal's bytes
            kind = type(value)
            if kind is int or (kind is float and value.is_integer()):
                o, n, sg, whole = slot
                try:
                    part = int(value).to_bytes(n, "little", signed=sg)
                except OverflowError:
                    pass        # cantools explains below
                else:
                    if whole:
                        data = part
                    else:
                        old = fr.data
                        assert old is not None    # a slot is only given with a payload
                        data = old[:o] + part + old[o + n:]
                    fr.data = data
                    fr.values[sig] = value
                    return fr.frame_id, data, fr.extended
        values = dict(fr.values)
        values[sig] = value
        plan = fr.whole_bytes
        if plan is not None and (fast := _encode_whole(plan, values, fr.length)):
            fr.values, fr.data = values, fast
            return fr.frame_id, fast, fr.extended
        try:
            data = bytes(fr.message.encode(selected(fr, values, sig), strict=True))
        except (cantools.database.EncodeError, ValueError, KeyError, OverflowError) as exc:
            raise BusError(f"cannot encode {device}={value!r} into {fr.message.name}: {exc}") \
                from exc
        fr.values = values
        if plan is not None:
            fr.data = data
        return fr.frame_id, data, fr.extended


def selected(fr: _Frame, values: dict[str, Any], sig: str) -> dict[str, Any]:
    """What to encode after a write of signal ``sig`` into ``values`` (all of the message's
    signals): ``values`` itself for a plain message. For a multiplexed one, the multiplexer(s)
    above ``sig`` are set in ``values`` to select it (the first multiplexer value listing it,
    unless the current one does), and only the signals that selection carries are returned:
    a node sending such a message (the simulator serving a multiplexed DBC message) sends one
    multiplexer value per frame, as the DBC describes it."""
    if not fr.multiplexed:
        return values
    by_name = {s.name: s for s in fr.message.signals}
    s = by_name[sig]
    while s.multiplexer_ids and s.multiplexer_signal is not None:
        if values.get(s.multiplexer_signal) not in s.multiplexer_ids:
            values[s.multiplexer_signal] = s.multiplexer_ids[0]
        s = by_name[s.multiplexer_signal]

    def carried(name: str) -> bool:
        s = by_name[name]
        return not s.multiplexer_ids or (values.get(s.multiplexer_signal) in s.multiplexer_ids
                                         and carried(s.multiplexer_signal))

    return {name: v for name, v in values.items() if carried(name)}


def capacity(sig: Any) -> tuple[float, float] | None:
    """The physical values a DBC signal's bits carry (raw range through scale and offset), or
    None for a float signal."""
    if sig.is_float:
        return None
    lo, hi = int_range(int(sig.length), bool(sig.is_signed))
    ends = sorted((lo * sig.scale + sig.offset, hi * sig.scale + sig.offset))
    return float(ends[0]), float(ends[1])


def limits_beyond(sig: Any) -> str:
    """Why the DBC's minimum and maximum of ``sig`` reach past what its bits carry ("" if they
    do not, or are not given): an 8-bit signal of scale 0.1 cannot carry 0..125."""
    cap = capacity(sig)
    if cap is None or (sig.minimum is None and sig.maximum is None):
        return ""
    lo = sig.minimum if sig.minimum is not None else cap[0]
    hi = sig.maximum if sig.maximum is not None else cap[1]
    eps = 1e-9 * max(1.0, abs(cap[0]), abs(cap[1]))
    if lo >= cap[0] - eps and hi <= cap[1] + eps:
        return ""
    return (f"the DBC's limits of {sig.name} [{lo:g}, {hi:g}] reach past what its "
            f"{sig.length} {'signed ' if sig.is_signed else ''}bits carry at scale {sig.scale:g}"
            f", offset {sig.offset:g} ([{cap[0]:g}, {cap[1]:g}])")


def check_address(bus: BusSpec, device: DeviceSpec, dbc: Any) -> list[str]:
    """Errors of one device address on a ``can`` bus (``dbc`` is the loaded DBC or None)."""
    key = f"{device.key}.address"
    a = device.address
    refused = [f"{key}.{k}: unknown key: a rolling counter or a checksum is declared per "
               f"message, in the bus's [[bus.message]] table (name = \"MESSAGE\", counter = "
               f"\"SIGNAL\", checksum = {{ signal = \"SIGNAL\", algorithm = \"...\" }}): "
               f"docs/can-faults.md" for k in a if k in UNSUPPORTED_KEYS]
    if refused:
        return refused
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
        if device.direction == "actuator" and msg.is_multiplexed():
            errs.append(f"{key}.message: {msg_name} is multiplexed; chcos decodes multiplexed "
                        f"messages for sensors but does not send them: an actuator needs a "
                        f"message without multiplexer")
        if device.direction == "actuator":
            spec = parse_messages(bus.options, bus.key, None)[0].get(msg_name)
            if spec is not None and sig_name in (spec.counter, spec.checksum and
                                                 spec.checksum.signal):
                errs.append(f"{key}.signal: {sig_name} is the counter or checksum of "
                            f"{msg_name} ({spec.key}): chcos computes it for every frame, an "
                            f"actuator cannot set it")
            beyond = limits_beyond(msg.get_signal_by_name(sig_name))
            if beyond:
                errs.append(f"{key}.signal: {beyond}: a command inside the DBC's limits could "
                            f"not be sent")
        return errs
    errs = [f"{key}.{k}: unknown key; valid keys: {', '.join(DBC_KEYS)} (DBC form) or "
            f"{', '.join(RAW_KEYS)} (raw form)" for k in a if k not in RAW_KEYS]
    if not a:
        return [f"{key}: expected {{message, signal}} (DBC) or {{id, start, length}} (raw)"]
    ext = a.get("extended", False)
    fid = a.get("id")
    if not isinstance(ext, bool):
        errs.append(f"{key}.extended: expected true or false, got {ext!r}")
    if not is_int(fid) or not 0 <= fid <= (0x1FFFFFFF if ext is True else 0x7FF):
        errs.append(f"{key}.id: expected a CAN id 0..{'0x1FFFFFFF' if ext is True else '0x7FF'}"
                    f", got {fid!r}")
    dlc = a.get("dlc", 8)
    if not is_int(dlc) or not 0 < dlc <= 64:
        errs.append(f"{key}.dlc: expected a frame length 1..64 bytes, got {dlc!r}")
        dlc = 8
    start, length = a.get("start"), a.get("length")
    if not is_int(start) or not 0 <= start < dlc * 8:
        errs.append(f"{key}.start: expected a start bit 0..{dlc * 8 - 1}, got {start!r}")
    if not is_int(length) or not 1 <= length <= 64:
        errs.append(f"{key}.length: expected a bit length 1..64, got {length!r}")
    if a.get("byte_order", "little_endian") not in BYTE_ORDERS:
        errs.append(f"{key}.byte_order: expected one of {', '.join(BYTE_ORDERS)}, "
                    f"got {a.get('byte_order')!r}")
    if not isinstance(a.get("signed", False), bool):
        errs.append(f"{key}.signed: expected true or false, got {a.get('signed')!r}")
    return errs
