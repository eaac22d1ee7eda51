"""Rolling counters and checksums of CAN messages ([[bus.message]]): the algorithms against their
published check values and an independent bitwise CRC, frames encoded by cantools (independently
of chcos' codec) checked by the driver, and the frames chcos sends decoded by cantools."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import cantools
import pytest

from drivers.can_raw import CanDriver
from drivers.codecs.can_e2e import Algorithm, ChecksumSpec, MessageSpec, Protection
from vcan_tests.support_dev import FakeHost, bus, device

DBC = """VERSION ""
NS_ :
BS_:
BU_: ECU CHCOS
BO_ 256 STEERING_CONTROL: 4 CHCOS
 SG_ CHECKSUM : 0|8@1+ (1,0) [0|255] "" ECU
 SG_ COUNTER : 8|4@1+ (1,0) [0|15] "" ECU
 SG_ ANGLE : 16|16@1- (0.1,0) [-500|500] "deg" ECU
BO_ 257 STEERING_STATUS: 4 ECU
 SG_ CHECKSUM : 0|8@1+ (1,0) [0|255] "" CHCOS
 SG_ COUNTER : 8|4@1+ (1,0) [0|15] "" CHCOS
 SG_ TORQUE : 16|16@1- (0.01,0) [-100|100] "Nm" CHCOS
BO_ 258 PLAIN: 2 ECU
 SG_ LEVEL : 0|8@1+ (0.1,0) [0|125] "%" CHCOS
 SG_ ALIVE_CNT : 8|8@1+ (1,0) [0|255] "" CHCOS
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 257 10;
"""


def crc8(data: bytes, poly: int, init: int, xor_out: int) -> int:
    """A bitwise CRC-8 (no reflection), written here from the definition: independent of the
    table-driven crccheck that chcos uses."""
    crc = init
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc ^ xor_out


def j1850(data: bytes) -> int:
    return crc8(data, 0x1D, 0xFF, 0xFF)


def autosar(data: bytes) -> int:
    return crc8(data, 0x2F, 0xFF, 0xFF)


def test_the_reference_crc_gives_the_published_check_values() -> None:
    assert j1850(b"123456789") == 0x4B      # CRC-8/SAE-J1850 check value
    assert autosar(b"123456789") == 0xDF    # CRC-8/AUTOSAR check value


@pytest.fixture
def dbc_file(tmp_path: Path) -> Path:
    p = tmp_path / "steer.dbc"
    p.write_text(DBC)
    return p


def _nine_byte_message() -> Any:
    """A CAN FD message of 10 bytes: 9 payload bytes then the checksum, so that the checksum
    covers exactly "123456789"."""
    from cantools.database.can import Message, Signal
    sigs = [Signal(f"B{i}", 8 * i, 8) for i in range(9)] + [Signal("CRC", 72, 8)]
    return Message(0x10, "CHECK", 10, sigs, strict=False)


@pytest.mark.parametrize(("algorithm", "check"), [
    (Algorithm.CRC8_SAE_J1850, 0x4B), (Algorithm.CRC8_AUTOSAR, 0xDF),
    (Algorithm.XOR, 0x31), (Algorithm.SUM, sum(b"123456789") & 0xFF)])
def test_each_algorithm_gives_its_check_value_over_the_covered_bytes(
        algorithm: Algorithm, check: int) -> None:
    prot = Protection(_nine_byte_message(), MessageSpec("CHECK", checksum=ChecksumSpec(
        "CRC", algorithm)))
    stamped = prot.stamp(b"123456789\0", 0)
    assert stamped[:9] == b"123456789" and stamped[9] == check
    assert prot.check(stamped) == (None, "")
    assert "checksum CRC is" in prot.check(stamped[:9] + bytes([check ^ 1]))[1]


def checksum_hook(frame_id: int, data: bytes) -> int:
    """A user's checksum: the id's low byte plus the bytes (a Honda-like sum), for the hook."""
    return (frame_id + sum(data)) & 0xFF


def test_the_python_hook_gets_the_id_and_the_payload_without_its_checksum() -> None:
    prot = Protection(_nine_byte_message(), MessageSpec("CHECK", checksum=ChecksumSpec(
        "CRC", Algorithm.PYTHON, f"{__name__}:checksum_hook")))
    stamped = prot.stamp(b"123456789\xAA", 0)
    assert stamped[9] == (0x10 + sum(b"123456789")) & 0xFF


def _bus(dbc_file: Path, channel: str, **extra: Any) -> Any:
    return bus("can", interface="virtual", channel=channel, dbc=str(dbc_file), message=[
        {"name": "STEERING_CONTROL", "counter": "COUNTER",
         "checksum": {"signal": "CHECKSUM", "algorithm": "crc8-sae-j1850"}},
        {"name": "STEERING_STATUS", "counter": "COUNTER",
         "checksum": {"signal": "CHECKSUM", "algorithm": "crc8-autosar"}}], **extra)


def status_frame(db: Any, counter: int, torque: float, good: bool = True) -> can.Message:
    """STEERING_STATUS as its ECU would send it, encoded by cantools; the checksum from the
    reference CRC over bytes 1..3 (the counter in place)."""
    msg = db.get_message_by_name("STEERING_STATUS")
    data = bytearray(msg.encode({"CHECKSUM": 0, "COUNTER": counter, "TORQUE": torque}))
    data[0] = autosar(bytes(data[1:])) ^ (0 if good else 0x5A)
    return can.Message(arbitration_id=msg.frame_id, data=bytes(data), is_extended_id=False)


@pytest.fixture
def channel(request: pytest.FixtureRequest) -> str:
    return f"e2e-{request.node.name}"


@pytest.fixture
def peer(channel: str) -> Iterator[can.BusABC]:
    b = can.Bus(interface="virtual", channel=channel)
    yield b
    b.shutdown()


def test_frames_cantools_encoded_with_the_right_counter_and_crc_are_delivered(
        dbc_file: Path, channel: str, peer: can.BusABC) -> None:
    db = cantools.database.load_file(str(dbc_file))
    host = FakeHost()
    drv = CanDriver(_bus(dbc_file, channel),
                    [device("torque", "sensor", message="STEERING_STATUS", signal="TORQUE")],
                    host)
    drv.start()
    try:
        for n in range(20):                      # the counter wraps at 16
            peer.send(status_frame(db, n % 16, n / 10))
        assert host.wait(lambda h: len(h.values("torque")) == 20)
        assert host.values("torque") == pytest.approx([n / 10 for n in range(20)])
        assert "checksum" not in host.error_kinds() and "counter" not in host.error_kinds()
    finally:
        drv.stop()


def test_a_wrong_checksum_or_counter_is_rejected_by_cause_and_fails_after_the_bound(
        dbc_file: Path, channel: str, peer: can.BusABC) -> None:
    db = cantools.database.load_file(str(dbc_file))
    host = FakeHost()
    drv = CanDriver(_bus(dbc_file, channel),
                    [device("torque", "sensor", message="STEERING_STATUS", signal="TORQUE")],
                    host)
    drv.start()
    try:
        peer.send(status_frame(db, 0, 1.0))
        peer.send(status_frame(db, 1, 2.0, good=False))      # bad CRC: not delivered
        peer.send(status_frame(db, 1, 3.0))
        peer.send(status_frame(db, 3, 4.0))                  # counter skipped 2
        assert host.wait(lambda h: len(h.errors) >= 2)
        assert host.error_kinds().count("checksum") == 1
        assert host.error_kinds().count("counter") == 1
        assert host.values("torque") == pytest.approx([1.0, 3.0])
        assert host.failures == []                           # one bad frame at a time: no failure
        for _ in range(3):                                   # a stuck counter, 3 in a row
            peer.send(status_frame(db, 3, 5.0))
        assert host.wait(lambda h: h.failures)
        assert host.failures[0][0] == "torque" and "counter stuck at 3" in host.failures[0][1]
        peer.send(status_frame(db, 4, 6.0))                  # follows the last: recovered
        assert host.wait(lambda h: "torque" in h.recoveries)
        assert host.wait(lambda h: h.values("torque")[-1:] == pytest.approx([6.0]))
    finally:
        drv.stop()


def test_chcos_sends_its_counter_and_checksum_in_every_frame(
        dbc_file: Path, channel: str, peer: can.BusABC) -> None:
    db = cantools.database.load_file(str(dbc_file))
    host = FakeHost()
    drv = CanDriver(_bus(dbc_file, channel),
                    [device("angle", "actuator", message="STEERING_CONTROL", signal="ANGLE")],
                    host)
    drv.start()
    try:
        for n in range(18):
            drv.write("angle", float(n))
        got = []
        while len(got) < 18:
            frame = peer.recv(timeout=5)
            assert frame is not None
            got.append(bytes(frame.data))
        decoded = [db.decode_message("STEERING_CONTROL", d) for d in got]
        assert [d["COUNTER"] for d in decoded] == [n % 16 for n in range(18)]
        assert [d["ANGLE"] for d in decoded] == pytest.approx([float(n) for n in range(18)])
        assert all(d[0] == j1850(d[1:]) for d in got)
    finally:
        drv.stop()


def _check(dbc_file: Path, **message: Any) -> list[str]:
    b = bus("can", interface="virtual", channel="x", dbc=str(dbc_file), message=[message])
    return CanDriver.check_bus(b)


def test_check_names_the_key_of_a_missing_counter_or_checksum_signal(dbc_file: Path) -> None:
    errs = _check(dbc_file, name="PLAIN", counter="COUNTER")
    assert errs == ["bus[0].message[0].counter: no signal 'COUNTER' in message PLAIN; expected "
                    "one of: LEVEL, ALIVE_CNT"]
    errs = _check(dbc_file, name="PLAIN", checksum={"signal": "CRC", "algorithm": "xor"})
    assert errs[0].startswith("bus[0].message[0].checksum.signal: no signal 'CRC'")
    errs = _check(dbc_file, name="PLAIN", checksum={"signal": "LEVEL", "algorithm": "md5"})
    assert errs[0].startswith("bus[0].message[0].checksum.algorithm: expected one of xor, sum")
    errs = _check(dbc_file, name="NOPE", cycle_time=0.01)
    assert errs[0].startswith("bus[0].message[0].name: no message 'NOPE' in the DBC")
    errs = _check(dbc_file, name="PLAIN", checksum={"signal": "LEVEL", "algorithm": "python",
                                                    "function": "no_such_module:f"})
    assert errs[0].startswith("bus[0].message[0].checksum.function: cannot import "
                              "no_such_module")
    assert _check(dbc_file, name="STEERING_CONTROL", cycle_time=0.02, counter="COUNTER",
                  checksum={"signal": "CHECKSUM", "algorithm": "crc8-autosar"}) == []


def test_check_warns_of_sensors_that_never_go_stale_and_of_limits_past_the_bits(
        dbc_file: Path) -> None:
    b = bus("can", interface="virtual", channel="x", dbc=str(dbc_file))
    devs = [device("level", "sensor", message="PLAIN", signal="LEVEL"),
            device("torque", "sensor", message="STEERING_STATUS", signal="TORQUE")]
    warns = CanDriver.check_warnings(b, devs)
    assert ("message: PLAIN has no cycle time (GenMsgCycleTime, or cycle_time in "
            "[[bus.message]]) and its sensor(s) level no stale_after: a silent sender never "
            "makes them stale") in warns
    assert not any("STEERING_STATUS has no cycle" in w for w in warns)   # the DBC's 10 ms
    assert any(w.startswith("device[0].address.signal: the DBC's limits of LEVEL [0, 125] "
                            "reach past what its 8 bits carry at scale 0.1") for w in warns)
    # an actuator on such a signal is an error; a counter an actuator would set too
    errs = CanDriver.check_device(b, device("lv", "actuator", message="PLAIN", signal="LEVEL"))
    assert errs == ["device[0].address.signal: the DBC's limits of LEVEL [0, 125] reach past "
                    "what its 8 bits carry at scale 0.1, offset 0 ([0, 25.5]): a command "
                    "inside the DBC's limits could not be sent"]
    warns = CanDriver.check_warnings(b, [device("angle", "actuator", message="STEERING_CONTROL",
                                                signal="ANGLE")])
    assert any("STEERING_CONTROL.COUNTER looks like a rolling counter" in w for w in warns)
    assert CanDriver.poll_period(b, devs[1]) == pytest.approx(0.01)
