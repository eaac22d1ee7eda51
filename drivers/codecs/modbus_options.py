"""modbus_options - the device-map keys of the Modbus buses as typed options: the
``modbus-tcp`` and ``modbus-rtu`` bus tables (:class:`TcpOptions`, :class:`RtuOptions`, with
the ``watchdog`` table), a device's ``address`` (:class:`ModbusAddress`) and the rules between
keys, parsed once by :mod:`chcos.devices.options` when a map is checked. Pure (no I/O): the
drivers (:mod:`drivers.modbus`), the simulated slaves and the importers read the same
dataclasses. What each key does under faults: ``docs/modbus-faults.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal

from chcos.devices import options as opts
from chcos.devices.options import REQUIRED, at_least, between, nonempty, option
from chcos.devices.spec import DeviceSpec
from drivers.codecs.modbus import (
    BIT_TABLES,
    BIT_TYPE,
    BROADCAST,
    FLOAT_MAX,
    INT_RANGES,
    MAX_REGISTERS,
    MAX_UNIT,
    REGISTER_TYPES,
    STRING,
    WORD_ORDERS,
    WRITABLE,
    Point,
    Table,
    unimplemented_value,
)

MAX_CONNECTIONS = 16   # the most connections a modbus-tcp bus may open for parallel polls
DEFAULT_POLL_PERIOD = 0.1   # s between two polls of a sensor
PROBE_PERIOD = 1.0          # s between liveness probes of a bus without sensors
ValueType = Literal["bool", "int16", "uint16", "int32", "uint32", "int64", "uint64", "float32",
                    "float64", "string"]
WordOrderName = Literal["ABCD", "CDAB", "BADC", "DCBA", "big", "little"]


# ---- checks ----------------------------------------------------------------------------------
def seconds(v: Any) -> str | None:
    """A check for a duration: a finite number of seconds > 0."""
    return opts.positive(v) and "a number of seconds > 0"


def tcp_port(v: Any) -> str | None:
    """A check for a TCP port."""
    return None if 1 <= v <= 65535 else "a TCP port 1..65535"


def unit_id(v: Any) -> str | None:
    """A check for a Modbus device id (0: broadcast)."""
    return None if 0 <= v <= MAX_UNIT else f"a Modbus device id 0..{MAX_UNIT}"


def connections(v: Any) -> str | None:
    """A check for ``connections``."""
    return None if 1 <= v <= MAX_CONNECTIONS else \
        f"an integer 1..{MAX_CONNECTIONS} (TCP connections a poll may use at once)"


def serial_port(v: Any) -> str | None:
    """A check for ``port`` of an RTU line."""
    return nonempty(v) and "a serial port (/dev/ttyUSB0, socket://host:port)"


def backoff_turns(v: Any) -> str | None:
    """A check for ``dead_unit_backoff``."""
    return None if v >= 1 else ("an integer >= 1 (the most poll periods between two tries of "
                                "a unit that does not answer)")


def host_name(v: Any) -> str | None:
    """A check for ``host``."""
    return nonempty(v) and "a host name or address"


# ---- the watchdog register ---------------------------------------------------------------------
@dataclass(frozen=True)
class WatchdogOptions:
    """A bus's watchdog register (``watchdog = {...}``): written every ``period`` s so the
    PLC's comm-loss logic sees the controller alive. ``value = "counter"`` writes 1, 2, ...
    (wrapping at 65536 on a holding register; 1, 0, 1... on a coil), an integer that value each
    time."""

    address: int = option(REQUIRED, doc="the register or coil", check=between(0, 0xFFFF))
    unit: int = option(1, doc="its unit", check=unit_id)
    table: Literal["holding", "coil"] = option("holding", doc="its table")
    period: float = option(1.0, unit="s", doc="between two writes", check=seconds)
    value: Literal["counter"] | int = option("counter", doc='"counter" or the integer written '
                                                        "each time")

    def problems(self) -> list[tuple[str, str]]:
        """A fixed value beyond what the table holds."""
        top = 1 if self.table == "coil" else 0xFFFF
        if self.value != "counter" and not (0 <= int(self.value) <= top):
            return [("value", f'"counter" or an integer 0..{top} for a {self.table}, got '
                              f"{self.value!r}")]
        return []

    def value_at(self, beat: int) -> int:
        """The value of the ``beat``-th write (0 first)."""
        if self.value != "counter":
            return int(self.value)
        return (beat + 1) % (2 if self.table == "coil" else 0x10000)

    def describe(self) -> str:
        """``unit 1 holding 900`` - for reasons."""
        return f"unit {self.unit} {self.table} {self.address}"


# ---- the buses ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class ModbusOptions:
    """What both Modbus kinds take (see :class:`TcpOptions`, :class:`RtuOptions`)."""

    timeout: float = option(1.0, unit="s", doc="per request: the longest wait for its answer",
                            check=seconds)
    retries: int = option(1, doc="repeats of a request that got no usable answer, at once, "
                                 "before it counts as unanswered", check=at_least(0))
    reconnect_delay: float = option(0.1, unit="s", doc="first reconnect back-off; doubled "
                                                       "after each failure", check=seconds)
    reconnect_delay_max: float = option(5.0, unit="s", doc="longest back-off", check=seconds)
    poll_period: float | None = option(
        None, unit="s", default_doc=f"{DEFAULT_POLL_PERIOD}", check=seconds,
        doc="default polling period of the sensors and of the read-back of an actuator whose "
            f"write failed; on a bus (or RTU unit) with no sensor the liveness probe's period "
            f"(default {PROBE_PERIOD})")
    watchdog: WatchdogOptions | None = option(
        None, type_doc="inline table",
        doc="a register written every `period` s so the PLC's comm-loss logic sees the "
            "controller alive: `{unit = 1, table = \"holding\", address, period = 1.0, value = "
            "\"counter\"}` (`table` also `\"coil\"`, `value` also an integer written each "
            "time); a counter writes 1, 2, ... (a coil toggles); a write not answered fails "
            "devices as any request, an exception answer fails the devices of its unit (see "
            "docs/modbus-faults.md)")
    direct: str = option("", doc="the name of an in-process simulated slave reached without a "
                                 "socket or serial port (written by `chcos run --virtual` and "
                                 "the pytest plugin; not for hand-written maps)")

    def probe_period(self) -> float:
        """Seconds between two liveness probes of the units no poll reads."""
        return self.poll_period if self.poll_period is not None else PROBE_PERIOD

    def sensor_period(self) -> float:
        """The default polling period of a sensor."""
        return self.poll_period if self.poll_period is not None else DEFAULT_POLL_PERIOD


ServerKind = Literal["device", "gateway"]


@dataclass(frozen=True)
class TcpOptions(ModbusOptions):
    """The options of a ``modbus-tcp`` bus."""

    host: str = option(REQUIRED, doc="server address", check=host_name)
    port: int = option(502, doc="server TCP port", check=tcp_port)
    connections: int = option(1, doc="TCP connections a poll of several requests spreads them "
                                     "over, all outstanding at once (a server taking fewer is "
                                     "polled over those)", check=connections)
    server: ServerKind | None = option(
        None, default_doc="`device` for one unit, `gateway` for several",
        doc="what answers at the address: one `device` (the unit id is not significant: its "
            "simulation answers any id) or a `gateway` to units behind it (an absent unit is "
            "exception 0x0B, and a unit that stops answering fails its own devices only)")

    def server_kind(self, units: set[int]) -> ServerKind:
        """``server``, or the default for a bus whose devices name ``units``."""
        if self.server is not None:
            return self.server
        return "gateway" if len(units) > 1 else "device"

    def link(self) -> str:
        """``host:port`` - for reasons."""
        return f"{self.host}:{self.port}"


@dataclass(frozen=True)
class RtuOptions(ModbusOptions):
    """The options of a ``modbus-rtu`` bus."""

    port: str = option(REQUIRED, doc="serial device or pyserial URL (`socket://host:port`)",
                       check=serial_port)
    baudrate: int = option(19200, doc="bit/s", check=at_least(1))
    parity: Literal["N", "E", "O"] = option("N", doc="parity")
    stopbits: Literal[1, 2] = option(1, doc="stop bits")
    bytesize: Literal[7, 8] = option(8, doc="data bits")
    dead_unit_backoff: int | None = option(
        None, type_doc="integer >= 1", default_doc="8, or more", check=backoff_turns,
        doc="the most poll periods between two tries of a unit that stopped answering (its "
            "requests are thinned out, the gaps doubling up to this); by default 8, raised so "
            "a dead unit's tries take at most a twentieth of the line's time; while another "
            "unit answers, the first gap already keeps to that share")
    line_guard: float = option(0.5, unit="s", check=seconds,
                               doc="how long after a request nobody answered the slaves may "
                                   "still be waiting for its answer and deaf to the next "
                                   "request (a stock libmodbus slave: its response timeout, "
                                   "0.5 s): the line is kept quiet that long from the request "
                                   "(nothing more when `timeout` is as long)")
    turnaround: float = option(0.1, unit="s", check=seconds,
                               doc="the silence kept after a broadcast write (unit 0), so that "
                                   "every slave has carried it out before the next request "
                                   "(the serial line specification's turnaround delay, "
                                   "typically 0.1 to 0.2 s)")

    def link(self) -> str:
        """The port - for reasons."""
        return self.port

    def guard_after_silence(self) -> float:
        """Seconds the line stays quiet after a request's timeout passed unanswered."""
        return max(0.0, self.line_guard - self.timeout)


# ---- a device's address ------------------------------------------------------------------------
@dataclass(frozen=True)
class ModbusAddress:
    """A device's ``address`` on a Modbus bus."""

    table: Table = option(REQUIRED, doc="`coil`, `discrete`, `holding` or `input`; actuators "
                                        "only `coil` or `holding`")
    address: int = option(REQUIRED, doc="protocol address, 0-based (register 40001 is "
                                        "`holding` 0)", check=between(0, 0xFFFF))
    unit: int = option(1, doc="unit (slave / device) id; 0 is a serial line's broadcast: "
                              "actuators only, written to every unit, never answered",
                       check=unit_id)
    type: ValueType | None = option(
        None, type_doc="string", default_doc="`bool` (bits), `uint16`",
        doc="`bool` for coils and discrete inputs; `int16 uint16 int32 uint32 int64 uint64 "
            "float32 float64` or `string` (with `count`) for registers")
    count: int | None = option(None, type_doc="integer 1..125", default_doc="none",
                               doc="registers of a `string` (two ASCII characters each, "
                                   "NUL-padded): the value is text")
    word_order: WordOrderName = option(
        "ABCD", doc="for 32/64-bit types, by the bytes of a 32-bit value A B C D (A most "
                    "significant): `ABCD` (high word first), `CDAB` (words swapped), `BADC` "
                    "(bytes swapped in each word), `DCBA` (both); `big` and `little` are "
                    "aliases of `ABCD` and `CDAB`; a 64-bit value follows the same rule over "
                    "its four words")
    poll_period: float | None = option(None, unit="s", default_doc="the bus's",
                                       doc="this sensor's polling period", check=seconds)
    scale_factor: int | None = option(
        None, default_doc="none", check=between(0, 0xFFFF),
        doc="the address of an int16 register of the same unit and table holding a power of "
            "ten (SunSpec's `sunssf`): the value is raw x 10^sf (then `scale` and `offset`), "
            "the factor read in the same request where it is next to the value, else in its "
            "own; 0x8000 there means not implemented")
    unimplemented: int | float | str | None = option(
        None, default_doc="none", type_doc="integer, float or string",
        nan=True,
        doc="the raw value meaning \"not implemented\", as a value or as the registers' bit "
            "pattern the way SunSpec publishes it (0x8000 for an int16, 0xFFFF for a uint16, "
            "0x7FC00000 or `nan` for a float32): such a reading is no value, the sensor fails "
            "with that reason")

    @property
    def value_type(self) -> str:
        """``type``, or the table's default."""
        if self.type is not None:
            return self.type
        return BIT_TYPE if self.table in BIT_TABLES else "uint16"

    @property
    def size(self) -> int:
        """Entries the value spans."""
        t = self.value_type
        if t == BIT_TYPE:
            return 1
        return (self.count or 0) if t == STRING else REGISTER_TYPES[t][1]

    def problems(self) -> list[tuple[str, str]]:
        """The rules between keys: the type against the table, a string's count, the address
        range the type spans, a scale factor and an unimplemented value that fit the type."""
        out: list[tuple[str, str]] = []
        t = self.value_type
        bits = self.table in BIT_TABLES
        if bits and t != BIT_TYPE:
            return [("type", f'"bool" (a {self.table} holds one bit), got {t!r}')]
        if not bits and t == BIT_TYPE:
            return [("type", f"one of {', '.join((*REGISTER_TYPES, STRING))} for a "
                             f"{self.table} register, got 'bool'")]
        if t == STRING and not (self.count is not None and 1 <= self.count <= MAX_REGISTERS):
            return [("count", f"an integer 1..{MAX_REGISTERS} (the registers of the string), "
                              f"got {self.count!r}")]
        if t != STRING and self.count is not None:
            out.append(("count", f"no count for a {t} (only a string has one), got "
                                 f"{self.count!r}"))
        size = self.size
        if self.address > 0x10000 - size:
            out.append(("address", f"an integer 0..{0x10000 - size} (a {t} spans {size} "
                                   f"entr{'y' if size == 1 else 'ies'}), got {self.address!r}"))
        out += self._scale_problems(t) + self._unimplemented_problems(t)
        return out

    def _scale_problems(self, t: str) -> list[tuple[str, str]]:
        sf = self.scale_factor
        if sf is None:
            return []
        if t not in INT_RANGES:
            return [("scale_factor", f"no scale factor for a {t} (integer types only), got "
                                     f"{sf!r}")]
        if self.address <= sf < self.address + self.size:
            return [("scale_factor", f"another register than the value's own "
                                     f"({self.address}..{self.address + self.size - 1}), got "
                                     f"{sf!r}")]
        return []

    def _unimplemented_problems(self, t: str) -> list[tuple[str, str]]:
        u = self.unimplemented
        if u is None:
            return []
        if t == BIT_TYPE:
            return [("unimplemented", f"no unimplemented value for a bit, got {u!r}")]
        if t == STRING:
            return [] if isinstance(u, str) else [
                ("unimplemented", f"text for a string, got {u!r}")]
        bits = 16 * REGISTER_TYPES[t][1]
        if t in INT_RANGES:
            lo, hi = INT_RANGES[t]
            top = 2 ** bits - 1 if lo < 0 else hi     # a signed type's bit pattern too
            return [] if isinstance(u, int) and lo <= u <= top else [
                ("unimplemented", f"a {t} value {lo}..{hi} or its bit pattern "
                                  f"0..0x{2 ** bits - 1:X}, got {u!r}")]
        if isinstance(u, int) and 0 <= u < 2 ** bits:     # the float's bit pattern
            return []
        return [] if isinstance(u, float) and (math.isnan(u) or abs(u) <= FLOAT_MAX[t]) else [
            ("unimplemented", f"a {t} value, nan or its bit pattern, got {u!r}")]


def address_rules(a: ModbusAddress, direction: str, kind: str) -> list[tuple[str, str]]:
    """The rules of a valid address that depend on the device and the bus kind: an actuator
    needs a writable table, unit 0 (broadcast) is a serial line's and takes writes only, a
    scale factor on an actuator must not be a string's. Each as ``(key, "<message>")``, the
    message as ``chcos check`` prints it after the key."""
    out: list[tuple[str, str]] = []
    if direction == "actuator" and a.table not in WRITABLE:
        out.append(("table", f"{a.table} is read-only; an actuator needs coil or holding"))
    if a.unit == BROADCAST:
        if kind != "modbus-rtu":
            out.append(("unit", "expected a unit id 1..247: unit 0 (broadcast) exists on a "
                                "serial line only; a Modbus TCP server is addressed by its IP "
                                "address (use its unit id, often 1 or 255)"))
        elif direction != "actuator":
            out.append(("unit", "expected a unit id 1..247 for a sensor: unit 0 (broadcast) "
                                "is written to every unit and never answered, so it cannot "
                                "be read"))
    return out


def point_of(device: DeviceSpec) -> Point:
    """The :class:`drivers.codecs.modbus.Point` of a device whose address is valid (parsed now
    if the map's check did not). Raises :class:`chcos.errors.ConfigError` for an invalid one."""
    a = address_of(device)
    return Point(device.name, a.unit, a.table, a.address, a.value_type,
                 WORD_ORDERS[a.word_order], a.count or 0, a.scale_factor,
                 unimplemented_value(a.value_type, a.unimplemented))


def address_of(device: DeviceSpec) -> ModbusAddress:
    """``device``'s typed address: the one the map's check parsed, or its table parsed now.
    Raises :class:`chcos.errors.ConfigError` naming every bad key."""
    if isinstance(device.addr, ModbusAddress):
        return device.addr
    return opts.parsed(ModbusAddress, device.address, f"{device.key}.address", device.file)
