"""modbus - the pure codec of the Modbus buses: the data model of a device address (unit, table,
address, type, word order), read planning, register packing and unpacking, the value checks of a
register type, RTU answer classification and the address checks. No I/O (no pymodbus, whose
import starts its asyncio clients): used by the Modbus drivers (:mod:`drivers.modbus`) and by
the simulated slaves.

Registers are 16-bit words sent big-endian; a 32/64-bit value spans 2/4 registers in one of
the four orders devices use, named by the bytes of a 32-bit value ``A B C D`` (``A`` most
significant): ``ABCD`` (most significant word first, each word big-endian; alias ``big``),
``CDAB`` (words swapped; alias ``little``), ``BADC`` (bytes swapped in each word) and ``DCBA``
(both). A 64-bit value follows the same rule over its four words. ``big`` and ``little`` pack
as pymodbus' ``convert_to_registers``/``convert_from_registers`` do.
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.helpers import is_int, is_number

#: Register types: the :mod:`struct` code of the value and its size in registers.
REGISTER_TYPES: dict[str, tuple[str, int]] = {
    "int16": ("h", 1), "uint16": ("H", 1), "int32": ("i", 2), "uint32": ("I", 2),
    "float32": ("f", 2), "float64": ("d", 4)}
#: The packed value of each register type, and the registers' words (big-endian 16-bit) by count.
VALUE_STRUCT = {t: struct.Struct(f">{code}") for t, (code, _) in REGISTER_TYPES.items()}
WORDS_STRUCT = {n: struct.Struct(f">{n}H") for n in (1, 2, 4)}
#: What each type can carry on the wire (float32: its largest finite value).
RAW_RANGE: dict[str, tuple[float, float]] = {
    "bool": (0, 1), "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
    "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1),
    "float32": (-3.4028234663852886e38, 3.4028234663852886e38)}
TABLES = ("coil", "discrete", "holding", "input")
WRITABLE = ("coil", "holding")
ADDRESS_KEYS = ("unit", "table", "address", "type", "word_order", "poll_period")
MAX_REGISTERS = 125     # per read request (Modbus application protocol, function 3/4)
MAX_BITS = 2000         # per read request (function 1/2)
EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "server device failure", 5: "acknowledge", 6: "server device busy",
                  8: "memory parity error", 10: "gateway path unavailable",
                  11: "gateway target device failed to respond"}


WordOrder = Literal["ABCD", "CDAB", "BADC", "DCBA"]
#: Every ``word_order`` a map may give, and the order each names (``big``/``little``: aliases).
WORD_ORDERS: dict[str, WordOrder] = {"ABCD": "ABCD", "CDAB": "CDAB", "BADC": "BADC",
                                     "DCBA": "DCBA", "big": "ABCD", "little": "CDAB"}


def _reorder(regs: list[int], order: str) -> list[int]:
    """``regs`` (most significant word first, each big-endian) in ``order``, or back: both
    steps - words reversed (``CDAB``, ``DCBA``), bytes swapped in each word (``BADC``,
    ``DCBA``) - undo themselves. Raises KeyError for an unknown order."""
    named = WORD_ORDERS[order]
    if named in ("BADC", "DCBA"):
        regs = [((r & 0xFF) << 8) | (r >> 8) for r in regs]
    return regs[::-1] if named in ("CDAB", "DCBA") else regs


def to_registers(type_: str, value: int | float, word_order: str = "ABCD") -> list[int]:
    """``value`` packed into the registers of ``type_`` in ``word_order`` (one of
    :data:`WORD_ORDERS`; a 16-bit type has one register, whatever the order). Raises
    struct.error if it does not fit (an integer out of range)."""
    code, size = REGISTER_TYPES[type_]
    raw = struct.pack(f">{code}", value)
    regs = [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]
    return _reorder(regs, word_order) if size > 1 else regs


def from_registers(type_: str, registers: Sequence[int],
                   word_order: str = "ABCD") -> int | float:
    """The value of ``type_`` in ``registers`` (exactly its size) in ``word_order``. Raises
    ValueError if their number is not the type's size or a register is not 0..0xFFFF."""
    size = REGISTER_TYPES[type_][1]
    if len(registers) != size:
        raise ValueError(f"{len(registers)} registers for a {type_}, expected {size}")
    if any(not 0 <= r <= 0xFFFF for r in registers):
        raise ValueError(f"registers {list(registers)} are not 16-bit words")
    try:
        raw = WORDS_STRUCT[size].pack(*(_reorder(list(registers), word_order) if size > 1
                                        else registers))
    except struct.error as exc:
        raise ValueError(f"registers {list(registers)} are not 16-bit words: {exc}") from None
    value: int | float = VALUE_STRUCT[type_].unpack(raw)[0]
    return value


def crc16(data: bytes) -> int:
    """The Modbus RTU CRC-16 of ``data`` (polynomial 0xA001, initial 0xFFFF), as the two bytes
    sent on the line read big-endian (low byte first on the wire)."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return ((crc & 0xFF) << 8) | (crc >> 8)


@dataclass(frozen=True)
class Point:
    """One device's place in the Modbus data model."""

    device: str
    unit: int
    table: str
    address: int
    type: str
    word_order: WordOrder

    @functools.cached_property
    def size(self) -> int:
        """Entries it spans: 1 bit, or its register count."""
        return 1 if self.type == "bool" else REGISTER_TYPES[self.type][1]

    def decode(self, entries: Sequence[Any]) -> Any:
        """The value from its own slice of a response's bits or registers; ValueError if the
        slice does not fit the type."""
        if self.type == "bool":
            return bool(entries[0])
        return from_registers(self.type, entries, self.word_order)

    def encode(self, value: Any) -> list[int]:
        """The registers that carry ``value`` (rounded for an integer type); struct.error,
        ValueError or OverflowError if it cannot."""
        return to_registers(self.type, coerce(self.type, value), self.word_order)


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
    order = WORD_ORDERS[str(a.get("word_order", "ABCD"))]
    return Point(device.name, int(a.get("unit", 1)), table, int(a["address"]),
                 str(a.get("type", default)), order)


def check_address(bus: BusSpec, device: DeviceSpec) -> list[str]:
    """Errors of a Modbus device address (shared by both kinds)."""
    k = f"{device.key}.address"
    a = device.address
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(ADDRESS_KEYS)}"
            for key in a if key not in ADDRESS_KEYS]
    unit = a.get("unit", 1)
    if not (is_int(unit) and 0 <= unit <= 247):
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
        size = REGISTER_TYPES[typ][1]
    address = a.get("address")
    if not (is_int(address) and 0 <= address <= 0x10000 - size):
        errs.append(f"{k}.address: expected an integer 0..{0x10000 - size} (a {typ} spans {size} "
                    f"entr{'y' if size == 1 else 'ies'}), got {address!r}")
    order = a.get("word_order", "ABCD")
    if not (isinstance(order, str) and order in WORD_ORDERS):
        errs.append(f"{k}.word_order: expected \"ABCD\", \"CDAB\", \"BADC\" or \"DCBA\" (or "
                    f"\"big\" = ABCD, \"little\" = CDAB), got {order!r}")
    pp = a.get("poll_period")
    if pp is not None and not (is_number(pp) and pp > 0):
        errs.append(f"{k}.poll_period: expected a number of seconds > 0, got {pp!r}")
    return errs


INT_RANGES = {"int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1),
              "int32": (-2**31, 2**31 - 1), "uint32": (0, 2**32 - 1)}
FLOAT_MAX = {"float32": 3.4028234663852886e38, "float64": 1.7976931348623157e308}


def accepted(type_: str) -> tuple[float, float, bool]:
    """The values :func:`value_error` accepts for a point of ``type_``, as ``(lo, hi,
    integral)``: 0..1 for a coil, the range of an integer type (integers only), +-the largest
    finite value of a float type."""
    if type_ == "bool":
        return 0.0, 1.0, True
    if type_ in FLOAT_MAX:
        return -FLOAT_MAX[type_], FLOAT_MAX[type_], False
    lo, hi = INT_RANGES[type_]
    return float(lo), float(hi), True


def value_error(type_: str, value: Any) -> str | None:
    """Why ``value`` cannot be written to a point of ``type_`` exactly (None if it can)."""
    if isinstance(value, bool):
        value = int(value)
    if not is_number(value):
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
    """The value of ``p`` from its slice of an answer. Raises ValueError or IndexError if the
    entries are too few or a float is nan or infinite: such a value is reported as malformed,
    never delivered."""
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
            crc = crc16(frame[:-2])
            if crc.to_bytes(2, "big") != frame[-2:]:
                return "crc", (f"answer {frame.hex()} fails its CRC (expected "
                               f"{crc:04x}, got {frame[-2:].hex()})")
        if size is None or len(head) < size:
            return "framing", (f"truncated answer {head.hex()} ({len(head)} of "
                               f"{size if size is not None else '?'} bytes)")
    return "framing", f"{len(received)} bytes that are no answer: {received[:32].hex()}"


def coerce(type_: str, value: Any) -> int | float:
    """``value`` as the Python number pymodbus packs for ``type_`` (integers are rounded)."""
    if type_.startswith("float"):
        return float(value)
    if isinstance(value, float):
        return round(value)  # raises OverflowError/ValueError for inf/nan
    return int(value)


@dataclass(frozen=True)
class LineTiming:
    """The timing of a Modbus RTU serial line: the time of one character (start bit, data bits,
    parity bit if any, stop bits) and the silence that must separate two frames (3.5
    characters; a fixed 1.75 ms above 19200 baud, as the Modbus serial line specification
    allows)."""

    baudrate: int
    bytesize: int = 8
    parity: str = "N"
    stopbits: int = 1

    @property
    def char_time(self) -> float:
        """Seconds one character takes on the line."""
        bits = 1 + self.bytesize + (0 if self.parity == "N" else 1) + self.stopbits
        return bits / self.baudrate

    @property
    def silence(self) -> float:
        """Seconds of silence between two frames (t3.5)."""
        return 1.75e-3 if self.baudrate > 19200 else 3.5 * self.char_time

    def exchange_time(self, request_bytes: int, answer_bytes: int) -> float:
        """Seconds a request and its answer take on the line, with the silence after each."""
        return (request_bytes + answer_bytes) * self.char_time + 2 * self.silence


def answer_bytes(r: ReadRequest) -> int:
    """The length of the RTU answer to read request ``r`` (unit, function, byte count, data,
    CRC)."""
    data = (r.count + 7) // 8 if r.table in ("coil", "discrete") else 2 * r.count
    return 5 + data


READ_REQUEST_BYTES = 8   # unit, function, address, count, CRC


class UnitBackoff:
    """Which units of an RTU line answer, and how often a unit that does not is tried: after
    its ``k``-th unanswered request in a row a unit sits out ``min(start * 2**(k-1), cap) - 1``
    of its requests, so a dead unit takes a bounded share of the line and the live units keep
    their rate. ``start`` is ``first`` while another unit of the line (``units``) answers -
    chosen by the driver so that even the second try of a unit that just died keeps the live
    units' share (see :func:`drivers.modbus_link.dead_unit_first`) - and 1 when none does
    (nobody pays for the tries: the unit is tried again at once, then ever less often); the
    bus's ``retries`` are what spares one lost answer. Each time a unit stops answering its
    ``epoch`` grows: a write queued in an older epoch is not sent (it was meant for a unit that
    answered). Not thread-safe: the driver's worker owns it (the epoch is read from the kernel
    thread, a plain int)."""

    def __init__(self, cap: int, first: int = 1, units: Iterable[int] = ()) -> None:
        self.cap = max(1, cap)
        #: the turns between the first two tries of a unit that stopped answering while
        #: another unit of the line answers
        self.first = min(max(1, first), self.cap)
        #: the units of the line
        self.units = frozenset(units)
        self._misses: dict[int, int] = {}      # unit -> unanswered requests in a row
        self._skip: dict[int, int] = {}        # unit -> requests still to sit out
        self._epoch: dict[int, int] = {}

    def due(self, unit: int) -> bool:
        """Whether a request to ``unit`` goes out now; a dead unit's request that sits out
        counts down its turn."""
        left = self._skip.get(unit, 0)
        if left <= 0:
            return True
        self._skip[unit] = left - 1
        return False

    def silent(self, unit: int) -> bool:
        """``unit`` did not answer a request; True if it answered until then (it fails now)."""
        k = self._misses.get(unit, 0) + 1
        self._misses[unit] = k
        others = any(u != unit and not self.dead(u) for u in self.units)
        start = self.first if others else 1
        self._skip[unit] = min(start * 2 ** min(k - 1, 30), self.cap) - 1
        if k == 1:
            self._epoch[unit] = self._epoch.get(unit, 0) + 1
        return k == 1

    def answered(self, unit: int) -> bool:
        """``unit`` answered (data or an exception); True if it had stopped answering."""
        self._skip.pop(unit, None)
        return self._misses.pop(unit, 0) > 0

    def dead(self, unit: int) -> bool:
        """True while ``unit``'s last request went unanswered."""
        return self._misses.get(unit, 0) > 0

    def epoch(self, unit: int) -> int:
        """How many times ``unit`` stopped answering."""
        return self._epoch.get(unit, 0)


WATCHDOG_KEYS = ("unit", "table", "address", "period", "value")
WATCHDOG_TABLES = ("holding", "coil")


@dataclass(frozen=True)
class Watchdog:
    """A bus's watchdog register: written every ``period`` s so the PLC's comm-loss logic sees
    the controller alive. ``value`` None is a counter (1, 2, ... wrapping at 65536 on a holding
    register; 1, 0, 1... on a coil), else the same value each time."""

    unit: int
    table: str
    address: int
    period: float
    value: int | None

    def value_at(self, beat: int) -> int:
        """The value of the ``beat``-th write (0 first)."""
        if self.value is not None:
            return self.value
        return (beat + 1) % (2 if self.table == "coil" else 0x10000)

    def describe(self) -> str:
        """``unit 1 holding 900`` - for reasons."""
        return f"unit {self.unit} {self.table} {self.address}"


def watchdog_of(bus: BusSpec) -> Watchdog | None:
    """The validated bus's watchdog (None without one)."""
    w = bus.options.get("watchdog")
    if not isinstance(w, dict):
        return None
    value = w.get("value", "counter")
    return Watchdog(int(w.get("unit", 1)), str(w.get("table", "holding")), int(w["address"]),
                    float(w.get("period", 1.0)), None if value == "counter" else int(value))


def check_watchdog(bus: BusSpec) -> list[str]:
    """Errors of a bus's ``watchdog`` table (none without one)."""
    if "watchdog" not in bus.options:
        return []
    w = bus.options["watchdog"]
    k = f"{bus.key}.watchdog"
    if not isinstance(w, dict):
        return [f"{k}: expected a table {{unit, table, address, period, value}}, got {w!r}"]
    errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(WATCHDOG_KEYS)}"
            for key in w if key not in WATCHDOG_KEYS]
    unit = w.get("unit", 1)
    if not (is_int(unit) and 0 <= unit <= 247):
        errs.append(f"{k}.unit: expected a Modbus device id 0..247, got {unit!r}")
    table = w.get("table", "holding")
    if table not in WATCHDOG_TABLES:
        errs.append(f"{k}.table: expected \"holding\" or \"coil\", got {table!r}")
    address = w.get("address")
    if not (is_int(address) and 0 <= address <= 0xFFFF):
        errs.append(f"{k}.address: expected an integer 0..65535, got {address!r}")
    period = w.get("period", 1.0)
    if not (is_number(period) and period > 0):
        errs.append(f"{k}.period: expected a number of seconds > 0, got {period!r}")
    value = w.get("value", "counter")
    top = 1 if table == "coil" else 0xFFFF
    if value != "counter" and not (is_int(value) and 0 <= value <= top):
        errs.append(f"{k}.value: expected \"counter\" or an integer 0..{top}, got {value!r}")
    return errs
