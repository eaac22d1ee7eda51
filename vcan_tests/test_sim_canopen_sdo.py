"""The simulated node's SDO server against a client scripted on the wire (CiA 301 byte layouts
written here, not encoded by canopen or chcos): every refused transfer is an abort with the code
a device sends and the index and sub-index of the transfer it ends; segmented and block
transfers both ways (block with its CRC, checked by a bit-by-bit CRC-16-CCITT written here);
the protocol's own errors (toggle, stray segments, unknown commands, sequence numbers,
timeouts on the node's clock). The last tests use canopen's SDO client, an independent
implementation, for the block transfers over python-can's virtual bus."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from typing import Any

import canopen
import pytest

from vcan_tests.netutil import unique_channel
from vcan_tests.support_cosim import (
    STRICT_EDS,
    Script,
    abort,
    crc_ccitt,
    download,
    upload,
)

NODE = 9


@pytest.fixture
def wire() -> Script:
    return Script(NODE)


# -- what exists and what may be accessed ------------------------------------------------------


@pytest.mark.parametrize(("request_", "answer"), [
    # sub-index 1 of a plain variable: "sub-index does not exist", not the variable's value
    (upload(0x2008, 1), abort(0x2008, 1, 0x06090011)),
    (upload(0x1018, 7), abort(0x1018, 7, 0x06090011)),         # a record's missing sub-index
    (upload(0x6099, 0), abort(0x6099, 0, 0x06020000)),         # an object the EDS lacks
    (upload(0x2001, 0), abort(0x2001, 0, 0x06010001)),         # read of a write-only object
    (download(0x2008, 0, bytes(4)), abort(0x2008, 0, 0x06010002)),   # write of read-only
    (download(0x2002, 0, bytes(4)), abort(0x2002, 0, 0x06010002)),   # write of a constant
    (download(0x1001, 0, b"\x00"), abort(0x1001, 0, 0x06010002)),    # the error register
    (download(0x2008, 3, bytes(4)), abort(0x2008, 3, 0x06090011)),
    (download(0x6099, 0, bytes(2)), abort(0x6099, 0, 0x06020000)),
], ids=["var-sub1", "record-sub7", "no-object", "write-only", "read-only", "const",
        "error-register", "var-sub3-write", "no-object-write"])
def test_refused_accesses_are_aborts_naming_the_object(wire: Script, request_: bytes,
                                                       answer: bytes) -> None:
    assert wire.sdo1(request_) == answer


@pytest.mark.parametrize(("request_", "answer"), [
    # 0x1017 is UNSIGNED16: four bytes are too many, one too few
    (download(0x1017, 0, b"\x64\x00\x00\x00"), abort(0x1017, 0, 0x06070012)),
    (download(0x1017, 0, b"\x64"), abort(0x1017, 0, 0x06070013)),
    # 0x2003 is INTEGER16 limited to -100..100
    (download(0x2003, 0, struct.pack("<h", 101)), abort(0x2003, 0, 0x06090031)),
    (download(0x2003, 0, struct.pack("<h", -101)), abort(0x2003, 0, 0x06090032)),
    (download(0x2004, 0, b"\x02"), abort(0x2004, 0, 0x06090030)),   # a BOOLEAN of 2
    (download(0x1003, 0, b"\x05"), abort(0x1003, 0, 0x06090030)),   # only 0 clears 0x1003
], ids=["too-long", "too-short", "too-high", "too-low", "boolean", "error-history"])
def test_values_the_object_cannot_take_are_refused(wire: Script, request_: bytes,
                                                   answer: bytes) -> None:
    assert wire.sdo1(request_) == answer
    index, sub = struct.unpack_from("<HB", request_, 1)
    if index == 0x2003:    # nothing half-applied: the old value is still there
        assert wire.sdo1(upload(index, sub)) == bytes.fromhex("4b03200000000000")


def test_values_within_the_rules_are_taken(wire: Script) -> None:
    assert wire.sdo1(download(0x2003, 0, struct.pack("<h", -100))) == \
        bytes.fromhex("6003200000000000")
    assert wire.sdo1(upload(0x2003, 0)) == bytes.fromhex("4b0320009cff0000")
    # expedited without the size indicated (0x22): the object's own size counts
    assert wire.sdo1(bytes.fromhex("22032000") + struct.pack("<h", 7) + b"\xAA\xAA") == \
        bytes.fromhex("6003200000000000")
    assert wire.sdo1(upload(0x2003, 0)) == bytes.fromhex("4b03200007000000")
    assert wire.sdo1(download(0x2001, 0, b"\x01\x00")) == bytes.fromhex("6001200000000000")


def test_an_abort_names_the_transfer_it_ends_never_the_previous_one(wire: Script) -> None:
    assert wire.sdo1(upload(0x1000, 0))[0] == 0x43             # a transfer on 0x1000 ...
    assert wire.sdo1(upload(0x2008, 1)) == abort(0x2008, 1, 0x06090011)   # ... then 0x2008:01
    # a segmented upload of 0x1008 in progress; an upload of 0x1000 meanwhile ends it
    assert wire.sdo1(upload(0x1008, 0)) == bytes.fromhex("4108100016000000")  # 22 bytes
    assert wire.sdo1(upload(0x1000, 0)) == abort(0x1008, 0, 0x05040001)
    assert wire.sdo1(upload(0x1000, 0))[0] == 0x43             # served again afterwards


# -- the protocol's own errors -----------------------------------------------------------------


@pytest.mark.parametrize("segment", [
    bytes.fromhex("6000000000000000"),    # an upload segment request, no transfer
    bytes.fromhex("0041424344454647"),    # a download segment, no transfer
    bytes.fromhex("A200000000000000"),    # a block upload acknowledgement, no transfer
    bytes.fromhex("C100000000000000"),    # an end of block download, no transfer
    bytes.fromhex("E000000000000000"),    # command specifier 7: unknown
], ids=["upload-segment", "download-segment", "block-ack", "block-end", "ccs7"])
def test_a_stray_frame_is_an_unknown_command_on_no_object(wire: Script, segment: bytes) -> None:
    assert wire.sdo1(upload(0x2008, 0))[0] == 0x43             # a transfer before it
    assert wire.sdo1(segment) == abort(0, 0, 0x05040001)


def test_segmented_upload_and_a_toggle_bit_that_does_not_alternate(wire: Script) -> None:
    name = b"chcos strict test node"
    assert wire.sdo1(upload(0x1008, 0)) == bytes.fromhex("41081000") + struct.pack("<I", 22)
    got = b""
    for n, toggle in enumerate((0x00, 0x10, 0x00, 0x10)):
        seg = wire.sdo1(bytes([0x60 | toggle]) + bytes(7))
        assert seg[0] & 0x10 == toggle
        used = 7 - ((seg[0] >> 1) & 0x07)
        got += seg[1:1 + used]
        assert bool(seg[0] & 0x01) == (n == 3)                 # c: the last segment
    assert got == name
    assert wire.sdo1(upload(0x1008, 0))[0] == 0x41
    assert wire.sdo1(bytes.fromhex("6000000000000000"))[0] == 0x00
    assert wire.sdo1(bytes.fromhex("6000000000000000")) == abort(0x1008, 0, 0x05030000)


def test_segmented_download_checks_the_size_it_was_told(wire: Script) -> None:
    # 0x2006 VISIBLE_STRING, 9 bytes indicated and sent in two segments
    assert wire.sdo1(bytes.fromhex("21062000") + struct.pack("<I", 9)) == \
        bytes.fromhex("6006200000000000")
    assert wire.sdo1(b"\x00" + b"new lab") == bytes.fromhex("2000000000000000")
    assert wire.sdo1(bytes([0x10 | (5 << 1) | 1]) + b"el" + bytes(5)) == \
        bytes.fromhex("3000000000000000")
    assert wire.sdo1(upload(0x2006, 0)) == bytes.fromhex("41062000") + struct.pack("<I", 9)
    assert wire.sdo1(bytes.fromhex("6000000000000000")) == b"\x00new lab"
    assert wire.sdo1(bytes.fromhex("7000000000000000")) == b"\x1bel" + bytes(5)  # 2 bytes, c
    # 5 bytes indicated, 7 sent: the client's own size does not match
    assert wire.sdo1(bytes.fromhex("21062000") + struct.pack("<I", 5))[0] == 0x60
    assert wire.sdo1(bytes([0x01]) + b"toolong") == abort(0x2006, 0, 0x06070010)
    # a segmented download of 6 bytes into an UNSIGNED32: refused at the start
    assert wire.sdo1(bytes.fromhex("21072000") + struct.pack("<I", 6)) == \
        abort(0x2007, 0, 0x06070012)
    # a toggle bit that does not alternate
    assert wire.sdo1(bytes.fromhex("21062000") + struct.pack("<I", 14))[0] == 0x60
    assert wire.sdo1(b"\x00abcdefg") == bytes.fromhex("2000000000000000")
    assert wire.sdo1(b"\x00hijklmn") == abort(0x2006, 0, 0x05030000)


def test_a_client_abort_ends_the_transfer_silently(wire: Script) -> None:
    assert wire.sdo1(upload(0x1008, 0))[0] == 0x41
    assert wire.sdo(abort(0x1008, 0, 0x05040000)) == []
    assert wire.sdo1(bytes.fromhex("6000000000000000")) == abort(0, 0, 0x05040001)


def test_a_frame_that_is_not_eight_bytes_is_no_sdo(wire: Script) -> None:
    assert wire.sdo(upload(0x1000, 0)[:4]) == []
    assert wire.sdo1(upload(0x1000, 0))[0] == 0x43


def test_a_transfer_the_client_leaves_times_out_on_the_node_clock(wire: Script) -> None:
    assert wire.sdo1(bytes.fromhex("21062000") + struct.pack("<I", 9))[0] == 0x60
    wire.run(0.99)
    assert [s for s in wire.seen if s.cob_id == 0x589 and s.data[0] == 0x80] == []
    answers = [s for s in wire.run(0.02) if s.cob_id == 0x589]
    assert [s.data for s in answers] == [abort(0x2006, 0, 0x05040000)]
    assert answers[0].at == pytest.approx(1.0, abs=0.011)
    assert wire.slave.next_due() is None                       # nothing left to time out


# -- block transfers ---------------------------------------------------------------------------


def _block_upload(wire: Script, index: int, sub: int, blksize: int = 4,
                  pst: int = 0) -> tuple[bytes, list[bytes]]:
    """A block upload to its end (CRC asked for); the data and every server frame."""
    init = wire.sdo1(bytes([0xA4, index & 0xFF, index >> 8, sub, blksize, pst, 0, 0]))
    assert init[0] == 0xC6 and init[1:4] == bytes([index & 0xFF, index >> 8, sub]), init.hex()
    size = struct.unpack_from("<I", init, 4)[0]
    frames = [init]
    got = b""
    request = bytes([0xA3]) + bytes(7)                          # start upload
    while True:
        block = wire.sdo(request)
        frames += block
        assert 1 <= len(block) <= blksize
        for n, seg in enumerate(block, 1):
            assert seg[0] & 0x7F == n
            got += seg[1:]
        if block[-1][0] & 0x80:                                 # the last segment
            break
        request = bytes([0xA2, len(block), blksize]) + bytes(5)
    end = wire.sdo1(bytes([0xA2, len(block), blksize]) + bytes(5))
    frames.append(end)
    assert end[0] & 0xE3 == 0xC1
    got = got[:len(got) - ((end[0] >> 2) & 0x07)]
    assert struct.unpack_from("<H", end, 1)[0] == crc_ccitt(got)
    assert wire.sdo(bytes([0xA1]) + bytes(7)) == []             # end response: no answer
    assert len(got) == size
    return got, frames


def test_block_upload_with_crc(wire: Script) -> None:
    got, frames = _block_upload(wire, 0x1008, 0, blksize=2)
    assert got == b"chcos strict test node"
    assert len(frames) == 1 + 4 + 1                             # init, 2 + 2 segments, end


def test_block_upload_under_the_switch_threshold_is_a_plain_upload(wire: Script) -> None:
    assert wire.sdo1(bytes.fromhex("A4001000" "7F04" "0000")) == bytes.fromhex(
        "4300100000000000")                                     # 4 bytes <= pst 4
    assert wire.sdo1(bytes.fromhex("A4081000" "7F20" "0000")) == bytes.fromhex(
        "4108100016000000")                                     # 22 bytes <= pst 32


def test_block_upload_resends_what_the_client_did_not_acknowledge(wire: Script) -> None:
    assert wire.sdo1(bytes.fromhex("A4081000" "0300" "0000"))[0] == 0xC6
    first = wire.sdo(bytes([0xA3]) + bytes(7))
    assert [f[0] for f in first] == [1, 2, 3]
    again = wire.sdo(bytes([0xA2, 1, 3]) + bytes(5))            # only segment 1 arrived
    assert [f[1:] for f in again[:2]] == [f[1:] for f in first[1:]]
    assert wire.sdo1(bytes([0xA2, 4, 3]) + bytes(5)) == abort(0x1008, 0, 0x05040003)


@pytest.mark.parametrize("blksize", [0, 128])
def test_block_upload_refuses_a_block_size_outside_1_to_127(wire: Script, blksize: int) -> None:
    assert wire.sdo1(bytes([0xA4, 0x08, 0x10, 0, blksize, 0, 0, 0])) == \
        abort(0x1008, 0, 0x05040002)


def _block_download(wire: Script, index: int, sub: int, data: bytes,
                    crc: int | None = None) -> bytes:
    """A block download of ``data`` with size indicated and CRC; the server's last answer."""
    init = wire.sdo1(bytes([0xC6, index & 0xFF, index >> 8, sub]) + struct.pack("<I", len(data)))
    assert init[:4] == bytes([0xA4, index & 0xFF, index >> 8, sub]), init.hex()
    blksize = init[4]
    segments = [data[k:k + 7] for k in range(0, len(data), 7)] or [b""]
    for n, seg in enumerate(segments, 1):
        last = n == len(segments)
        answers = wire.sdo(bytes([n | (0x80 if last else 0)]) + seg.ljust(7, b"\x00"))
        if last or n == blksize:
            assert answers == [bytes([0xA2, n, 127]) + bytes(5)]
        else:
            assert answers == []
    unused = 7 * len(segments) - len(data)
    value = crc_ccitt(data) if crc is None else crc
    return wire.sdo1(bytes([0xC1 | (unused << 2)]) + struct.pack("<H", value) + bytes(5))


def test_block_download_with_crc(wire: Script) -> None:
    block = bytes(range(40))
    assert _block_download(wire, 0x2005, 0, block) == bytes.fromhex("A100000000000000")
    got, _ = _block_upload(wire, 0x2005, 0)
    assert got == block


def test_block_download_with_a_wrong_crc_is_aborted_and_not_stored(wire: Script) -> None:
    block = bytes(range(20))
    assert _block_download(wire, 0x2005, 0, block, crc=crc_ccitt(block) ^ 1) == \
        abort(0x2005, 0, 0x05040004)
    assert wire.sdo1(upload(0x2005, 0)) == bytes.fromhex("4105200000000000")   # still empty


def test_block_download_sequence_numbers(wire: Script) -> None:
    assert wire.sdo1(bytes.fromhex("C6052000") + struct.pack("<I", 14))[0] == 0xA4
    assert wire.sdo(b"\x01" + b"abcdefg") == []
    assert wire.sdo(b"\x01" + b"abcdefg") == []                 # a repeat: ignored
    assert wire.sdo1(b"\x00" + b"hijklmn") == abort(0x2005, 0, 0x05040003)


def test_block_download_of_a_read_only_object_is_refused_at_the_start(wire: Script) -> None:
    assert wire.sdo1(bytes.fromhex("C6082000") + struct.pack("<I", 4)) == \
        abort(0x2008, 0, 0x06010002)


# -- an independent client: canopen's, over python-can's virtual bus ---------------------------


@pytest.fixture
def client() -> Iterator[Any]:
    from chcos.apps.sim.canopen_slave import CanopenSlave, Clock

    channel = unique_channel("cosim-sdo")
    slave = CanopenSlave(NODE, STRICT_EDS, channel=channel, heartbeat_period=0,
                         clock=Clock.TICK)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=channel)
    try:
        slave.start()
        node = canopen.RemoteNode(NODE, str(STRICT_EDS))
        network.add_node(node)
        yield node
    finally:
        network.disconnect()
        slave.stop()


def test_canopens_client_reads_and_writes_by_block_transfer(client: Any) -> None:
    with client.sdo.open(0x1008, 0, "rb", block_transfer=True) as fp:
        assert fp.read() == b"chcos strict test node"
    payload = bytes(range(256)) * 3
    with client.sdo.open(0x2005, 0, "wb", size=len(payload), block_transfer=True) as fp:
        fp.write(payload)
    with client.sdo.open(0x2005, 0, "rb", block_transfer=True) as fp:
        assert fp.read() == payload
    assert client.sdo.upload(0x2005, 0) == payload              # segmented, the same bytes
    with pytest.raises(canopen.SdoAbortedError) as err:
        client.sdo.upload(0x2008, 1)
    assert err.value.code == 0x06090011
