"""modbus_slave - simulated Modbus slaves as strict as a device: the register store and the pure
request handler that serves it per the Modbus Application Protocol (V1.1b3).

:class:`RegisterStore` holds, per unit, the four tables (coils, discrete inputs, holding and
input registers) under one lock, only at the mapped addresses; the owner (a test, a simulated
cell, value scripts) reads and writes it from any thread.

:class:`ModbusSlave` is the handler: request bytes in, answer bytes (or silence) out, given the
time - no I/O, so the same code serves a TCP socket, a serial line or pty, and the in-process
hand-off of a driver on virtual time (it is a :class:`drivers.codecs.modbus_direct.DirectSlave`).
What it answers, as a device does:

* functions 1, 2, 3, 4 (reads), 5, 6, 15, 16 (writes); any other function code is exception
  01 (illegal function) - no invented answer;
* a quantity out of the function's range, a byte count that does not match it, a request PDU of
  the wrong length (truncated, or with extra bytes), a coil value other than 0x0000/0xFF00:
  exception 03 (illegal data value);
* an address range of which any entry is not mapped: exception 02 (illegal data address), per
  register and per unit - nothing is served next to a mapped address, nor one unit's address
  from another's;
* Modbus RTU: a frame with a bad CRC, or for a unit not on the line, gets silence; a broadcast
  (unit 0) write is carried out on every unit, unanswered; a broadcast read is ignored;
* Modbus TCP: as one ``device`` (the unit id is not significant: any id is served, the answer
  repeats it) or as a ``gateway`` to its units (a unit not present is exception 0x0B, gateway
  target device failed to respond; unit 0 is a broadcast write, unanswered). A protocol id
  other than 0 or a MBAP length that does not fit gets no answer.

A store may refuse a request on its own (:meth:`RegisterStore.refusal`: the welding cell's
silent inputs answer 0x0B).
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, Literal

from chcos.errors import ConfigError
from drivers.codecs.modbus import (
    BIT_TABLES,
    BROADCAST,
    REGISTER_TYPES,
    STRING,
    TABLES,
    from_registers,
    text_from_registers,
    text_to_registers,
    to_registers,
    with_crc,
)
from drivers.codecs.modbus import crc16 as _crc16

Span = tuple[int, int]
"""A run of mapped addresses: (first, count)."""
Framing = Literal["tcp", "rtu"]
TcpRole = Literal["device", "gateway"]

ILLEGAL_FUNCTION, ILLEGAL_ADDRESS, ILLEGAL_VALUE, DEVICE_FAILURE = 1, 2, 3, 4
GATEWAY_NO_RESPONSE = 11
#: function code -> (table, is a write)
FUNCTIONS: dict[int, tuple[str, bool]] = {1: ("coil", False), 2: ("discrete", False),
                                          3: ("holding", False), 4: ("input", False),
                                          5: ("coil", True), 6: ("holding", True),
                                          15: ("coil", True), 16: ("holding", True)}
MAX_READ = {1: 2000, 2: 2000, 3: 125, 4: 125}
MAX_WRITE = {15: 0x7B0, 16: 0x7B}
COIL_ON, COIL_OFF = 0xFF00, 0x0000
_MBAP = struct.Struct(">HHHB")
_TWO = struct.Struct(">HH")


def merge(spans: Iterable[Span]) -> list[Span]:
    """``spans`` sorted, with overlapping and adjacent runs joined."""
    out: list[Span] = []
    for first, count in sorted(s for s in spans if s[1] > 0):
        if out and first <= out[-1][0] + out[-1][1]:
            last_first, last_count = out[-1]
            out[-1] = (last_first, max(last_count, first + count - last_first))
        else:
            out.append((first, count))
    return out


class RegisterStore:
    """The four tables of each unit. Only mapped addresses exist: by default ``size`` entries
    from 0 in each table; with ``spans`` (table -> runs of (first, count)) only those runs, in
    every unit, so a device with registers at 0 and 64512 costs a few entries, not 64513; with
    ``unit_spans`` (unit -> table -> runs) each unit has its own (the units are its keys).
    Thread-safe.

    Raises :class:`chcos.errors.ConfigError` for an unknown unit/table or an address that is
    not mapped, or for an address beyond 65535.
    """

    def __init__(self, units: Iterable[int] = (1,), size: int = 1000, *,
                 spans: Mapping[str, Iterable[Span]] | None = None,
                 unit_spans: Mapping[int, Mapping[str, Iterable[Span]]] | None = None) -> None:
        layout: dict[int, dict[str, list[Span]]]
        if unit_spans is not None:
            layout = {u: {t: merge(per.get(t, ())) for t in TABLES}
                      for u, per in unit_spans.items()}
        else:
            shared: dict[str, list[Span]] = {
                t: merge(spans.get(t, ()) if spans is not None else [(0, size)]) for t in TABLES}
            layout = {u: shared for u in units}
        #: the mapped runs of each table, of every unit together
        self.spans: dict[str, list[Span]] = {
            t: merge(r for per in layout.values() for r in per[t]) for t in TABLES}
        for table, runs in self.spans.items():
            for first, count in runs:
                if first < 0 or first + count > 0x10000:
                    raise ConfigError(f"modbus store {table}: addresses {first}.."
                                      f"{first + count - 1} outside 0..65535")
        self.size = max([f + c for runs in self.spans.values() for f, c in runs] + [0])
        self._cond = threading.Condition()
        self._layout = layout
        self._units: dict[int, dict[str, dict[int, Any]]] = {
            u: {t: {a: (False if t in BIT_TABLES else 0)
                    for first, count in per[t] for a in range(first, first + count)}
                for t in TABLES} for u, per in layout.items()}
        #: write requests carried out, and requests handled (any unit, any outcome)
        self.client_writes = 0
        self.requests = 0

    @property
    def units(self) -> list[int]:
        """The unit ids served."""
        return sorted(self._units)

    def has_unit(self, unit: int) -> bool:
        """True if ``unit`` is one of the store's."""
        return unit in self._units

    def exists(self, unit: int, table: str, address: int, count: int) -> bool:
        """True if every entry ``address .. address + count - 1`` of ``unit``'s ``table`` is
        mapped."""
        data = self._units.get(unit, {}).get(table)
        if data is None:
            return False
        return all(a in data for a in range(address, address + count))

    def refusal(self, unit: int, table: str, address: int, count: int, write: bool
                ) -> int | None:
        """The exception code a valid request of mapped entries gets anyway (a device's own
        rule), None to carry it out. The default: none; a subclass may refuse."""
        return None

    def _table(self, unit: int, table: str, address: int, count: int) -> dict[int, Any]:
        if unit not in self._units:
            raise ConfigError(f"modbus store: no unit {unit}; units are {self.units}")
        if table not in TABLES:
            raise ConfigError(f"modbus store: table {table!r}; expected one of {TABLES}")
        data = self._units[unit][table]
        if address < 0 or count < 0 or not all(a in data for a in range(address,
                                                                        address + count)):
            mapped = " and ".join(f"{f}..{f + c - 1}" for f, c in self._layout[unit][table])
            raise ConfigError(f"modbus store unit {unit} {table}: addresses {address}.."
                              f"{address + count - 1} outside {mapped or 'nothing mapped'}")
        return data

    def read(self, unit: int, table: str, address: int, count: int = 1) -> list[Any]:
        """``count`` raw entries (bools or 16-bit ints) from ``address``."""
        with self._cond:
            data = self._table(unit, table, address, count)
            return [data[a] for a in range(address, address + count)]

    def write(self, unit: int, table: str, address: int, values: Sequence[Any]) -> None:
        """Store raw entries (bools for bit tables, 0..65535 for registers) from ``address``."""
        with self._cond:
            data = self._table(unit, table, address, len(values))
            bits = table in BIT_TABLES
            for v in values:
                if not bits and not (isinstance(v, int) and 0 <= v <= 0xFFFF):
                    raise ConfigError(f"modbus store unit {unit} {table}: register value {v!r} "
                                      f"is not 0..65535")
            for a, v in enumerate(values, address):
                data[a] = bool(v) if bits else v
            self._cond.notify_all()

    def set_value(self, unit: int, table: str, address: int, value: Any, type: str = "uint16",
                  word_order: str = "ABCD", count: int = 0) -> None:
        """Store an engineering value of ``type`` (bool, int16 ... float64, or a ``string`` of
        ``count`` registers) in ``word_order`` (one of the codec's ``WORD_ORDERS``)."""
        if type == "bool":
            self.write(unit, table, address, [bool(value)])
            return
        try:
            if type == STRING:
                regs = text_to_registers(str(value), count)
            elif type in REGISTER_TYPES:
                regs = to_registers(type, value, word_order)
            else:
                raise ConfigError(f"modbus store: type {type!r}; expected bool, string or one "
                                  f"of {', '.join(REGISTER_TYPES)}")
        except (struct.error, TypeError, ValueError, OverflowError) as exc:
            raise ConfigError(f"modbus store: {value!r} is not a valid {type}: {exc}") from exc
        self.write(unit, table, address, regs)

    def get_value(self, unit: int, table: str, address: int, type: str = "uint16",
                  word_order: str = "ABCD", count: int = 0) -> Any:
        """The value of ``type`` at ``address`` (see :meth:`set_value`)."""
        if type == "bool":
            return self.read(unit, table, address, 1)[0]
        if type == STRING:
            return text_from_registers(self.read(unit, table, address, count))
        if type not in REGISTER_TYPES:
            raise ConfigError(f"modbus store: type {type!r}; expected bool, string or one of "
                              f"{', '.join(REGISTER_TYPES)}")
        regs = self.read(unit, table, address, REGISTER_TYPES[type][1])
        return from_registers(type, regs, word_order)

    def wait_for(self, pred: Callable[[RegisterStore], bool], timeout: float) -> bool:
        """Block until ``pred(store)`` holds, re-checked after every write; False on timeout."""
        with self._cond:
            return self._cond.wait_for(lambda: pred(self), timeout)

    # ---- the handler's side (under the store's lock) ----------------------------------------
    def _serve(self, units: Sequence[int], fc: int, address: int, count: int,
               values: list[Any] | None) -> list[Any] | int:
        """Read (``values`` None) or write entries of ``units`` (several: a broadcast) for
        function ``fc``: the entries read, [] for a write, or an exception code."""
        table, _ = FUNCTIONS[fc]
        with self._cond:
            self.requests += 1
            for unit in units:
                if not self.exists(unit, table, address, count):
                    return ILLEGAL_ADDRESS
                code = self.refusal(unit, table, address, count, values is not None)
                if code is not None:
                    return code
            if values is None:
                data = self._units[units[0]][table]
                return [data[a] for a in range(address, address + count)]
            for unit in units:
                data = self._units[unit][table]
                for a, v in enumerate(values, address):
                    data[a] = v
            self.client_writes += 1
            self._cond.notify_all()
            return []


def _exception(fc: int, code: int) -> bytes:
    return bytes([fc | 0x80, code])


def _pack_bits(bits: Sequence[Any]) -> bytes:
    out = bytearray((len(bits) + 7) // 8)
    for i, b in enumerate(bits):
        if b:
            out[i // 8] |= 1 << (i % 8)
    return bytes(out)


def _unpack_bits(data: bytes, count: int) -> list[bool]:
    return [bool(data[i // 8] >> (i % 8) & 1) for i in range(count)]


class ModbusSlave:
    """The request handler of the slaves of one bus (see the module doc): ``framing`` the bytes
    it takes, ``role`` on TCP (``device``: any unit id served from the store's one unit;
    ``gateway``: the store's units, 0x0B for others). While :meth:`silence` lasts it takes no
    connection (TCP) or answers nothing (RTU)."""

    def __init__(self, store: RegisterStore, framing: Framing = "tcp",
                 role: TcpRole = "gateway") -> None:
        self.store = store
        self.framing: Framing = framing
        self.role: TcpRole = role
        self.silent = False
        #: units that answer nothing (dead units of the line, or behind the gateway)
        self.silent_units: frozenset[int] = frozenset()
        #: requests that got silence because of their unit (RTU) or framing
        self.ignored = 0

    def silence(self) -> None:
        """Stop answering (see the class doc)."""
        self.silent = True

    def silence_units(self, units: Iterable[int]) -> None:
        """Make ``units`` answer nothing from now on (an empty set: all answer again)."""
        self.silent_units = frozenset(units)

    def restore(self) -> None:
        """Answer again."""
        self.silent = False

    # ---- DirectSlave ------------------------------------------------------------------------
    def accepts(self) -> bool:
        """Whether a TCP connection would be taken now."""
        return not (self.silent and self.framing == "tcp")

    def exchange(self, adu: bytes, now: float) -> bytes | None:
        """One request ADU (the framing's) at clock time ``now``: the answer ADU or None."""
        if self.silent:
            return None
        return self.handle_tcp(adu) if self.framing == "tcp" else self.handle_rtu(adu)

    # ---- framings ---------------------------------------------------------------------------
    def handle_tcp(self, adu: bytes) -> bytes | None:
        """A Modbus TCP ADU (MBAP header and PDU): the answer ADU, or None (no answer)."""
        if len(adu) < 8:
            self.ignored += 1
            return None
        tid, protocol, length, unit = _MBAP.unpack_from(adu)
        if protocol != 0 or length != len(adu) - 6:
            self.ignored += 1
            return None
        pdu = adu[7:]
        if unit == BROADCAST and self.role == "gateway":
            self.handle_pdu(tuple(self.store.units), pdu, broadcast=True)
            return None
        if self.role == "device":
            units: tuple[int, ...] = (self.store.units[0],) if self.store.units else ()
        elif unit in self.silent_units:
            return None
        elif self.store.has_unit(unit):
            units = (unit,)
        else:
            absent = _exception(pdu[0], GATEWAY_NO_RESPONSE)
            return _MBAP.pack(tid, 0, len(absent) + 1, unit) + absent
        answer = self.handle_pdu(units, pdu, broadcast=False) if units else None
        if answer is None:
            return None
        return _MBAP.pack(tid, 0, len(answer) + 1, unit) + answer

    def handle_rtu(self, frame: bytes) -> bytes | None:
        """A Modbus RTU frame (unit, PDU, CRC): the answer frame, or None (silence)."""
        if len(frame) < 4 or _crc16(frame[:-2]).to_bytes(2, "big") != frame[-2:]:
            self.ignored += 1
            return None
        unit, pdu = frame[0], frame[1:-2]
        if unit == BROADCAST:
            self.handle_pdu(tuple(self.store.units), pdu, broadcast=True)
            return None
        if not self.store.has_unit(unit):
            self.ignored += 1
            return None
        if unit in self.silent_units:
            return None
        answer = self.handle_pdu((unit,), pdu, broadcast=False)
        return None if answer is None else with_crc(bytes([unit]) + answer)

    # ---- the application protocol -----------------------------------------------------------
    def handle_pdu(self, units: Sequence[int], pdu: bytes, broadcast: bool) -> bytes | None:
        """The answer PDU of request ``pdu`` for ``units`` (several: a broadcast, carried out
        on each and never answered); None for no answer."""
        if not pdu:
            return None
        fc = pdu[0]
        if fc not in FUNCTIONS:
            return None if broadcast else _exception(fc & 0x7F, ILLEGAL_FUNCTION)
        _, write = FUNCTIONS[fc]
        if broadcast:               # every unit carries out a write on its own; nobody answers
            if write:
                for unit in units:
                    self._write((unit,), pdu)
            return None
        return self._write(units, pdu) if write else self._read(units, pdu)

    def _read(self, units: Sequence[int], pdu: bytes) -> bytes:
        fc = pdu[0]
        if len(pdu) != 5:
            return _exception(fc, ILLEGAL_VALUE)
        address, count = _TWO.unpack_from(pdu, 1)
        if not 1 <= count <= MAX_READ[fc]:
            return _exception(fc, ILLEGAL_VALUE)
        if address + count > 0x10000:
            return _exception(fc, ILLEGAL_ADDRESS)
        got = self.store._serve(units, fc, address, count, None)
        if isinstance(got, int):
            return _exception(fc, got)
        data = _pack_bits(got) if fc in (1, 2) else struct.pack(f">{count}H", *got)
        return bytes([fc, len(data)]) + data

    def _write(self, units: Sequence[int], pdu: bytes) -> bytes:
        fc = pdu[0]
        parsed = self._write_values(pdu)
        if isinstance(parsed, int):
            return _exception(fc, parsed)
        address, values = parsed
        if address + len(values) > 0x10000:
            return _exception(fc, ILLEGAL_ADDRESS)
        got = self.store._serve(units, fc, address, len(values), values)
        if isinstance(got, int):
            return _exception(fc, got)
        return pdu if fc in (5, 6) else pdu[:5]

    @staticmethod
    def _write_values(pdu: bytes) -> tuple[int, list[Any]] | int:
        """A write request's address and entries, or the exception code its form earns."""
        fc = pdu[0]
        if fc in (5, 6):
            if len(pdu) != 5:
                return ILLEGAL_VALUE
            address, value = _TWO.unpack_from(pdu, 1)
            if fc == 5:
                if value not in (COIL_ON, COIL_OFF):
                    return ILLEGAL_VALUE
                return address, [value == COIL_ON]
            return address, [value]
        if len(pdu) < 6:
            return ILLEGAL_VALUE
        address, count = _TWO.unpack_from(pdu, 1)
        size = pdu[5]
        want = (count + 7) // 8 if fc == 15 else 2 * count
        if not 1 <= count <= MAX_WRITE[fc] or size != want or len(pdu) != 6 + size:
            return ILLEGAL_VALUE
        data = pdu[6:]
        if fc == 15:
            return address, list(_unpack_bits(data, count))
        return address, list(struct.unpack(f">{count}H", data))


def request_size(head: bytes) -> int | None:
    """The length of an RTU request frame starting with ``head`` (unit, function...), or None
    when it cannot be told from the bytes so far or the function's requests vary (then the
    silence after the frame ends it)."""
    if len(head) < 2:
        return None
    fc = head[1]
    if fc in (1, 2, 3, 4, 5, 6, 8):
        return 8
    if fc in (7, 11, 12, 17):
        return 4
    if fc in (15, 16):
        return 9 + head[6] if len(head) >= 7 else None
    return None
