"""Modbus TCP/RTU drivers end to end against the simulated pymodbus server on 127.0.0.1."""

from __future__ import annotations

import socket
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest

from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.devices.spec import BusSpec
from drivers.codecs.modbus import Point, accepted, plan_reads, value_error
from drivers.modbus import ModbusRtuDriver, ModbusTcpDriver
from vcan_tests.netutil import free_port
from vcan_tests.support_fb import WAIT, FakeHost, make_device

DEVICES = [
    make_device("t1", "sensor", "mb", table="holding", address=10, type="float32"),
    make_device("t2", "sensor", "mb", table="holding", address=12, type="int32",
                word_order="little"),
    make_device("t3", "sensor", "mb", table="holding", address=14, type="int16"),
    make_device("sw", "sensor", "mb", table="discrete", address=5),
    make_device("in", "sensor", "mb", unit=2, table="input", address=3),
    make_device("valve", "actuator", "mb", table="coil", address=7),
    make_device("sp", "actuator", "mb", table="holding", address=50, type="float64"),
    make_device("sp16", "actuator", "mb", table="holding", address=60, type="int16"),
]
NAMES = {d.name for d in DEVICES}


def tcp_bus(port: int, **extra: Any) -> BusSpec:
    return BusSpec(name="mb", kind="modbus-tcp", key="bus[1]",
                   options={"host": "127.0.0.1", "port": port, "timeout": 0.5, "retries": 0,
                            "reconnect_delay": 0.02, "reconnect_delay_max": 0.1, **extra})


@dataclass
class Rig:
    store: RegisterStore
    server: ModbusSimServer
    driver: ModbusTcpDriver
    host: FakeHost
    port: int


@pytest.fixture
def rig() -> Iterator[Rig]:
    store = RegisterStore((1, 2), size=200)
    port = free_port()
    server = ModbusSimServer(store, port)
    server.start()
    host = FakeHost()
    driver = ModbusTcpDriver(tcp_bus(port), DEVICES, host)
    driver.start()
    try:
        yield Rig(store, server, driver, host, port)
    finally:
        driver.stop()
        server.stop()


def poll(rig: Rig) -> None:
    rig.host.tick(0.1)
    assert rig.driver.settle(WAIT)


def test_poll_delivers_converted_values_in_grouped_requests(rig: Rig) -> None:
    rig.store.set_value(1, "holding", 10, 21.5, "float32")
    rig.store.set_value(1, "holding", 12, -100000, "int32", "little")
    rig.store.set_value(1, "holding", 14, -3, "int16")
    rig.store.write(1, "discrete", 5, [True])
    rig.store.write(2, "input", 3, [65535])
    before = rig.store.requests
    poll(rig)
    assert rig.host.values("t1") == [21.5]
    assert rig.host.values("t2") == [-100000]
    assert rig.host.values("t3") == [-3]
    assert rig.host.values("sw") == [True]
    assert rig.host.values("in") == [65535]
    assert rig.store.requests - before == 3   # holding 10..14 in one read, discrete, input
    assert rig.host.failures == [] and rig.host.errors == []


def test_writes_reach_the_datastore(rig: Rig) -> None:
    rig.driver.write("valve", True)
    rig.driver.write("sp", -1.25e9)
    rig.driver.write("sp16", -8)
    assert rig.driver.settle(WAIT)
    assert rig.store.read(1, "coil", 7) == [True]
    assert rig.store.get_value(1, "holding", 50, "float64") == -1.25e9
    assert rig.store.get_value(1, "holding", 60, "int16") == -8
    assert [(d, r) for d, _, r in rig.host.writes] == [("valve", ""), ("sp", ""), ("sp16", "")]


@pytest.mark.parametrize("type_", ["bool", "int16", "uint16", "int32", "uint32", "float32",
                                   "float64"])
def test_what_the_driver_accepts_unasked_is_what_its_check_accepts(type_: str) -> None:
    """Driver.accepts (Devtab's check without asking check_value) is exactly value_error's
    range: its ends pass, a step beyond them and a fraction of an integer type do not."""
    lo, hi, integral = accepted(type_)
    assert value_error(type_, lo) is None and value_error(type_, hi) is None
    beyond = (lo - 1, hi + 1) if integral else (lo * 1.001, hi * 1.001)
    assert all(value_error(type_, v) is not None for v in beyond)
    if integral:
        assert value_error(type_, lo + 0.5) is not None
    else:
        assert value_error(type_, 0.5) is None


def test_fractions_are_never_rounded_silently(rig: Rig) -> None:
    assert rig.driver.accepts("sp16") == (-32768.0, 32767.0, True)
    assert rig.driver.accepts("nope") is None
    assert rig.driver.check_value("sp16", -7.6) is not None
    assert rig.driver.check_value("sp16", -8.0) is None
    rig.driver.write("sp16", -7.6)             # an int16 register cannot carry it
    assert rig.driver.settle(WAIT)
    assert rig.store.client_writes == 0
    assert rig.host.writes and "integer" in rig.host.writes[0][2]


def test_bad_writes_are_reported_not_sent(rig: Rig) -> None:
    rig.driver.write("sp16", 40000)            # does not fit an int16
    rig.driver.write("t1", 1.0)                # a sensor
    rig.driver.write("nope", 1.0)
    assert rig.driver.settle(WAIT)
    assert sorted(rig.host.error_kinds()) == ["range", "unknown-device", "unknown-device"]
    assert rig.store.client_writes == 0


def test_server_stop_fails_devices_and_restart_recovers(rig: Rig) -> None:
    rig.server.stop()
    poll(rig)
    assert rig.host.wait_for(lambda h: {d for d, _ in h.failures} == NAMES)
    reason = rig.host.failed("t1")[0]
    assert f"127.0.0.1:{rig.port}" in reason and "mb" in reason
    poll(rig)                                  # polls while down complete without I/O
    rig.server.start()                         # same port, same store
    assert rig.host.wait_for(lambda h: set(h.recoveries) == NAMES)
    rig.store.set_value(1, "holding", 14, 99, "int16")
    poll(rig)
    assert rig.host.values("t3")[-1] == 99


def test_exception_responses_fail_only_their_devices() -> None:
    store = RegisterStore((1,), size=20)
    port = free_port()
    devices = [make_device("ok", "sensor", "mb", table="holding", address=0),
               make_device("edge", "sensor", "mb", table="holding", address=19, type="float32"),
               make_device("ghost", "sensor", "mb", unit=9, table="input", address=0)]
    host = FakeHost()
    with ModbusSimServer(store, port, role="gateway"):     # unit 1 behind it, no unit 9
        # every request is answered: a long timeout only keeps a loaded machine from
        # turning an answer into a timeout
        driver = ModbusTcpDriver(tcp_bus(port, timeout=5.0), devices, host)
        driver.start()
        try:
            host.tick(0.1)
            assert driver.settle(WAIT)
        finally:
            driver.stop()
    assert host.values("ok") == [0]
    assert "exception code 2 (illegal data address)" in host.failed("edge")[0]
    assert "unit 1 holding 19..20" in host.failed("edge")[0]
    assert "unit 9" in host.failed("ghost")[0] and "exception code 11" in host.failed("ghost")[0]
    assert host.failed("ok") == []


def test_unreachable_server_at_start_then_comes_up() -> None:
    port = free_port()
    host = FakeHost()
    dev = make_device("x", "sensor", "mb", table="holding", address=0)
    driver = ModbusTcpDriver(tcp_bus(port), [dev], host)
    driver.start()
    store = RegisterStore((1,), size=10)
    server = ModbusSimServer(store, port)
    try:
        assert "cannot connect" in host.failed("x")[0]
        server.start()
        assert host.wait_for(lambda h: h.recoveries == ["x"])
        store.write(1, "holding", 0, [42])
        host.tick(0.1)
        assert driver.settle(WAIT)
        assert host.values("x") == [42]
    finally:
        driver.stop()
        server.stop()
    driver.stop()                              # idempotent


def test_rtu_framing_over_socket_port() -> None:
    store = RegisterStore((3,), size=50)
    port = free_port()
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[2]",
                  options={"port": f"socket://127.0.0.1:{port}", "baudrate": 115200,
                           "timeout": 0.5, "retries": 0})
    devices = [make_device("level", "sensor", "rtu", unit=3, table="input", address=4,
                           type="uint32"),
               make_device("pump", "actuator", "rtu", unit=3, table="holding", address=8,
                           type="float32", word_order="little")]
    host = FakeHost()
    store.set_value(3, "input", 4, 70000, "uint32")
    with ModbusSimServer(store, port, framer="rtu"):
        driver = ModbusRtuDriver(bus, devices, host)
        driver.start()
        try:
            host.tick(0.1)
            driver.write("pump", 0.5)
            assert driver.settle(WAIT)
        finally:
            driver.stop()
    assert host.values("level") == [70000]
    assert store.get_value(3, "holding", 8, "float32", "little") == 0.5


def pt(name: str, table: str, address: int, type_: str = "uint16", unit: int = 1) -> Point:
    return Point(name, unit, table, address, type_, "big")


def test_plan_reads_groups_only_contiguous_same_unit_and_table() -> None:
    plan = plan_reads([pt("a", "holding", 10, "float32"), pt("b", "holding", 12),
                       pt("c", "holding", 14), pt("d", "input", 13), pt("e", "holding", 13,
                                                                         unit=2),
                       pt("f", "holding", 11)])   # overlaps a: same request
    got = [(r.unit, r.table, r.address, r.count, [p.device for p in r.points]) for r in plan]
    assert got == [(1, "holding", 10, 3, ["a", "f", "b"]), (1, "holding", 14, 1, ["c"]),
                   (1, "input", 13, 1, ["d"]), (2, "holding", 13, 1, ["e"])]


def test_plan_reads_splits_at_the_protocol_limit() -> None:
    plan = plan_reads([pt(f"r{i}", "holding", i * 2, "float32") for i in range(70)])
    assert [r.count for r in plan] == [124, 16]
    bits = plan_reads([pt(f"b{i}", "coil", i, "bool") for i in range(2001)])
    assert [r.count for r in bits] == [2000, 1]


def test_tcp_server_that_accepts_but_never_answers_is_a_lost_link() -> None:
    host = FakeHost()
    with socket.socket() as mute:               # the kernel accepts; nobody ever answers
        mute.bind(("127.0.0.1", 0))
        mute.listen(8)
        port = mute.getsockname()[1]
        # a long back-off: exactly one attempt before stop, however slow the machine
        bus = tcp_bus(port, timeout=0.05, reconnect_delay=60.0, reconnect_delay_max=60.0)
        driver = ModbusTcpDriver(bus, [make_device("x", "sensor", "mb", table="input",
                                                   address=0)], host)
        driver.start()
        try:
            host.tick(0.1)
            assert driver.settle(WAIT)
        finally:
            driver.stop()
    reason = host.failed("x")[0]
    assert f"127.0.0.1:{port}" in reason and "no response" in reason
    assert host.error_kinds() == ["timeout", "disconnected"]


def test_rtu_unit_that_does_not_answer_fails_only_its_devices() -> None:
    store = RegisterStore((3,), size=10)
    port = free_port()
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[2]",
                  options={"port": f"socket://127.0.0.1:{port}", "timeout": 0.1, "retries": 0})
    devices = [make_device("here", "sensor", "rtu", unit=3, table="holding", address=1),
               make_device("gone", "sensor", "rtu", unit=4, table="holding", address=1)]
    host = FakeHost()
    store.write(3, "holding", 1, [11])
    with ModbusSimServer(store, port, framer="rtu"):
        driver = ModbusRtuDriver(bus, devices, host)
        driver.start()
        try:
            host.tick(0.1)
            assert driver.settle(WAIT)
        finally:
            driver.stop()
    assert host.values("here") == [11]
    assert ["unit 3 has not answered a request yet" in r for r in host.failed("here")] == [True]
    assert host.recoveries == ["here"], host.failures    # unit 4 never showed OK
    assert "unit 4 has not answered a request yet" in host.failed("gone")[0]
    assert "unit 4 holding 1..1 (device gone)" in host.failed("gone")[1]


class ScriptedRtuPeer:
    """An RTU slave behind a TCP port (what ``socket://`` reaches): it answers each request with
    the next step of its script - ``good`` (unit 3, one register holding 11, its CRC from
    pymodbus' framer), ``crc`` (the same frame with its CRC flipped), ``junk`` or ``close``
    (closes the connection) - then ``good`` for ever. It records every request it received."""

    def __init__(self, script: list[str]) -> None:
        self.script = list(script)
        self.requests: list[bytes] = []
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    @staticmethod
    def answer(step: str) -> bytes:
        from pymodbus.framer.rtu import FramerRTU

        body = bytes([3, 3, 2, 0, 11])
        frame = body + FramerRTU.compute_CRC(body).to_bytes(2, "big")
        if step == "crc":
            return frame[:-1] + bytes([frame[-1] ^ 0xFF])
        return b"\x55\xaa\x00\x17\x42" if step == "junk" else frame

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.server.accept()
            except OSError:
                return
            with conn:
                while data := conn.recv(256):
                    self.requests.append(data)
                    step = self.script.pop(0) if self.script else "good"
                    if step == "close":
                        break
                    conn.sendall(self.answer(step))

    def close(self) -> None:
        self.server.close()


def test_rtu_over_socket_classifies_bad_answers_and_a_lost_connection() -> None:
    """RTU through a serial server on TCP (``socket://``), against a scripted slave: the answer's
    bytes reach the classification (crc, framing), never the device; the third unusable answer
    in a row fails it; a closed connection is a lost link (the device fails, the port is
    re-opened), and good answers recover the device."""
    peer = ScriptedRtuPeer(["good", "crc", "junk", "crc", "close"])
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[2]",
                  options={"port": f"socket://127.0.0.1:{peer.port}", "timeout": 0.2,
                           "retries": 0, "reconnect_delay": 0.02})
    host = FakeHost()
    driver = ModbusRtuDriver(bus, [make_device("lvl", "sensor", "rtu", unit=3, table="holding",
                                               address=1)], host)
    driver.start()
    try:
        for _ in range(3):                    # good, crc, junk
            host.tick(0.1)
            assert driver.settle(WAIT)
        assert host.values("lvl") == [11]
        assert driver.unanswered == {"crc": 1, "framing": 1}
        assert [k for k in host.error_kinds() if k in ("crc", "framing")] == ["crc", "framing"]
        assert len(host.failed("lvl")) == 1          # "not answered yet" at the open only
        host.tick(0.1)                        # crc: the third unusable answer in a row
        assert driver.settle(WAIT)
        assert host.values("lvl") == [11]
        assert "3 unusable answers in a row" in host.failed("lvl")[-1]
        assert "fails its CRC" in host.failed("lvl")[-1]
        assert any(k == "framing" and "55aa001742" in detail for _, k, detail in host.errors)
        host.tick(0.1)                        # the slave's side closes
        assert driver.settle(WAIT)
        assert host.wait_for(lambda h: any("lost" in why for why in h.failed("lvl")))
        assert "disconnected" in host.error_kinds()
        assert host.wait_for(lambda h: h.stats.get("reconnects", 0) == 1)
        host.tick(0.1)                        # re-opened: answered again
        assert driver.settle(WAIT)
        assert host.values("lvl") == [11, 11]
        assert host.recoveries[-1] == "lvl"
    finally:
        driver.stop()
        peer.close()
    request = bytes([3, 3, 0, 1, 0, 1])       # unit 3, read holding 1, count 1, then its CRC
    assert all(r.startswith(request) and len(r) == 8 for r in peer.requests), peer.requests
    assert len(peer.requests) == 6
