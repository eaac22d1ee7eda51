"""codec - the wire format of chcos link messages (what one satellite sends another over Zenoh).

A message is a fixed 32-byte big-endian header, the source and destination task names, and a
payload::

    offset size field
    0      2    magic          b"CH"
    2      1    version        1 (WIRE_VERSION); any other value is refused
    3      1    kind           MessageKind code (1..12)
    4      1    flags          0 in version 1 (reserved; non-zero is refused)
    5      1    priority       link (message) priority 0..99, higher is more urgent (thesis 6.3)
    6      4    link id        u32, the Msgtab entry the message travels on (0 = system traffic)
    10     8    sequence       u64, per-link sequence number chosen by the sender
    18     8    timestamp      u64, nanoseconds since the Unix epoch at the sender
    26     1    src length     bytes of the UTF-8 source task name (0..255; 0 = the system itself)
    27     1    dst length     bytes of the UTF-8 destination task name (0..255; 0 = broadcast)
    28     4    payload length u32 bytes of payload
    32     ...  src name, dst name, payload; nothing may follow the payload

The payload is the message's value as compact UTF-8 JSON (``json.dumps(value,
separators=(",", ":"), allow_nan=False)``): ``None``, ``bool``, ``int``, ``float`` (finite only),
``str``, lists and objects with string keys. Tuples are sent as lists. Binary data must be encoded
by the caller (e.g. base64 text). The empty payload is not valid JSON and is refused; ``None``
encodes as ``null``.

Everything here is a pure function. Malformed input raises :class:`chcos.errors.LinkError` whose
message names the field that is wrong and what was expected.
"""

from __future__ import annotations

import enum
import json
import struct
from dataclasses import dataclass
from typing import Any

from chcos.errors import LinkError

MAGIC = b"CH"
WIRE_VERSION = 1
HEADER = struct.Struct(">2sBBBBIQQBBI")
HEADER_SIZE = HEADER.size  # 32
MAX_NAME_BYTES = 255
MAX_PAYLOAD_BYTES = 16 * 1024 * 1024
MAX_PRIORITY = 99
#: From this CHC-OS priority up, messages are sent express (never held back for batching).
EXPRESS_FROM = 75
_U32 = 0xFFFFFFFF
_U64 = 0xFFFFFFFFFFFFFFFF


class MessageKind(enum.IntEnum):
    """What a link message is, as the message, task and system managers see it.

    ``droppable`` kinds carry state where the newest value supersedes an older one (the thesis'
    "yesterday's newspaper"): the transport may drop them under congestion. Every other kind must
    arrive, so the transport blocks the sender rather than lose it.
    """

    SENSORY = 1  # sensory data flowing up the hierarchy
    COMMAND = 2  # a command flowing down (topen/tputc on a command link)
    COMPLETION = 3  # a command finished, normally or abnormally (value says which)
    PREEMPTION = 4  # the owner of a task lost it to a higher-priority command
    STATUS = 5  # periodic status / msgstat report
    TABLE_UPDATE = 6  # broadcast of a message-table change after an install
    INSTALL = 7  # host -> satellite: install a task
    SETPRI = 8  # host -> satellite: set a link priority
    INVOKE = 9  # host -> satellite: invoke a task
    QUERY = 10  # request for a piece of state (world model, tables)
    REPLY = 11  # the answer to a QUERY
    ERROR = 12  # a request failed; the value names why

    @property
    def droppable(self) -> bool:
        """True for kinds whose newest value supersedes older ones (sensory, status)."""
        return self in (MessageKind.SENSORY, MessageKind.STATUS)


@dataclass(frozen=True)
class LinkMessage:
    """One decoded link message. ``value`` is any JSON-representable Python value.

    ``src``/``dst`` are task names ('' = the system itself / broadcast); ``link`` is the Msgtab link
    id; ``priority`` is 0..99 (higher is more urgent); ``seq`` and ``timestamp_ns`` are set by the
    sender.
    """

    kind: MessageKind
    src: str
    dst: str
    link: int
    priority: int
    seq: int
    timestamp_ns: int
    value: Any = None


def _check_range(name: str, value: int, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise LinkError(f"link message {name}: expected an integer {low}..{high}, got {value!r}")
    if not low <= value <= high:
        raise LinkError(f"link message {name}: expected {low}..{high}, got {value}")


def _name_bytes(field: str, name: str) -> bytes:
    if not isinstance(name, str):
        raise LinkError(f"link message {field}: expected a task name string, got {name!r}")
    raw = name.encode("utf-8")
    if len(raw) > MAX_NAME_BYTES:
        raise LinkError(
            f"link message {field}: task name is {len(raw)} UTF-8 bytes, at most "
            f"{MAX_NAME_BYTES} expected"
        )
    return raw


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


# made once: json.dumps/json.loads with options build a new encoder/decoder on every call
_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False, ensure_ascii=False)
_DECODER = json.JSONDecoder(parse_constant=_no_constant)


def encode_value(value: Any) -> bytes:
    """The JSON payload bytes of ``value``; raises LinkError if it is not JSON-representable."""
    try:
        text = _ENCODER.encode(value)
    except (TypeError, ValueError) as exc:
        raise LinkError(
            f"link message value: expected JSON data (None, bool, int, finite float, str, list, "
            f"dict with str keys), got {type(value).__name__}: {exc}"
        ) from exc
    return text.encode("utf-8")


def decode_value(payload: bytes) -> Any:
    """The value of JSON payload bytes; raises LinkError if they are not UTF-8 JSON."""
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise LinkError(
            f"link message payload: expected UTF-8 JSON, bad byte at {exc.start}"
        ) from exc

    try:
        return _DECODER.decode(text)
    except ValueError as exc:
        raise LinkError(f"link message payload: expected JSON, {exc}") from exc


def encode(message: LinkMessage) -> bytes:
    """The wire bytes of ``message``.

    Raises LinkError if a field is out of range (priority 0..99, link u32, seq and timestamp u64,
    names up to 255 UTF-8 bytes) or the value is not JSON-representable.
    """
    try:
        kind = MessageKind(message.kind)
    except ValueError as exc:
        raise LinkError(
            f"link message kind: expected one of {[k.name for k in MessageKind]}, "
            f"got {message.kind!r}"
        ) from exc
    _check_range("priority", message.priority, 0, MAX_PRIORITY)
    _check_range("link id", message.link, 0, _U32)
    _check_range("sequence number", message.seq, 0, _U64)
    _check_range("timestamp", message.timestamp_ns, 0, _U64)
    src = _name_bytes("source task", message.src)
    dst = _name_bytes("destination task", message.dst)
    payload = encode_value(message.value)
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise LinkError(
            f"link message value: encoded to {len(payload)} bytes, at most {MAX_PAYLOAD_BYTES} "
            "expected"
        )
    header = HEADER.pack(
        MAGIC,
        WIRE_VERSION,
        int(kind),
        0,
        message.priority,
        message.link,
        message.seq,
        message.timestamp_ns,
        len(src),
        len(dst),
        len(payload),
    )
    return b"".join((header, src, dst, payload))


def decode(data: bytes | bytearray | memoryview) -> LinkMessage:
    """The message encoded in ``data``.

    Raises LinkError naming the problem: too short, wrong magic, unknown version, unknown kind,
    reserved flags set, priority above 99, lengths that do not match the data (truncated or
    trailing bytes), task names that are not UTF-8, a payload that is not JSON.
    """
    buf = bytes(data)
    if len(buf) < HEADER_SIZE:
        raise LinkError(
            f"link message: {len(buf)} bytes, at least a {HEADER_SIZE}-byte header expected"
        )
    (magic, version, kind_code, flags, priority, link, seq, stamp, src_len, dst_len, pay_len) = (
        HEADER.unpack_from(buf)
    )
    if magic != MAGIC:
        raise LinkError(f"link message magic: expected {MAGIC!r}, got {magic!r}")
    if version != WIRE_VERSION:
        raise LinkError(f"link message version: expected {WIRE_VERSION}, got {version}")
    try:
        kind = MessageKind(kind_code)
    except ValueError as exc:
        raise LinkError(
            f"link message kind: expected a code 1..{max(MessageKind)}, got {kind_code}"
        ) from exc
    if flags != 0:
        raise LinkError(f"link message flags: expected 0 in version {WIRE_VERSION}, got {flags}")
    if priority > MAX_PRIORITY:
        raise LinkError(f"link message priority: expected 0..{MAX_PRIORITY}, got {priority}")
    expected = HEADER_SIZE + src_len + dst_len + pay_len
    if len(buf) != expected:
        what = "truncated" if len(buf) < expected else "trailing bytes"
        raise LinkError(
            f"link message length: header says {expected} bytes, got {len(buf)} ({what})"
        )
    src_end = HEADER_SIZE + src_len
    dst_end = src_end + dst_len
    src = _decode_name("source task", buf[HEADER_SIZE:src_end])
    dst = _decode_name("destination task", buf[src_end:dst_end])
    value = decode_value(buf[dst_end:])
    return LinkMessage(kind, src, dst, link, priority, seq, stamp, value)


def _decode_name(field: str, raw: bytes) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise LinkError(f"link message {field}: expected a UTF-8 name, got {raw!r}") from exc


def encode_batch(encoded: list[bytes]) -> bytes:
    """Several encoded messages as one payload: they are simply concatenated (each header gives
    its message's length)."""
    return b"".join(encoded)


def decode_batch(data: bytes | bytearray | memoryview) -> list[LinkMessage]:
    """The messages of a payload made by :func:`encode_batch` (a single message is a batch of
    one). Raises LinkError like :func:`decode`, naming the message's position in the batch."""
    buf = bytes(data)
    out: list[LinkMessage] = []
    i = 0
    while i < len(buf):
        if len(buf) - i < HEADER_SIZE:
            raise LinkError(f"link batch: message {len(out)} at byte {i}: {len(buf) - i} bytes, "
                            f"at least a {HEADER_SIZE}-byte header expected")
        src_len, dst_len, pay_len = _LENGTHS.unpack_from(buf, i + 26)
        end = i + HEADER_SIZE + src_len + dst_len + pay_len
        try:
            out.append(decode(buf[i:end]))
        except LinkError as exc:
            raise LinkError(f"link batch: message {len(out)} at byte {i}: {exc}") from exc
        i = end
    return out


_LENGTHS = struct.Struct(">BBI")
