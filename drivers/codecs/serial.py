"""serial - the pure codec of the ``serial`` bus: line and binary framers, checksums, hex, the
command encoding of actuators and the checks of the protocol options. No I/O: used by the
serial driver (:mod:`drivers.serial_line`) and by the simulated serial devices.

Line protocol: each line matched against a regular expression with named groups (numbers as an
instrument writes them, see :func:`parse_number`). Binary protocol: ``sync`` + a :mod:`struct`
payload + an optional one-byte checksum (``sum8``/``xor8``) over the payload.
"""

from __future__ import annotations

import math
import re
import struct
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

COMMON_OPTIONS = ("url", "baudrate", "protocol", "poll", "reconnect_min", "reconnect_max")
LINE_OPTIONS = ("pattern", "eol", "encoding", "max_line")
BINARY_OPTIONS = ("sync", "struct", "fields", "checksum")
CHECKSUMS = ("none", "sum8", "xor8")
INT_CODES = set("bBhHiIlLqQnN")

Event = tuple[str, Any]   # ("values", {name: value}) or (error kind, detail)


def checksum(kind: str, payload: bytes) -> bytes:
    """The checksum byte(s) of ``payload``: b"" for none, one byte for sum8/xor8."""
    if kind == "sum8":
        return bytes([sum(payload) & 0xFF])
    if kind == "xor8":
        x = 0
        for b in payload:
            x ^= b
        return bytes([x])
    return b""


def parse_hex(text: str) -> bytes:
    """``"AA 55"`` -> b"\\xaa\\x55"; raises ValueError."""
    return bytes.fromhex(text)


class LineFramer:
    """Bytes in, decoded lines out: each complete line matched against ``pattern``."""

    def __init__(self, pattern: str, eol: str = "\n", encoding: str = "ascii",
                 max_line: int = 1024, text_groups: Iterable[str] = ()) -> None:
        self.pattern = re.compile(pattern)
        self.text_groups = frozenset(text_groups)
        self.eol = eol.encode(encoding)
        self.encoding = encoding
        self.max_line = max_line
        self._buf = bytearray()

    def feed(self, data: bytes) -> list[Event]:
        """Append ``data``; return an event per complete line (empty lines are skipped)."""
        self._buf += data
        events: list[Event] = []
        while True:
            idx = self._buf.find(self.eol)
            if idx < 0:
                if len(self._buf) > self.max_line:
                    events.append(("garbage", f"{len(self._buf)} bytes without an end of line"))
                    self._buf.clear()
                return events
            raw = bytes(self._buf[:idx])
            del self._buf[:idx + len(self.eol)]
            if raw.rstrip(b"\r"):
                events.append(self._line(raw.rstrip(b"\r")))

    def _line(self, raw: bytes) -> Event:
        try:
            text = raw.decode(self.encoding)
        except UnicodeDecodeError:
            return "garbage", f"line {raw[:40]!r} is not {self.encoding}"
        m = self.pattern.fullmatch(text)
        if m is None:
            return "garbage", f"line {text[:80]!r} does not match {self.pattern.pattern!r}"
        values: dict[str, Any] = {}
        for name, val in m.groupdict().items():
            if val is None:
                continue
            if name in self.text_groups:
                values[name] = val
                continue
            number = parse_number(val)
            if number is None:
                return "malformed", (f"line {text[:80]!r}: group {name} = {val[:40]!r} is no "
                                     f"finite decimal number")
            values[name] = number
        return "values", values


_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def parse_number(text: str) -> float | None:
    """A decimal number as an instrument writes it (``-12.5``, ``1e3``, ``.5``, surrounding
    blanks allowed), or None: ``nan``, ``inf``, ``1_000``, hex, non-ASCII digits and numbers
    too large for a float (``1e999``) are no readings."""
    text = text.strip()
    if not _DECIMAL.fullmatch(text):
        return None
    value = float(text)
    return value if math.isfinite(value) else None


class BinaryFramer:
    """Bytes in, decoded frames out: ``sync`` + struct payload + optional checksum byte."""

    MAX_RUN = 1024

    def __init__(self, sync: bytes, fmt: str, fields: Sequence[str], check: str = "none") -> None:
        self.sync = sync
        self.struct = struct.Struct(fmt)
        self.fields = list(fields)
        self.check = check
        self.frame_len = len(sync) + self.struct.size + len(checksum(check, b""))
        self._buf = bytearray()
        self._skipped = 0
        self._absorb = 0

    def feed(self, data: bytes) -> list[Event]:
        """Append ``data``; return an event per frame and per run of skipped bytes.

        A run of bytes that are no frame is reported once, when the next sync ends it (or every
        ``MAX_RUN`` bytes), however the bytes were split over reads. The rest of a frame that
        failed its checksum is not reported again as garbage."""
        self._buf += data
        events: list[Event] = []
        while True:
            idx = self._buf.find(self.sync)
            if idx < 0:
                keep = self._sync_prefix_len()
                self._skip(len(self._buf) - keep)
                if self._skipped >= self.MAX_RUN:
                    events.append(self._garbage())
                return events
            self._skip(idx)
            if self._skipped:
                events.append(self._garbage())
            if len(self._buf) < self.frame_len:
                return events
            start = len(self.sync)
            payload = bytes(self._buf[start:start + self.struct.size])
            got = bytes(self._buf[start + self.struct.size:self.frame_len])
            if got != checksum(self.check, payload):
                events.append(("checksum", f"frame {bytes(self._buf[:self.frame_len]).hex()}: "
                                           f"{self.check} checksum mismatch"))
                del self._buf[:1]
                self._absorb = self.frame_len - 1
                continue
            del self._buf[:self.frame_len]
            self._absorb = 0
            items = self.struct.unpack(payload)
            values = {f: v for f, v in zip(self.fields, items, strict=True) if f != "_"}
            bad = [f for f, v in values.items() if isinstance(v, float) and not math.isfinite(v)]
            if bad:
                events.append(("malformed", f"frame {payload.hex()}: field {bad[0]} is "
                                            f"{values[bad[0]]}, not a finite number"))
                continue
            events.append(("values", values))

    def _sync_prefix_len(self) -> int:
        """How many trailing bytes of the buffer could be the start of a sync."""
        for n in range(min(len(self.sync) - 1, len(self._buf)), 0, -1):
            if self._buf.endswith(self.sync[:n]):
                return n
        return 0

    def _skip(self, n: int) -> None:
        if n <= 0:
            return
        del self._buf[:n]
        absorbed = min(n, self._absorb)
        self._absorb -= absorbed
        self._skipped += n - absorbed

    def _garbage(self) -> Event:
        n, self._skipped = self._skipped, 0
        return "garbage", f"{n} bytes that are no frame (sync {self.sync.hex()})"


def num_ok(v: object, lo: float, hi: float) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and lo < v <= hi


def check_line_bus(key: str, o: Mapping[str, Any]) -> list[str]:
    errs: list[str] = []
    pat = o.get("pattern")
    if not isinstance(pat, str):
        return [f"{key}.pattern: expected a regular expression with named groups, got {pat!r}"]
    try:
        if not re.compile(pat).groupindex:
            errs.append(f"{key}.pattern: expected at least one named group (?P<name>...)")
    except re.error as exc:
        errs.append(f"{key}.pattern: invalid regular expression: {exc}")
    enc = o.get("encoding", "ascii")
    try:
        str(o.get("eol", "\n")).encode(str(enc))
    except LookupError:
        errs.append(f"{key}.encoding: unknown encoding {enc!r}")
    if not isinstance(o.get("eol", "\n"), str) or not o.get("eol", "\n"):
        errs.append(f"{key}.eol: expected a non-empty string, got {o.get('eol')!r}")
    ml = o.get("max_line", 1024)
    if not isinstance(ml, int) or isinstance(ml, bool) or ml < 16:
        errs.append(f"{key}.max_line: expected an integer >= 16, got {ml!r}")
    return errs


MAX_FRAME = 4096   # bytes in a binary frame's struct payload


def struct_of(fmt: object) -> struct.Struct:
    """``struct.Struct(fmt)`` for a device map's ``struct`` string. Raises struct.error with
    what was expected: a string of ASCII format characters, a payload of at most MAX_FRAME
    bytes."""
    if not isinstance(fmt, str) or not fmt.isascii():
        raise struct.error("expected a string of ASCII struct format characters")
    try:
        st = struct.Struct(fmt)
    except (ValueError, OverflowError, MemoryError) as exc:
        raise struct.error(str(exc)) from None
    if st.size > MAX_FRAME:
        raise struct.error(f"payload of {st.size} bytes; expected at most {MAX_FRAME}")
    return st


def check_binary_bus(key: str, o: Mapping[str, Any]) -> list[str]:
    errs: list[str] = []
    try:
        if not parse_hex(str(o.get("sync", ""))):
            errs.append(f"{key}.sync: expected hex bytes such as \"AA 55\", got {o.get('sync')!r}")
    except ValueError:
        errs.append(f"{key}.sync: expected hex bytes such as \"AA 55\", got {o.get('sync')!r}")
    fields = o.get("fields")
    if not (isinstance(fields, list) and fields and all(isinstance(f, str) for f in fields)):
        errs.append(f"{key}.fields: expected a list of field names, got {fields!r}")
        fields = None
    try:
        st = struct_of(o.get("struct"))
        n = len(st.unpack(bytes(st.size)))
        if fields is not None and n != len(fields):
            errs.append(f"{key}.fields: struct {st.format!r} has {n} items, expected as many "
                        f"names, got {len(fields)}")
    except struct.error as exc:
        errs.append(f"{key}.struct: expected a struct format, got {o.get('struct')!r}: {exc}")
    if o.get("checksum", "none") not in CHECKSUMS:
        errs.append(f"{key}.checksum: expected one of {', '.join(CHECKSUMS)}, "
                    f"got {o.get('checksum')!r}")
    return errs




def encode_command(options: Mapping[str, Any], address: Mapping[str, Any], value: Any) -> bytes:
    """The bytes that set an actuator with ``address`` on a serial bus with ``options`` to
    ``value``: line, ``format`` with ``value`` and the bus's ``eol``; binary, sync + payload
    (``prefix`` + the value packed with ``struct``, rounded for an integer code) + checksum.
    Raises struct.error, ValueError, TypeError, UnicodeEncodeError or OverflowError when the
    value does not fit."""
    enc = str(options.get("encoding", "ascii"))
    if options.get("protocol") != "binary":
        eol = str(options.get("eol", "\n")).encode(enc)
        return str(address["format"]).format(value=value).encode(enc) + eol
    fmt = str(address["struct"])
    v = round(float(value)) if fmt[-1] in INT_CODES else value
    payload = parse_hex(str(address.get("prefix", ""))) + struct.pack(fmt, v)
    return (parse_hex(str(options["sync"])) + payload
            + checksum(str(options.get("checksum", "none")), payload))
