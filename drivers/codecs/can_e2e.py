"""can_e2e - what a CAN map says of a DBC message beyond the DBC (``[[bus.message]]``: cycle
time, rolling counter, checksum) and the pure coding of counters and checksums into payloads.

A map names a message of its bus's DBC and may give it:

- ``cycle_time`` (seconds; default the DBC's ``GenMsgCycleTime``; 0: event-driven),
- ``counter = "SIGNAL"``: a rolling counter, 0, 1, ... 2**length - 1, 0, ... incremented per
  frame sent, checked on receive (each frame one more than the last),
- ``checksum = { signal = "SIGNAL", algorithm = ... }`` with ``algorithm`` one of
  :class:`Algorithm` (``"python"`` with ``function = "module:callable"``).

The checksum covers the payload bytes in order, the counter already in place, leaving out the
bytes the checksum signal fills entirely; bits of the checksum signal that share a byte with
other signals count as 0. ``xor``: the XOR of those bytes; ``sum``: their sum; ``crc8-sae-j1850``
(poly 0x1D, init 0xFF, xor-out 0xFF) and ``crc8-autosar`` (poly 0x2F, init 0xFF, xor-out 0xFF)
through crccheck's ``Crc8SaeJ1850`` / ``Crc8Autosar``; each result cut to the signal's length.
``python``: ``callable(frame_id, payload)`` returns the value, ``payload`` the whole frame with
the checksum signal's bits 0. Nothing here does I/O; a :class:`Protection` is built once per
message and used by the driver and the simulated ECU alike.
"""

from __future__ import annotations

import enum
import importlib
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from crccheck.crc import Crc8Autosar, Crc8SaeJ1850

#: Keys of one ``[[bus.message]]`` table.
MESSAGE_KEYS = ("name", "cycle_time", "counter", "checksum")
#: Keys of its ``checksum`` table.
CHECKSUM_KEYS = ("signal", "algorithm", "function")
#: Longest counter or checksum signal coded by lookup tables (longer ones go through cantools).
TABLE_BITS = 8


class Algorithm(enum.StrEnum):
    """How a checksum signal is computed (see the module doc)."""

    XOR = "xor"
    SUM = "sum"
    CRC8_SAE_J1850 = "crc8-sae-j1850"
    CRC8_AUTOSAR = "crc8-autosar"
    PYTHON = "python"


Hook = Callable[[int, bytes], int]


@dataclass(frozen=True)
class ChecksumSpec:
    """A message's checksum: its signal, its algorithm, the hook ``module:callable`` of
    ``python``."""

    signal: str
    algorithm: Algorithm
    function: str = ""


@dataclass(frozen=True)
class MessageSpec:
    """What the map adds to one DBC message: ``cycle_time`` in seconds (None: the map does not
    say; 0.0: event-driven), the counter signal, the checksum; ``key`` is where the map said it
    (``bus[0].message[1]``)."""

    name: str
    cycle_time: float | None = None
    counter: str | None = None
    checksum: ChecksumSpec | None = None
    key: str = ""


def load_hook(ref: str) -> Hook:
    """The checksum callable ``module:callable`` names. Raises ValueError saying why it
    cannot be had."""
    module, colon, name = ref.partition(":")
    if not colon or not module or not name.isidentifier():
        raise ValueError(f"expected \"module:callable\", got {ref!r}")
    try:
        mod = importlib.import_module(module)
    except Exception as exc:  # the user's module failed to import: say how
        raise ValueError(f"cannot import {module}: {type(exc).__name__}: {exc}") from exc
    fn = getattr(mod, name, None)
    if not callable(fn):
        raise ValueError(f"{module} has no callable {name}")
    return fn  # type: ignore[no-any-return]


def _checksum_spec(value: Any, key: str) -> tuple[ChecksumSpec | None, list[str]]:
    if not isinstance(value, Mapping):
        return None, [f"{key}: expected {{ signal = \"SIGNAL\", algorithm = \"...\" }}, "
                      f"got {value!r}"]
    errs = [f"{key}.{k}: unknown key; valid keys: {', '.join(CHECKSUM_KEYS)}"
            for k in value if k not in CHECKSUM_KEYS]
    sig, algo, fn = value.get("signal"), value.get("algorithm"), value.get("function", "")
    if not isinstance(sig, str) or not sig:
        errs.append(f"{key}.signal: expected a signal name, got {sig!r}")
    try:
        algorithm = Algorithm(str(algo))
    except ValueError:
        errs.append(f"{key}.algorithm: expected one of "
                    f"{', '.join(a.value for a in Algorithm)}, got {algo!r}")
        return None, errs
    if algorithm is Algorithm.PYTHON:
        try:
            load_hook(fn if isinstance(fn, str) else repr(fn))
        except ValueError as exc:
            errs.append(f"{key}.function: {exc}")
    elif "function" in value:
        errs.append(f"{key}.function: only for algorithm \"python\"")
    if errs:
        return None, errs
    return ChecksumSpec(str(sig), algorithm, str(fn)), []


def parse_messages(options: Mapping[str, Any], bus_key: str,
                   dbc: Any) -> tuple[dict[str, MessageSpec], list[str]]:
    """The ``message`` tables of a bus's options, checked against ``dbc`` (the loaded DBC, or
    None when it cannot be loaded: then only their form): the specs by message name, and the
    errors, each naming its key (``bus[0].message[1].counter: ...``)."""
    items = options.get("message", [])
    if not isinstance(items, list):
        return {}, [f"{bus_key}.message: expected [[bus.message]] tables, got {items!r}"]
    specs: dict[str, MessageSpec] = {}
    errs: list[str] = []
    for i, item in enumerate(items):
        key = f"{bus_key}.message[{i}]"
        if not isinstance(item, Mapping):
            errs.append(f"{key}: expected a table, got {item!r}")
            continue
        errs += [f"{key}.{k}: unknown key; valid keys: {', '.join(MESSAGE_KEYS)}"
                 for k in item if k not in MESSAGE_KEYS]
        name = item.get("name")
        if not isinstance(name, str) or not name:
            errs.append(f"{key}.name: expected a DBC message name, got {name!r}")
            continue
        if name in specs:
            errs.append(f"{key}.name: {name} is described twice (also {specs[name].key})")
            continue
        cycle = item.get("cycle_time")
        if cycle is not None and (isinstance(cycle, bool) or not isinstance(cycle, int | float)
                                  or not math.isfinite(cycle) or not 0 <= cycle <= 3600):
            errs.append(f"{key}.cycle_time: expected seconds 0..3600 (0: event-driven), "
                        f"got {cycle!r}")
            cycle = None
        counter = item.get("counter")
        if counter is not None and (not isinstance(counter, str) or not counter):
            errs.append(f"{key}.counter: expected a signal name, got {counter!r}")
            counter = None
        checksum = None
        if "checksum" in item:
            checksum, more = _checksum_spec(item["checksum"], f"{key}.checksum")
            errs += more
        spec = MessageSpec(name, None if cycle is None else float(cycle), counter, checksum, key)
        specs[name] = spec
        if dbc is not None:
            errs += _against_dbc(spec, dbc)
    return specs, errs


def _against_dbc(spec: MessageSpec, dbc: Any) -> list[str]:
    """Errors of ``spec`` against the DBC: the message and its counter and checksum signals
    exist, fit what chcos codes (unsigned, at most 32 bits, not multiplexed, two apart)."""
    try:
        msg = dbc.get_message_by_name(spec.name)
    except KeyError:
        return [f"{spec.key}.name: no message {spec.name!r} in the DBC; expected one of: "
                f"{', '.join(m.name for m in dbc.messages)}"]
    names = [s.name for s in msg.signals]
    errs = []
    protected = [(k, s) for k, s in (("counter", spec.counter),
                                     ("checksum.signal",
                                      spec.checksum.signal if spec.checksum else None)) if s]
    if protected and msg.is_multiplexed():
        errs.append(f"{spec.key}.name: {spec.name} is multiplexed: chcos codes counters and "
                    f"checksums of plain messages only")
    for k, sig_name in protected:
        if sig_name not in names:
            errs.append(f"{spec.key}.{k}: no signal {sig_name!r} in message {spec.name}; "
                        f"expected one of: {', '.join(names)}")
            continue
        sig = msg.get_signal_by_name(sig_name)
        if sig.is_signed or sig.is_float or sig.length > 32:
            errs.append(f"{spec.key}.{k}: {sig_name} is {'signed' if sig.is_signed else 'a float' if sig.is_float else f'{sig.length} bits'}; "  # noqa: E501
                        f"expected an unsigned integer signal of at most 32 bits")
    if len(protected) == 2 and protected[0][1] == protected[1][1]:
        errs.append(f"{spec.key}.checksum.signal: {protected[1][1]} is the counter too")
    return errs


def cycle_of(spec: MessageSpec | None, dbc_message: Any) -> float | None:
    """Seconds between two frames of a message: the map's ``cycle_time``, else the DBC's
    ``GenMsgCycleTime``; None when event-driven (0 or not given)."""
    if spec is not None and spec.cycle_time is not None:
        return spec.cycle_time or None
    ms = dbc_message.cycle_time
    return ms / 1000.0 if ms else None


class _Field:
    """One unsigned signal of a message as bits of the payload (an int, little-endian byte
    order): its mask, and a value's bits by lookup (up to :data:`TABLE_BITS`) or by cantools."""

    def __init__(self, message: Any, name: str) -> None:
        self._message = message
        self.name = name
        self.length = int(message.get_signal_by_name(name).length)
        self.modulo = 1 << self.length
        self._zeros = {s.name: 0 for s in message.signals}
        self.mask = self.place(self.modulo - 1)
        self._table: list[int] | None = None
        self._back: dict[int, int] | None = None
        if self.length <= TABLE_BITS:
            self._table = [self.place(v) for v in range(self.modulo)]
            self._back = {bits: v for v, bits in enumerate(self._table)}

    def place(self, value: int) -> int:
        """``value``'s bits where the signal lies (every other bit 0)."""
        table: list[int] | None = getattr(self, "_table", None)
        if table is not None:
            return table[value]
        raw = self._message.encode({**self._zeros, self.name: value}, scaling=False,
                                   strict=False)
        return int.from_bytes(raw, "little")

    def read(self, payload: int, data: bytes) -> int:
        """The signal's value in ``payload`` (``data`` as an int)."""
        if self._back is not None:
            return self._back[payload & self.mask]
        return int(self._message.decode(data, scaling=False, decode_choices=False)[self.name])


class Protection:
    """The counter and checksum of one DBC message (see the module doc): :meth:`stamp` puts
    them into a payload to send, :meth:`check` reads them back from one received."""

    def __init__(self, message: Any, spec: MessageSpec) -> None:
        self.spec = spec
        self.frame_id = int(message.frame_id)
        self.length = int(message.length)
        self.counter = _Field(message, spec.counter) if spec.counter else None
        self.checksum = _Field(message, spec.checksum.signal) if spec.checksum else None
        self._algorithm = spec.checksum.algorithm if spec.checksum else None
        self._hook = (load_hook(spec.checksum.function)
                      if spec.checksum and spec.checksum.algorithm is Algorithm.PYTHON else None)
        if self.checksum is not None:
            mask = self.checksum.mask.to_bytes(self.length, "little")
            #: the payload bytes the checksum covers, and the bits of each it keeps
            self._covered = tuple((i, 0xFF & ~m) for i, m in enumerate(mask) if m != 0xFF)

    @property
    def modulo(self) -> int:
        """How many counter values there are (1 without a counter)."""
        return self.counter.modulo if self.counter is not None else 1

    def compute(self, data: bytes) -> int:
        """The checksum ``data`` (a whole payload) should carry."""
        assert self.checksum is not None
        if self._hook is not None:
            cleared = int.from_bytes(data, "little") & ~self.checksum.mask
            value = int(self._hook(self.frame_id, cleared.to_bytes(self.length, "little")))
        else:
            covered = bytes(data[i] & keep for i, keep in self._covered)
            match self._algorithm:
                case Algorithm.XOR:
                    value = 0
                    for b in covered:
                        value ^= b
                case Algorithm.SUM:
                    value = sum(covered)
                case Algorithm.CRC8_SAE_J1850:
                    value = int(Crc8SaeJ1850.calc(covered))
                case _:
                    value = int(Crc8Autosar.calc(covered))
        return value & (self.checksum.modulo - 1)

    def stamp(self, data: bytes, counter: int) -> bytes:
        """``data`` with the counter set to ``counter`` (modulo its range) and the checksum
        computed over the result."""
        payload = int.from_bytes(data, "little")
        if self.counter is not None:
            payload = (payload & ~self.counter.mask) | self.counter.place(
                counter % self.counter.modulo)
        out = payload.to_bytes(self.length, "little")
        if self.checksum is None:
            return out
        payload = (payload & ~self.checksum.mask) | self.checksum.place(self.compute(out))
        return payload.to_bytes(self.length, "little")

    def check(self, data: bytes) -> tuple[int | None, str]:
        """What a received payload carries: its counter (None without one) and why its
        checksum is wrong ("" if right or there is none)."""
        payload = int.from_bytes(data, "little")
        counter = None if self.counter is None else self.counter.read(payload, data)
        if self.checksum is None:
            return counter, ""
        got = self.checksum.read(payload, data)
        want = self.compute(data)
        if got == want:
            return counter, ""
        return counter, (f"checksum {self.checksum.name} is 0x{got:X}, expected 0x{want:X} "
                         f"({self.spec.checksum.algorithm.value if self.spec.checksum else ''})")


class CounterCheck:
    """The receiving side of a rolling counter: each frame's counter one more than the last
    (modulo); the first frame, and the first after :meth:`reset`, only sets the base."""

    def __init__(self, modulo: int) -> None:
        self.modulo = modulo
        self._last: int | None = None

    def reset(self) -> None:
        """Forget the last counter (the sender restarted, or the frames stopped)."""
        self._last = None

    def next(self, counter: int) -> str:
        """Take ``counter``; why it is wrong ("" if it follows the last)."""
        last, self._last = self._last, counter
        if last is None or counter == (last + 1) % self.modulo:
            return ""
        if counter == last:
            return f"counter stuck at {counter}"
        return f"counter {counter} after {last} (expected {(last + 1) % self.modulo})"
