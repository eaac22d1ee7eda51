"""All four word orders of 32- and 64-bit Modbus values (issue 38): ABCD, CDAB, BADC, DCBA, with
``big``/``little`` as aliases of ABCD/CDAB - on literal registers (the codec), in the map check,
and against a pyModbusTCP server whose registers hold a known value in each order (reads) or
show what chcos wrote (writes). The expected registers are spelled out from the value's bytes,
not computed by the codec under test."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from pyModbusTCP.server import DataBank, ModbusServer

from chcos.devices.spec import BusSpec
from chcos.errors import ConfigError
from drivers.codecs.modbus import from_registers, to_registers
from drivers.modbus import ModbusTcpDriver
from vcan_tests.netutil import free_port
from vcan_tests.support_fb import WAIT, FakeHost, make_device

ORDERS = ("ABCD", "CDAB", "BADC", "DCBA")


def words(raw: bytes, order: str) -> list[int]:
    """The registers of the big-endian bytes ``raw`` laid out in ``order``, by the definition:
    DCBA is the value's bytes little-endian, BADC each big-endian word's bytes swapped, CDAB the
    words in reverse."""
    if order in ("DCBA", "BADC"):
        le = raw[::-1]                                    # every byte reversed: DCBA
        if order == "BADC":                               # ... then the words put back in order
            le = b"".join(le[i:i + 2] for i in range(len(le) - 2, -1, -2))
        raw = le
    elif order == "CDAB":
        raw = b"".join(raw[i:i + 2] for i in range(len(raw) - 2, -1, -2))
    return [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]


@pytest.mark.parametrize("order, regs", [
    ("ABCD", [0x1122, 0x3344]), ("CDAB", [0x3344, 0x1122]),
    ("BADC", [0x2211, 0x4433]), ("DCBA", [0x4433, 0x2211]),
    ("big", [0x1122, 0x3344]), ("little", [0x3344, 0x1122]),
])
def test_int32_on_literal_registers(order: str, regs: list[int]) -> None:
    assert to_registers("uint32", 0x11223344, order) == regs
    assert from_registers("uint32", regs, order) == 0x11223344
    assert words(bytes.fromhex("11223344"), order if order in ORDERS else
                 {"big": "ABCD", "little": "CDAB"}[order]) == regs


@pytest.mark.parametrize("order, regs", [
    ("ABCD", [0x4009, 0x21FB, 0x5444, 0x2D18]), ("CDAB", [0x2D18, 0x5444, 0x21FB, 0x4009]),
    ("BADC", [0x0940, 0xFB21, 0x4454, 0x182D]), ("DCBA", [0x182D, 0x4454, 0xFB21, 0x0940]),
])
def test_float64_on_literal_registers(order: str, regs: list[int]) -> None:
    pi = 3.141592653589793                               # 40 09 21 fb 54 44 2d 18
    assert to_registers("float64", pi, order) == regs
    assert from_registers("float64", regs, order) == pi
    assert words(struct.pack(">d", pi), order) == regs


def test_sixteen_bit_types_ignore_the_order() -> None:
    assert [to_registers("int16", -2, o) for o in ORDERS] == [[0xFFFE]] * 4


@pytest.mark.parametrize("bad", ["ACBD", "abcd", "middle", 1])
def test_check_names_the_key_of_a_bad_word_order(bad: object) -> None:
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]", options={"host": "x"})
    dev = make_device("t", "sensor", "mb", key="device[3]", table="holding", address=0,
                      type="float32", word_order=bad)
    errs = ModbusTcpDriver.check_device(bus, dev)
    assert len(errs) == 1 and errs[0].startswith("device[3].address.word_order: expected one "
                                                 "of 'ABCD', 'CDAB', 'BADC', 'DCBA'"), errs
    assert repr(bad) in errs[0]


F32 = 3.25                                              # exact in float32: 40 50 00 00
F32B = 1234.5678                                        # 44 9a 52 2b (rounded in float32)


@pytest.fixture
def server() -> Iterator[ModbusServer]:
    bank = DataBank()
    for i, order in enumerate(ORDERS):
        bank.set_holding_registers(10 * i, words(struct.pack(">f", F32B), order))
        bank.set_holding_registers(10 * i + 2, words(struct.pack(">d", -2.5e-300), order))
    srv = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True, data_bank=bank)
    srv.start()
    try:
        yield srv
    finally:
        srv.stop()


def test_each_order_against_a_pymodbustcp_server(server: ModbusServer) -> None:
    devices = []
    for i, order in enumerate(ORDERS):
        devices += [make_device(f"f32_{order}", "sensor", "mb", table="holding",
                                address=10 * i, type="float32", word_order=order),
                    make_device(f"f64_{order}", "sensor", "mb", table="holding",
                                address=10 * i + 2, type="float64", word_order=order),
                    make_device(f"out_{order}", "actuator", "mb", table="holding",
                                address=100 + 10 * i, type="float32", word_order=order)]
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]",
                  options={"host": "127.0.0.1", "port": server.port, "timeout": 0.5,
                           "retries": 0})
    host = FakeHost()
    driver = ModbusTcpDriver(bus, devices, host)
    driver.start()
    try:
        host.tick(0.1)
        for order in ORDERS:
            driver.write(f"out_{order}", F32)
        assert driver.settle(WAIT)
    finally:
        driver.stop()
    want32 = struct.unpack(">f", struct.pack(">f", F32B))[0]
    for i, order in enumerate(ORDERS):
        assert host.values(f"f32_{order}") == [want32], order
        assert host.values(f"f64_{order}") == [-2.5e-300], order
        assert server.data_bank.get_holding_registers(100 + 10 * i, 2) == \
            words(struct.pack(">f", F32), order), order
    assert host.errors == []


def test_a_register_list_may_name_every_order(tmp_path: Path) -> None:
    """The CSV importer takes the four orders (and its old spellings) and writes what the map
    check accepts; a word order it does not know is an error naming the file and row."""
    from chcos.devices.importers.modbus_csv import import_modbus_csv

    rows = ["Tag;Register Type;Address;Data Type;Word Swap",
            "a;Holding Register;0;REAL;ABCD", "b;Holding Register;2;REAL;CDAB",
            "c;Holding Register;4;REAL;BADC", "d;Holding Register;6;LREAL;DCBA",
            "e;Holding Register;10;DINT;byte swap"]
    path = tmp_path / "regs.csv"
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    draft = import_modbus_csv(path)
    orders = {d["name"]: d["address"]["word_order"] for _, d in draft.devices}
    assert orders == {"a": "big", "b": "little", "c": "BADC", "d": "DCBA", "e": "BADC"}
    bus = BusSpec(name="plc", kind="modbus-tcp", key="bus[0]", options={"host": "x"})
    for _, d in draft.devices:
        dev = make_device(d["name"], "sensor", "plc", **d["address"])
        assert ModbusTcpDriver.check_device(bus, dev) == []
    path.write_text(rows[0] + "\nz;Holding Register;0;REAL;ACBD\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"regs\.csv.*'ACBD'.*BADC or DCBA"):
        import_modbus_csv(path)
