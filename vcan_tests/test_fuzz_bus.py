"""Values from the bus under bad input (issue 15, items 8 and 9): the decode paths of the CAN,
Modbus and RTU drivers never raise, never deliver nan or an infinity, and classify what they
refuse; a CAN remote frame is its own class (not "wrong-length"); the socket drop count that
reports a SocketCAN overrun is read from the kernel.
"""

from __future__ import annotations

import math
import socket
import subprocess

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.exceptions import ModbusException

from drivers.can_raw import CanDriver
from drivers.canbus import socket_drops
from drivers.codecs.can import CanCodec, Decoded, FrameFault, Ignored, Rejected
from drivers.codecs.modbus import REGISTER_TYPES, Point, classify_rtu_answer, reading_of
from vcan_tests.conftest import require
from vcan_tests.netutil import unique_channel
from vcan_tests.support_dev import CELL_DBC, WAIT, FakeHost, bus, device

FUZZ = settings(max_examples=300, deadline=None, derandomize=True)

FLOAT_DBC = """VERSION ""

NS_ :

BS_:

BU_: CELL PLC

BO_ 259 Floats: 8 CELL
 SG_ F : 0|32@1- (1,0) [-1E+38|1E+38] "" PLC
 SG_ I : 32|32@1- (1,0) [-2147483648|2147483647] "" PLC

SIG_VALTYPE_ 259 F : 1;
"""


@pytest.fixture(scope="module")
def codec(tmp_path_factory: pytest.TempPathFactory) -> CanCodec:
    dbc = tmp_path_factory.mktemp("dbc") / "floats.dbc"
    dbc.write_text(FLOAT_DBC, encoding="utf-8")
    spec = bus("can", interface="virtual", channel="x", dbc=str(dbc))
    return CanCodec(spec, [device("F", "sensor", i=0, message="Floats", signal="F"),
                           device("I", "sensor", i=1, message="Floats", signal="I"),
                           device("Door", "sensor", i=2, id=0x300, start=0, length=1, dlc=1)])


@FUZZ
@given(st.sampled_from([0x103, 0x300, 0x555]), st.binary(max_size=8), st.booleans(),
       st.booleans())
def test_any_can_frame_decodes_to_finite_values_or_a_class(codec: CanCodec, fid: int,
                                                           data: bytes, remote: bool,
                                                           extended: bool) -> None:
    frame = can.Message(arbitration_id=fid, data=b"" if remote else data,
                        dlc=len(data), is_remote_frame=remote, is_extended_id=extended)
    result = codec.decode(frame)
    assert isinstance(result, Decoded | Ignored | Rejected)
    if remote:
        assert isinstance(result, Rejected) and result.fault is FrameFault.REMOTE_FRAME
    if isinstance(result, Rejected):
        assert result.fault in (FrameFault.REMOTE_FRAME, FrameFault.UNKNOWN_ID,
                                FrameFault.WRONG_LENGTH, FrameFault.UNDECODABLE)
    if isinstance(result, Decoded):
        assert all(not isinstance(v, float) or math.isfinite(v) for _, v in result.readings)


def test_nan_in_a_float_signal_is_undecodable(codec: CanCodec) -> None:
    nan = bytes.fromhex("0000c07f") + bytes(4)              # float32 quiet nan, little endian
    result = codec.decode(can.Message(arbitration_id=0x103, data=nan, is_extended_id=False))
    assert isinstance(result, Rejected) and result.fault is FrameFault.UNDECODABLE
    assert "not a finite number" in result.detail


def test_a_remote_frame_is_counted_as_such_not_as_wrong_length() -> None:
    channel = unique_channel("remote")
    host = FakeHost()
    drv = CanDriver(bus("can", interface="virtual", channel=channel, dbc=str(CELL_DBC)),
                    [device("T1", "sensor", i=0, message="Temps", signal="T1")], host)
    drv.start()
    peer = can.Bus(interface="virtual", channel=channel)
    try:
        peer.send(can.Message(arbitration_id=0x101, is_remote_frame=True, dlc=4,
                              is_extended_id=False))
        peer.send(can.Message(arbitration_id=0x101, data=b"\x10\x00\x20\x00",
                              is_extended_id=False))
        assert host.wait(lambda h: h.values("T1"))
        assert drv.settle(WAIT)
        assert drv.error_counts == {"remote-frame": 1}
        assert host.error_kinds() == ["remote-frame"]
        assert drv.overrun_lost == 0                       # virtual: no socket, no overrun
    finally:
        peer.shutdown()
        drv.stop()


def test_socket_drops_counts_what_the_kernel_dropped() -> None:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        rx.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        rx.bind(("127.0.0.1", 0))
        rx.setblocking(False)
        assert socket_drops(rx) == 0
        sent = 500
        for _ in range(sent):
            tx.sendto(b"x" * 64, rx.getsockname())
        got = 0
        while True:
            try:
                rx.recv(128)
            except BlockingIOError:
                break
            got += 1
        drops = socket_drops(rx)
        assert drops is not None and drops > 0 and got + drops == sent
    finally:
        rx.close()
        tx.close()
    assert socket_drops(object()) is None


@FUZZ
@given(st.sampled_from(sorted(REGISTER_TYPES)), st.sampled_from(["big", "little"]),
       st.lists(st.integers(0, 0xFFFF), max_size=4))
def test_any_registers_give_a_finite_reading_or_an_error(type_: str, order: str,
                                                         regs: list[int]) -> None:
    p = Point("P", 1, "holding", 0, type_, order)  # type: ignore[arg-type]
    try:
        value = reading_of(p, regs)
    except (ValueError, IndexError, ModbusException) as exc:
        assert str(exc)
        return
    assert len(regs) >= p.size
    assert not isinstance(value, float) or math.isfinite(value)


def test_float32_nan_registers_are_refused() -> None:
    p = Point("P", 1, "holding", 0, "float32", "big")
    with pytest.raises(ValueError, match="not a finite number"):
        reading_of(p, [0x7FC0, 0x0000])
    assert reading_of(p, [0x41A8, 0x0000]) == 21.0


@FUZZ
@given(st.binary(max_size=8), st.binary(max_size=40))
def test_any_rtu_bytes_are_classified(request: bytes, received: bytes) -> None:
    kind, why = classify_rtu_answer(request, received)
    assert kind in ("timeout", "crc", "framing") and why
    assert (kind == "timeout") == (received == b"")



@pytest.mark.socketcan
def test_a_flood_past_the_socket_buffer_is_reported_with_the_frames_lost() -> None:
    """On real SocketCAN (inside User-Mode Linux): can-utils' cangen floods vcan0 with 6,000
    frames while the driver's reader is held; the driver reports the overrun with exactly the
    frames the kernel dropped, so received + lost = sent."""
    from vcan_tests import uml

    channel = uml.socketcan_channel()
    require(channel is not None, f"a SocketCAN channel: {uml.socketcan_skip_reason()}")
    assert channel is not None
    host = FakeHost()
    drv = CanDriver(bus("can", interface="socketcan", channel=channel, dbc=str(CELL_DBC)),
                    [device("T1", "sensor", i=0, message="Temps", signal="T1")], host)
    drv.start()
    try:
        with drv._rx.lock:                                  # the reader cannot drain meanwhile
            subprocess.run(["cangen", channel, "-I", "101", "-L", "4", "-D", "i", "-g", "0",
                            "-n", "6000"], check=True, timeout=60)
        assert host.wait(lambda h: drv.received + drv.overrun_lost >= 6000, 30)
        assert drv.settle(WAIT)
        assert drv.overrun_lost > 0
        assert drv.received + drv.overrun_lost == 6000
        assert drv.error_counts["overrun"] >= 1
        assert any(k == "overrun" and "frame(s) lost" in d for _, k, d in host.errors)
    finally:
        drv.stop()
