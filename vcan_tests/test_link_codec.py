"""The link wire format: byte literals both ways, and every malformed input refused by name."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from chcos.comm.codec import (
    HEADER_SIZE,
    LinkMessage,
    MessageKind,
    decode,
    decode_value,
    encode,
    encode_value,
)
from chcos.errors import LinkError

# A command B1 -> A1 on link 7 at priority 60, seq 3, stamped 1 s after the epoch, value {"move":5}
COMMAND = LinkMessage(MessageKind.COMMAND, "B1", "A1", 7, 60, 3, 1_000_000_000, {"move": 5})
COMMAND_BYTES = (
    b"CH"  # magic
    b"\x01"  # version
    b"\x02"  # kind COMMAND
    b"\x00"  # flags
    b"\x3c"  # priority 60
    b"\x00\x00\x00\x07"  # link 7
    b"\x00\x00\x00\x00\x00\x00\x00\x03"  # seq 3
    b"\x00\x00\x00\x00\x3b\x9a\xca\x00"  # 1_000_000_000 ns
    b"\x02"  # src length
    b"\x02"  # dst length
    b"\x00\x00\x00\x0a"  # payload length 10
    b"B1A1"
    b'{"move":5}'
)


def test_header_is_32_bytes() -> None:
    assert HEADER_SIZE == 32


def test_encode_matches_the_documented_bytes() -> None:
    assert encode(COMMAND) == COMMAND_BYTES


def test_decode_of_the_documented_bytes() -> None:
    assert decode(COMMAND_BYTES) == COMMAND
    assert decode(bytearray(COMMAND_BYTES)) == COMMAND
    assert decode(memoryview(COMMAND_BYTES)) == COMMAND


def test_system_broadcast_with_empty_names_and_null_value() -> None:
    msg = LinkMessage(MessageKind.TABLE_UPDATE, "", "", 0, 99, 0, 0, None)
    data = encode(msg)
    assert data == (
        b"CH\x01\x06\x00\x63" + b"\x00" * 4 + b"\x00" * 8 + b"\x00" * 8 + b"\x00\x00"
        b"\x00\x00\x00\x04null"
    )
    assert decode(data) == msg


def test_unicode_names_and_values_round_trip() -> None:
    msg = LinkMessage(MessageKind.SENSORY, "Ä1", "B₂", 1, 0, 2**64 - 1, 2**64 - 1, ["°C", 1.5])
    assert decode(encode(msg)) == msg


def test_tuple_values_arrive_as_lists() -> None:
    msg = LinkMessage(MessageKind.STATUS, "a", "b", 1, 1, 1, 1, (1, 2))
    assert decode(encode(msg)).value == [1, 2]


def test_droppable_kinds() -> None:
    assert {k for k in MessageKind if k.droppable} == {MessageKind.SENSORY, MessageKind.STATUS}


def _patched(offset: int, new: bytes) -> bytes:
    return COMMAND_BYTES[:offset] + new + COMMAND_BYTES[offset + len(new) :]


@pytest.mark.parametrize(
    ("data", "fragment"),
    [
        (b"", "at least a 32-byte header"),
        (COMMAND_BYTES[:31], "at least a 32-byte header"),
        (_patched(0, b"XX"), "magic"),
        (_patched(2, b"\x02"), "version: expected 1, got 2"),
        (_patched(3, b"\x00"), "kind: expected a code 1..12, got 0"),
        (_patched(3, b"\x0d"), "kind: expected a code 1..12, got 13"),
        (_patched(4, b"\x01"), "flags: expected 0"),
        (_patched(5, b"\x64"), "priority: expected 0..99, got 100"),
        (COMMAND_BYTES[:-1], "truncated"),
        (COMMAND_BYTES + b"\x00", "trailing bytes"),
        (_patched(26, b"\x03"), "truncated"),
        (_patched(32, b"\xff"), "source task: expected a UTF-8 name"),
        (_patched(34, b"\xc3"), "destination task: expected a UTF-8 name"),
        (_patched(36, b"\xff"), "payload: expected UTF-8 JSON"),
        (_patched(36, b"X"), "payload: expected JSON"),
    ],
)
def test_malformed_input_is_refused_by_name(data: bytes, fragment: str) -> None:
    with pytest.raises(LinkError, match=fragment):
        decode(data)


def test_empty_and_non_standard_json_payloads_are_refused() -> None:
    with pytest.raises(LinkError, match="expected JSON"):
        decode_value(b"")
    with pytest.raises(LinkError, match="NaN is not JSON"):
        decode_value(b"NaN")
    with pytest.raises(LinkError, match="Infinity is not JSON"):
        decode_value(b"[Infinity]")


@pytest.mark.parametrize(
    ("changes", "fragment"),
    [
        ({"priority": 100}, "priority: expected 0..99, got 100"),
        ({"priority": -1}, "priority: expected 0..99"),
        ({"priority": True}, "priority: expected an integer"),
        ({"link": 2**32}, "link id"),
        ({"seq": -1}, "sequence number"),
        ({"timestamp_ns": 2**64}, "timestamp"),
        ({"src": "x" * 256}, "source task: task name is 256 UTF-8 bytes"),
        ({"dst": 5}, "destination task: expected a task name string"),
        ({"value": float("nan")}, "value: expected JSON data"),
        ({"value": {1: object()}}, "value: expected JSON data"),
        ({"value": b"raw"}, "value: expected JSON data"),
        ({"kind": 99}, "kind: expected one of"),
    ],
)
def test_bad_messages_are_refused_by_name(changes: dict[str, object], fragment: str) -> None:
    fields = dict(COMMAND.__dict__)
    fields.update(changes)
    with pytest.raises(LinkError, match=fragment):
        encode(LinkMessage(**fields))


def test_encode_value_is_compact_utf8() -> None:
    assert encode_value({"a": [1, "é"]}) == '{"a":[1,"é"]}'.encode()


json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**63)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner),
    max_leaves=12,
)


@given(
    kind=st.sampled_from(list(MessageKind)),
    src=st.text(max_size=60),
    dst=st.text(max_size=60),
    link=st.integers(0, 2**32 - 1),
    priority=st.integers(0, 99),
    seq=st.integers(0, 2**64 - 1),
    stamp=st.integers(0, 2**64 - 1),
    value=json_values,
)
def test_round_trip(
    kind: MessageKind,
    src: str,
    dst: str,
    link: int,
    priority: int,
    seq: int,
    stamp: int,
    value: object,
) -> None:
    msg = LinkMessage(kind, src, dst, link, priority, seq, stamp, value)
    data = encode(msg)
    assert decode(data) == msg
    # every strict prefix is refused, never mis-decoded
    for cut in (0, HEADER_SIZE - 1, len(data) - 1):
        with pytest.raises(LinkError):
            decode(data[:cut])
