"""RPDO length errors on the simulated node (CiA 301), frames written here as the standard lays
them out: an RPDO shorter than its mapping is not processed and raises EMCY 0x8210 (PDO not
processed due to length error), a longer one is processed (its first bytes) and raises 0x8220
(PDO length exceeded); the error register (EMCY byte 2, 0x1001) and the error history (0x1003)
say the same; the next RPDO of the right length clears the error with the error-reset EMCY
(code 0000) and the register of what is left. Both the pure core and python-can's virtual bus."""

from __future__ import annotations

import struct
from collections.abc import Iterator

import can
import pytest

from chcos.apps.sim.canopen_slave import CanopenSlave, Clock
from vcan_tests.netutil import unique_channel
from vcan_tests.support_cosim import STRICT_EDS, Script, upload
from vcan_tests.support_fb import WAIT

NODE = 9
RPDO1 = 0x200 + NODE           # mapped: 0x2003 INTEGER16, 0x2007 UNSIGNED32 (6 bytes)
EMCY = 0x80 + NODE


def emcy(code: int, register: int, extra: bytes = b"") -> bytes:
    """An EMCY frame: code LE, error register, five manufacturer bytes."""
    return struct.pack("<HB", code, register) + extra.ljust(5, b"\x00")


@pytest.fixture
def wire() -> Script:
    w = Script(NODE)
    w.nmt(0x01)
    return w


def values(wire: Script) -> tuple[bytes, bytes]:
    return wire.sdo1(upload(0x2003, 0)), wire.sdo1(upload(0x2007, 0))


def test_a_short_rpdo_is_not_processed_and_raises_8210(wire: Script) -> None:
    before = values(wire)
    mark = len(wire.seen)
    wire.send(RPDO1, struct.pack("<h", 5) + b"\x01\x02\x03")         # 5 of 6 bytes
    # manufacturer bytes: PDO number 1 (LE), 5 bytes received, 6 mapped
    assert wire.emcys(mark) == [emcy(0x8210, 0x11, bytes([1, 0, 5, 6]))]
    assert values(wire) == before                                    # nothing applied
    assert wire.sdo1(upload(0x1001, 0)) == bytes.fromhex("4f01100011000000")
    assert wire.sdo1(upload(0x1003, 1)) == bytes.fromhex("4303100110820000")
    wire.send(RPDO1, b"\x01")                                        # again: no new EMCY
    assert wire.emcys(mark) == [emcy(0x8210, 0x11, bytes([1, 0, 5, 6]))]
    mark = len(wire.seen)
    wire.send(RPDO1, struct.pack("<hI", -7, 0xAABBCCDD))             # the right length
    assert wire.emcys(mark) == [emcy(0x0000, 0x00)]                  # error reset
    assert values(wire) == (bytes.fromhex("4b032000f9ff0000"),
                            bytes.fromhex("43072000ddccbbaa"))
    assert wire.sdo1(upload(0x1001, 0)) == bytes.fromhex("4f01100000000000")
    assert wire.slave.stats.rpdos_length_errors == 2


def test_a_long_rpdo_is_processed_and_raises_8220(wire: Script) -> None:
    mark = len(wire.seen)
    wire.send(RPDO1, struct.pack("<hI", 3, 4) + b"\xEE\xEE")         # 8 of 6 bytes
    assert wire.emcys(mark) == [emcy(0x8220, 0x11, bytes([1, 0, 8, 6]))]
    assert values(wire) == (bytes.fromhex("4b03200003000000"),
                            bytes.fromhex("4307200004000000"))
    mark = len(wire.seen)
    wire.send(RPDO1, b"\x00")                                        # now too short
    # 0x8220 is over (reset, 0x8210 not yet counted), then 0x8210
    assert wire.emcys(mark) == [emcy(0x0000, 0x00), emcy(0x8210, 0x11, bytes([1, 0, 1, 6]))]


def test_another_fault_stays_in_the_register_when_the_length_error_clears(wire: Script) -> None:
    wire.slave.inject_fault(0x4310)                                  # temperature: 0x09
    wire.send(RPDO1, b"\x00\x00")
    mark = len(wire.seen)
    wire.send(RPDO1, bytes(6))
    assert wire.emcys(mark) == [emcy(0x0000, 0x09)]
    assert wire.sdo1(upload(0x1001, 0)) == bytes.fromhex("4f01100009000000")


def test_rpdos_before_operational_are_ignored_without_an_error() -> None:
    wire = Script(NODE)                                              # PRE-OPERATIONAL
    wire.send(RPDO1, b"\x01")
    assert wire.emcys() == []
    assert wire.slave.stats.rpdos_ignored == 1


@pytest.fixture
def bus() -> Iterator[tuple[can.BusABC, CanopenSlave]]:
    channel = unique_channel("cosim-rpdo")
    master = can.Bus(interface="virtual", channel=channel)
    slave = CanopenSlave(NODE, STRICT_EDS, channel=channel, heartbeat_period=0,
                         clock=Clock.TICK)
    try:
        slave.start()
        yield master, slave
    finally:
        slave.stop()
        master.shutdown()


def test_a_short_rpdo_on_the_virtual_bus(bus: tuple[can.BusABC, CanopenSlave]) -> None:
    master, slave = bus
    master.send(can.Message(arbitration_id=0x000, data=bytes([0x01, NODE]),
                            is_extended_id=False))
    assert slave.wait_state("OPERATIONAL", WAIT)
    master.send(can.Message(arbitration_id=RPDO1, data=b"\x01\x02", is_extended_id=False))
    while True:
        msg = master.recv(WAIT)
        assert msg is not None, "no EMCY"
        if msg.arbitration_id == EMCY:
            break
    assert bytes(msg.data) == emcy(0x8210, 0x11, bytes([1, 0, 2, 6]))


def test_the_drives_fault_emcy_and_0x1001_agree() -> None:
    from chcos.apps.sim.cia402_drive import CIA402_EDS, Cia402Drive

    wire = Script(NODE, CIA402_EDS, drive=True)
    assert isinstance(wire.slave, Cia402Drive)
    wire.run(0.02)                                                   # self test done
    wire.slave.set_temperature(95.0)
    mark = len(wire.seen)
    wire.run(0.02)
    assert wire.emcys(mark) == [emcy(0x4310, 0x09)]                  # generic + temperature
    assert wire.sdo1(upload(0x1001, 0)) == bytes.fromhex("4f01100009000000")
    assert wire.sdo1(upload(0x603F, 0)) == bytes.fromhex("4b3f600010430000")
    wire.slave.set_temperature(25.0)
    mark = len(wire.seen)
    assert wire.sdo1(bytes.fromhex("2b40600080000000"))[0] == 0x60   # fault reset (bit 7)
    wire.run(0.02)
    assert wire.emcys(mark) == [emcy(0x0000, 0x00)]
    assert wire.sdo1(upload(0x1001, 0)) == bytes.fromhex("4f01100000000000")
