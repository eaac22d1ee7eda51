"""modbus - the pure data model of the Modbus buses: a device's point (unit, table, address,
type, word order, string length, scale-factor register, "not implemented" value), read
planning, register packing and unpacking, a register type's value checks, the RTU CRC and line
timing, the backoff of RTU units that stop answering, and the classification of a bad RTU
answer. No I/O and no pymodbus (whose import starts asyncio): the Modbus drivers
(:mod:`drivers.modbus`), the simulated slaves (:mod:`chcos.apps.sim.modbus_slave`) and the
importers use it. The keys of a map are :mod:`drivers.codecs.modbus_options`.

Registers are 16-bit words sent big-endian; a 32/64-bit value spans 2/4 registers in one of
the four orders devices use, named by the bytes of a 32-bit value ``A B C D`` (``A`` most
significant): ``ABCD`` (most significant word first, each word big-endian; alias ``big``),
``CDAB`` (words swapped; alias ``little``), ``BADC`` (bytes swapped in each word) and ``DCBA``
(both). A 64-bit value follows the same rule over its four words. ``big`` and ``little`` pack
as pymodbus' ``convert_to_registers``/``convert_from_registers`` do. A ``string`` is ``count``
registers of ASCII, two characters each (the high byte first), NUL-padded (SunSpec's
``string``).
"""

from __future__ import annotations

import functools
import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal

#: Fixed-size register types: the :mod:`struct` code of the value and its size in registers.
REGISTER_TYPES: dict[str, tuple[str, int]] = {
    "int16": ("h", 1), "uint16": ("H", 1), "int32": ("i", 2), "uint32": ("I", 2),
    "int64": ("q", 4), "uint64": ("Q", 4), "float32": ("f", 2), "float64": ("d", 4)}
#: The register type whose size is the address's ``count``: ASCII text, NUL-padded.
STRING = "string"
#: Every ``type`` of a register address, and of a bit.
VALUE_TYPES = (*REGISTER_TYPES, STRING)
BIT_TYPE = "bool"
#: The packed value of each register type, and the registers' words (big-endian 16-bit) by count.
VALUE_STRUCT = {t: struct.Struct(f">{code}") for t, (code, _) in REGISTER_TYPES.items()}
WORDS_STRUCT = {n: struct.Struct(f">{n}H") for n in (1, 2, 4)}
#: The integer types' ranges, and the largest finite value of the float types.
INT_RANGES: dict[str, tuple[int, int]] = {
    "int16": (-2**15, 2**15 - 1), "uint16": (0, 2**16 - 1), "int32": (-2**31, 2**31 - 1),
    "uint32": (0, 2**32 - 1), "int64": (-2**63, 2**63 - 1), "uint64": (0, 2**64 - 1)}
FLOAT_MAX = {"float32": 3.4028234663852886e38, "float64": 1.7976931348623157e308}
#: What each numeric type can carry on the wire (float64 is left out: any finite float fits).
RAW_RANGE: dict[str, tuple[float, float]] = {
    "bool": (0, 1), **{t: (float(lo), float(hi)) for t, (lo, hi) in INT_RANGES.items()},
    "float32": (-FLOAT_MAX["float32"], FLOAT_MAX["float32"])}
#: An address's "not implemented" value, as the map writes it.
Unimplemented = int | float | str | None


def unimplemented_value(register_type: str, u: Unimplemented) -> Unimplemented:
    """The decoded value an address's ``unimplemented`` stands for: the value itself, or, where
    it is written as the registers' bit pattern the way SunSpec publishes it (0x8000 for an
    int16, 0x7FC00000 for a float32's NaN), the value those bits decode to. None stays None."""
    if u is None or isinstance(u, str) or register_type not in REGISTER_TYPES:
        return u
    regs = REGISTER_TYPES[register_type][1]
    bits = 16 * regs
    if isinstance(u, int) and register_type in INT_RANGES:
        lo, hi = INT_RANGES[register_type]
        if hi < u < 2 ** bits and lo < 0:      # a signed type's bit pattern
            return int(u - 2 ** bits)
        return u
    if isinstance(u, int) and 0 <= u < 2 ** bits:    # a float's bit pattern
        return float(VALUE_STRUCT[register_type].unpack(u.to_bytes(2 * regs, "big"))[0])
    return u


def is_unimplemented(value: Any, u: Unimplemented) -> bool:
    """True if decoded ``value`` is the "not implemented" value ``u`` (NaN matches NaN)."""
    if u is None:
        return False
    if isinstance(u, float) and math.isnan(u):
        return isinstance(value, float) and math.isnan(value)
    return bool(value == u)


Table = Literal["coil", "discrete", "holding", "input"]
TABLES: tuple[Table, ...] = ("coil", "discrete", "holding", "input")
BIT_TABLES = ("coil", "discrete")
WRITABLE = ("coil", "holding")
MAX_REGISTERS = 125     # per read request (Modbus application protocol, function 3/4)
MAX_BITS = 2000         # per read request (function 1/2)
MAX_WRITE_REGISTERS = 123   # per write request (function 16)
#: SunSpec's range of a scale factor (``sunssf``), and its "not implemented" value.
SCALE_FACTOR_RANGE = (-10, 10)
SCALE_FACTOR_UNIMPLEMENTED = -0x8000
BROADCAST = 0           # the unit id every slave of a serial line takes (writes only)
MAX_UNIT = 247
EXCEPTION_TEXT = {1: "illegal function", 2: "illegal data address", 3: "illegal data value",
                  4: "server device failure", 5: "acknowledge", 6: "server device busy",
                  8: "memory parity error", 10: "gateway path unavailable",
                  11: "gateway target device failed to respond"}


def exception_text(code: int) -> str:
    """``exception code 2 (illegal data address)`` - for reasons."""
    return f"exception code {code} ({EXCEPTION_TEXT.get(code, 'unknown')})"


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


def text_to_registers(text: str, count: int) -> list[int]:
    """``text`` as ``count`` registers of ASCII, two characters each (high byte first),
    NUL-padded. Raises ValueError for text that is not ASCII, holds a NUL or is longer than
    ``2 x count`` characters."""
    try:
        raw = text.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"{text!r} is not ASCII text") from None
    if b"\0" in raw or len(raw) > 2 * count:
        raise ValueError(f"{text!r} does not fit {count} register(s) of NUL-padded ASCII "
                         f"({2 * count} characters at most, no NUL)")
    raw = raw.ljust(2 * count, b"\0")
    return [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]


def text_from_registers(registers: Sequence[int]) -> str:
    """The NUL-padded ASCII text of ``registers`` (trailing NULs dropped). Raises ValueError
    for a byte that is not ASCII or a NUL before the padding."""
    raw = b"".join(int(r).to_bytes(2, "big") for r in registers)
    text = raw.rstrip(b"\0")
    if b"\0" in text or any(b > 0x7F for b in text):
        raise ValueError(f"registers {list(registers)} hold {raw!r}: not NUL-padded ASCII")
    return text.decode("ascii")


_CRC_TABLE: list[int] = []
for _byte in range(256):
    _crc = _byte
    for _ in range(8):
        _crc = (_crc >> 1) ^ 0xA001 if _crc & 1 else _crc >> 1
    _CRC_TABLE.append(_crc)


def crc16(data: bytes) -> int:
    """The Modbus RTU CRC-16 of ``data`` (polynomial 0xA001, initial 0xFFFF), as the two bytes
    sent on the line read big-endian (low byte first on the wire)."""
    crc = 0xFFFF
    table = _CRC_TABLE
    for b in data:
        crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
    return ((crc & 0xFF) << 8) | (crc >> 8)


def with_crc(frame: bytes) -> bytes:
    """``frame`` (unit, function, data) with its CRC appended, as it goes on an RTU line."""
    return frame + crc16(frame).to_bytes(2, "big")


@dataclass(frozen=True)
class Absent:
    """A reading that carries no value: the device said the value is not implemented (its raw
    value is the address's ``unimplemented``, or its scale factor is SunSpec's 0x8000)."""

    reason: str


@dataclass(frozen=True)
class Point:
    """One device's place in the Modbus data model: ``count`` is the registers of a
    ``string``, ``scale_factor`` the address of the int16 register holding its power-of-ten
    scale (same unit and table), ``unimplemented`` the raw value meaning "not implemented"."""

    device: str
    unit: int
    table: str
    address: int
    type: str
    word_order: WordOrder = "ABCD"
    count: int = 0
    scale_factor: int | None = None
    unimplemented: int | float | str | None = None

    @functools.cached_property
    def size(self) -> int:
        """Entries it spans: 1 bit, its register count, or a string's ``count``."""
        if self.type == BIT_TYPE:
            return 1
        return self.count if self.type == STRING else REGISTER_TYPES[self.type][1]

    @functools.cached_property
    def broadcast(self) -> bool:
        """True for unit 0: every slave of the line takes its writes, none answers."""
        return self.unit == BROADCAST

    def decode(self, entries: Sequence[Any]) -> Any:
        """The raw value from its own slice of a response's bits or registers; ValueError if
        the slice does not fit the type."""
        if self.type == BIT_TYPE:
            return bool(entries[0])
        if self.type == STRING:
            return text_from_registers(entries)
        return from_registers(self.type, entries, self.word_order)

    def encode(self, value: Any) -> list[int]:
        """The registers that carry ``value`` (rounded for an integer type); struct.error,
        ValueError or OverflowError if it cannot."""
        if self.type == STRING:
            return text_to_registers(value, self.count)
        return to_registers(self.type, coerce(self.type, value), self.word_order)

    def describe(self) -> str:
        """``unit 1 holding 10`` - for reasons."""
        return f"unit {self.unit} {self.table} {self.address}"


def scale_factor_point(p: Point) -> Point:
    """The int16 point of ``p``'s scale-factor register (its device name empty: read, never
    delivered)."""
    assert p.scale_factor is not None
    return Point("", p.unit, p.table, p.scale_factor, "int16")


@dataclass(frozen=True)
class ReadRequest:
    """One read of ``count`` entries of one unit and table, and the points it serves (those of
    scale-factor registers have no device)."""

    unit: int
    table: str
    address: int
    count: int
    points: tuple[Point, ...]

    def describe(self) -> str:
        """``unit 1 holding 10..13`` - for failure reasons."""
        return f"unit {self.unit} {self.table} {self.address}..{self.address + self.count - 1}"


def plan_reads(points: Sequence[Point]) -> list[ReadRequest]:
    """Group ``points`` - and the scale-factor registers they name - into as few requests as
    possible: contiguous (or overlapping) addresses of the same unit and table, within the
    protocol's per-request limit. A scale-factor register next to its value is read in the
    same request, else in its own."""
    wanted = list(points)
    seen = {(p.unit, p.table, p.address, p.type) for p in wanted if not p.device}
    for p in points:
        if p.scale_factor is not None:
            sf = scale_factor_point(p)
            key = (sf.unit, sf.table, sf.address, sf.type)
            if key not in seen:
                seen.add(key)
                wanted.append(sf)
    out: list[ReadRequest] = []
    cur: list[Point] = []
    end = 0
    for p in sorted(wanted, key=lambda p: (p.unit, p.table, p.address, p.device)):
        limit = MAX_BITS if p.table in BIT_TABLES else MAX_REGISTERS
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


def accepted(type_: str) -> tuple[float, float, bool] | None:
    """The values :func:`value_error` accepts for a point of ``type_``, as ``(lo, hi,
    integral)``: 0..1 for a coil, the range of an integer type (integers only), +-the largest
    finite value of a float type; None for a string (not a number)."""
    if type_ == BIT_TYPE:
        return 0.0, 1.0, True
    if type_ in FLOAT_MAX:
        return -FLOAT_MAX[type_], FLOAT_MAX[type_], False
    if type_ not in INT_RANGES:
        return None
    lo, hi = INT_RANGES[type_]
    return float(lo), float(hi), True


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def value_error(type_: str, value: Any, count: int = 0) -> str | None:
    """Why ``value`` cannot be written to a point of ``type_`` exactly (None if it can);
    ``count`` is a string's register count."""
    if type_ == STRING:
        if not isinstance(value, str):
            return f"expected text for a string address, got {value!r}"
        try:
            text_to_registers(value, count)
        except ValueError as exc:
            return f"expected NUL-free ASCII of at most {2 * count} characters: {exc}"
        return None
    if isinstance(value, bool):
        value = int(value)
    if not _is_number(value):
        return f"expected a number for a {type_} address, got {value!r}"
    if value != value or value in (float("inf"), float("-inf")):
        return f"expected a finite number for a {type_} address, got {value!r}"
    if type_ == BIT_TYPE:
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


def scaled(raw: int | float, sf: int) -> int | float:
    """``raw`` x 10^``sf`` (a division for a negative ``sf``: 2345 and -2 give 23.45 exactly
    as a float can)."""
    factor: int = 10 ** abs(sf)
    return raw * factor if sf >= 0 else raw / factor


def scale_factor_error(sf: int) -> str | None:
    """Why the register value ``sf`` is no usable scale factor (None if it is)."""
    lo, hi = SCALE_FACTOR_RANGE
    return None if lo <= sf <= hi else f"scale factor {sf} outside {lo}..{hi}"


def reading_of(p: Point, entries: Sequence[Any], sf: int | None = None) -> Any:
    """The value of ``p`` from its slice of an answer - raw, times 10^``sf`` (the value of its
    scale-factor register, read in the same poll) where it has one - or :class:`Absent` when
    the device says it is not implemented. Raises ValueError or IndexError if the entries are
    too few, a float is nan or infinite, or the scale factor is out of range: such a value is
    reported as malformed, never delivered."""
    if len(entries) < p.size:
        raise IndexError(f"{len(entries)} entries for a {p.type}, expected {p.size}")
    value = p.decode(entries)
    if is_unimplemented(value, p.unimplemented):
        return Absent(f"{p.describe()} holds {value!r}: not implemented")
    if isinstance(value, float) and not math.isfinite(value):
        raise ValueError(f"{p.type} registers {list(entries)} hold {value}, not a finite number")
    if p.scale_factor is None or sf is None:
        return value
    if sf == SCALE_FACTOR_UNIMPLEMENTED:
        return Absent(f"its scale factor ({p.table} {p.scale_factor}) is not implemented")
    why = scale_factor_error(sf)
    if why is not None:
        raise ValueError(f"{p.table} {p.scale_factor}: {why}")
    return scaled(value, sf)


def coerce(type_: str, value: Any) -> int | float:
    """``value`` as the Python number packed for ``type_`` (integers are rounded)."""
    if type_.startswith("float"):
        return float(value)
    if isinstance(value, float):
        return round(value)  # raises OverflowError/ValueError for inf/nan
    return int(value)


def unscaled(value: int | float, sf: int) -> int | None:
    """The integer raw value that carries ``value`` with scale factor ``sf`` (value /
    10^sf), or None if none does exactly (beyond float noise)."""
    raw = value * 10 ** -sf if sf <= 0 else value / 10 ** sf
    near = round(raw)
    return near if abs(raw - near) <= 1e-6 * max(1.0, abs(raw)) else None


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

    def frame_time(self, n: int) -> float:
        """Seconds ``n`` bytes take on the line, with the silence that ends them."""
        return n * self.char_time + self.silence

    def exchange_time(self, request_bytes: int, answer_bytes: int) -> float:
        """Seconds a request and its answer take on the line, with the silence after each."""
        return self.frame_time(request_bytes) + self.frame_time(answer_bytes)


def answer_bytes(r: ReadRequest) -> int:
    """The length of the RTU answer to read request ``r`` (unit, function, byte count, data,
    CRC)."""
    data = (r.count + 7) // 8 if r.table in BIT_TABLES else 2 * r.count
    return 5 + data


READ_REQUEST_BYTES = 8   # unit, function, address, count, CRC


def rtu_answer_size(head: bytes) -> int | None:
    """The length of an RTU answer starting with ``head`` (unit, function...), None if it
    cannot be told yet or the function is not one a master of chcos asks."""
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
        size = rtu_answer_size(head)
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


class UnitBackoff:
    """Which units of an RTU line answer, and how often a unit that does not is tried: after
    its ``k``-th unanswered request in a row a unit sits out ``min(start * 2**(k-1), cap) - 1``
    of its requests, so a dead unit takes a bounded share of the line and the live units keep
    their rate. ``start`` is ``first`` while another unit of the line (``units``) answers (it
answered once at least, and its last request too) -
    chosen by the driver so that even the second try of a unit that just died keeps the live
    units' share (see :func:`drivers.modbus.config.dead_unit_first`) - and 1 when none does
    (nobody pays for the tries: the unit is tried again at once, then ever less often); the
    bus's ``retries`` are what spares one lost answer. Each time a unit stops answering its
    ``epoch`` grows: a write queued in an older epoch is not sent (it was meant for a unit that
    answered). Not thread-safe: the driver's requests own it (the epoch is read from the kernel
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
        self._heard: set[int] = set()          # units that answered at least once

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
        others = any(u != unit and u in self._heard and not self.dead(u) for u in self.units)
        start = self.first if others else 1
        self._skip[unit] = min(start * 2 ** min(k - 1, 30), self.cap) - 1
        if k == 1:
            self._epoch[unit] = self._epoch.get(unit, 0) + 1
        return k == 1

    def answered(self, unit: int) -> bool:
        """``unit`` answered (data or an exception); True if it had stopped answering."""
        self._heard.add(unit)
        self._skip.pop(unit, None)
        return self._misses.pop(unit, 0) > 0

    def dead(self, unit: int) -> bool:
        """True while ``unit``'s last request went unanswered."""
        return self._misses.get(unit, 0) > 0

    def epoch(self, unit: int) -> int:
        """How many times ``unit`` stopped answering."""
        return self._epoch.get(unit, 0)

    def dead_units(self) -> list[int]:
        """The units whose last request went unanswered, in order."""
        return sorted(u for u, k in self._misses.items() if k > 0)
