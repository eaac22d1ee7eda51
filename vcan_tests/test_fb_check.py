"""check_bus / check_device of the CANopen and Modbus drivers: a row per mistake, no bus opened."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from chcos.devices.spec import BusSpec
from chcos.errors import ConfigError
from drivers.base import Driver
from drivers.canopen_node import CanopenDriver
from drivers.modbus import ModbusRtuDriver, ModbusTcpDriver
from drivers.registry import driver_class
from vcan_tests.support_fb import FakeHost, make_device

CO_OK: dict[str, Any] = {"interface": "virtual", "channel": "c",
                         "nodes": [{"id": 5, "eds": str(SERVO_EDS), "heartbeat_timeout": 0.5}]}
TCP_OK: dict[str, Any] = {"host": "127.0.0.1", "port": 1502}
RTU_OK: dict[str, Any] = {"port": "/dev/ttyUSB0", "baudrate": 9600, "parity": "E"}


def bus(cls: type[Driver], options: dict[str, Any]) -> BusSpec:
    return BusSpec(name="b", kind=cls.kind, options=options, key="bus[4]")


BUS_ROWS = [
    (CanopenDriver, {**CO_OK, "bogus": 1}, "bus[4].bogus: unknown option"),
    (CanopenDriver, {**CO_OK, "bitrate": -5}, "bus[4].bitrate: expected an integer > 0"),
    (CanopenDriver, {**CO_OK, "sync_period": 0},
     "bus[4].sync_period: expected seconds in [0.0005, 4294.967295]"),
    (CanopenDriver, {"channel": "c"}, "bus[4].nodes: expected a non-empty array"),
    (CanopenDriver, {"nodes": ["x"]}, "bus[4].nodes[0]: expected a table"),
    (CanopenDriver, {"nodes": [{"id": 128, "eds": str(SERVO_EDS)}]},
     "bus[4].nodes[0].id: expected a CANopen node id 1..127, got 128"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS)}, {"id": 3, "eds": str(SERVO_EDS)}]},
     "bus[4].nodes[1].id: node id 3 appears twice"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": "/no/such.eds"}]},
     "bus[4].nodes[0].eds: expected a readable EDS file; EDS file /no/such.eds does not exist"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS), "heartbeat_timeout": "1"}]},
     "bus[4].nodes[0].heartbeat_timeout: expected seconds in [0.001, 196.605]"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS), "heartbeat_timeout": 256}]},
     "bus[4].nodes[0].heartbeat_timeout: expected seconds in [0.001, 196.605]"),
    (CanopenDriver, {**CO_OK, "liveness_ms": 5}, "bus[4].liveness_ms: expected 10..65535 ms"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS), "restart_limit": -1}]},
     "bus[4].nodes[0].restart_limit: expected 0..1000 restarts"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS), "restart_backoff": 0}]},
     "bus[4].nodes[0].restart_backoff: expected seconds in [0.05, 30]"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS), "nmt_start": 1}]},
     "bus[4].nodes[0].nmt_start: expected true or false"),
    (CanopenDriver, {"nodes": [{"id": 3, "eds": str(SERVO_EDS), "ed": 1}]},
     "bus[4].nodes[0].ed: unknown key"),
    (ModbusTcpDriver, {"port": 1502}, "bus[4].host: required; expected a string"),
    (ModbusTcpDriver, {"host": ""}, "bus[4].host: expected a host name or address"),
    (ModbusTcpDriver, {**TCP_OK, "port": 70000}, "bus[4].port: expected a TCP port 1..65535"),
    (ModbusTcpDriver, {**TCP_OK, "timeout": -1}, "bus[4].timeout: expected a number of seconds"),
    (ModbusTcpDriver, {**TCP_OK, "retries": 1.5}, "bus[4].retries: expected an integer, got"),
    (ModbusTcpDriver, {**TCP_OK, "retries": -1}, "bus[4].retries: expected an integer >= 0"),
    (ModbusTcpDriver, {**TCP_OK, "baudrate": 9600}, "bus[4].baudrate: unknown key; expected one "
     "of connections"),
    (ModbusRtuDriver, {"baudrate": 9600}, "bus[4].port: required; expected a string"),
    (ModbusRtuDriver, {"port": ""}, "bus[4].port: expected a serial port"),
    (ModbusRtuDriver, {**RTU_OK, "parity": "X"}, "bus[4].parity: expected one of 'N', 'E', 'O'"),
    (ModbusRtuDriver, {**RTU_OK, "stopbits": 3}, "bus[4].stopbits: expected one of 1, 2, got 3"),
    (ModbusRtuDriver, {**RTU_OK, "bytesize": 9}, "bus[4].bytesize: expected one of 7, 8, got 9"),
    (ModbusRtuDriver, {**RTU_OK, "host": "x"},
     "bus[4].host: unknown key; expected one of baudrate"),
]


@pytest.mark.parametrize(("cls", "options", "expected"), BUS_ROWS)
def test_check_bus_names_key_and_expectation(cls: type[Driver], options: dict[str, Any],
                                             expected: str) -> None:
    errs = cls.check_bus(bus(cls, options))
    assert len(errs) == 1, errs
    assert errs[0].startswith(expected), errs


@pytest.mark.parametrize(("cls", "options"), [(CanopenDriver, CO_OK), (ModbusTcpDriver, TCP_OK),
                                              (ModbusRtuDriver, RTU_OK)])
def test_valid_buses_have_no_errors(cls: type[Driver], options: dict[str, Any]) -> None:
    assert cls.check_bus(bus(cls, options)) == []


DEVICE_ROWS = [
    (CanopenDriver, CO_OK, "sensor", {"node": 5, "index": 0x6064}, None),
    (CanopenDriver, CO_OK, "sensor", {"node": 6, "index": 0x6064},
     "device[7].address.node: expected the id of a node of bus b (5), got 6"),
    (CanopenDriver, CO_OK, "sensor", {"node": 5, "index": 0x10000},
     "device[7].address.index: expected an object index 0..0xFFFF"),
    (CanopenDriver, CO_OK, "sensor", {"node": 5, "index": 0x6064, "subindex": -1},
     "device[7].address.subindex: expected a subindex 0..255"),
    (CanopenDriver, CO_OK, "sensor", {"node": 5, "index": 0x6064, "poll_period": 0},
     "device[7].address.poll_period: expected seconds in [0.0005, 86400]"),
    (CanopenDriver, CO_OK, "sensor", {"node": 5, "index": 0x6064, "sub": 0},
     "device[7].address.sub: unknown key"),
    (CanopenDriver, CO_OK, "sensor", {"node": 5, "index": 0x2100},
     "device[7].address: expected an object of node 5's EDS, no 0x2100:00"),
    (CanopenDriver, CO_OK, "actuator", {"node": 5, "index": 0x6064},
     "device[7].address: 0x6064:00 is read-only"),
    (ModbusTcpDriver, TCP_OK, "sensor", {"table": "holding", "address": 0, "type": "float64"},
     None),
    (ModbusTcpDriver, TCP_OK, "sensor", {"table": "register", "address": 0},
     "device[7].address.table: expected one of 'coil', 'discrete', 'holding', 'input', got "
     "'register'"),
    (ModbusTcpDriver, TCP_OK, "actuator", {"table": "input", "address": 0},
     "device[7].address.table: input is read-only"),
    (ModbusTcpDriver, TCP_OK, "sensor", {"table": "coil", "address": 0, "type": "int16"},
     "device[7].address.type: expected \"bool\" (a coil holds one bit), got 'int16'"),
    (ModbusTcpDriver, TCP_OK, "sensor", {"table": "holding", "address": 0, "type": "bool"},
     "device[7].address.type: expected one of int16"),
    (ModbusTcpDriver, TCP_OK, "sensor", {"table": "holding", "address": 65535, "type": "int32"},
     "device[7].address.address: expected an integer 0..65534 (a int32 spans 2 entries)"),
    (ModbusTcpDriver, TCP_OK, "sensor", {"table": "holding", "address": "4"},
     "device[7].address.address: expected an integer"),
    (ModbusTcpDriver, TCP_OK, "sensor", {"unit": 300, "table": "coil", "address": 1},
     "device[7].address.unit: expected a Modbus device id 0..247"),
    (ModbusRtuDriver, RTU_OK, "sensor", {"table": "holding", "address": 1, "word_order": "mid"},
     "device[7].address.word_order: expected one of 'ABCD', 'CDAB', 'BADC', 'DCBA', 'big', "
     "'little', got 'mid'"),
    (ModbusRtuDriver, RTU_OK, "sensor", {"table": "holding", "address": 1, "poll_period": -2},
     "device[7].address.poll_period: expected a number of seconds > 0"),
]


@pytest.mark.parametrize(("cls", "options", "direction", "address", "expected"), DEVICE_ROWS)
def test_check_device_names_key_and_expectation(cls: type[Driver], options: dict[str, Any],
                                                direction: str, address: dict[str, Any],
                                                expected: str | None) -> None:
    dev = make_device("d", direction, "b", key="device[7]", **address)
    errs = cls.check_device(bus(cls, options), dev)
    if expected is None:
        assert errs == []
    else:
        assert len(errs) == 1, errs
        assert errs[0].startswith(expected), errs


def test_relative_eds_is_resolved_against_the_device_map_file(tmp_path: Path) -> None:
    (tmp_path / "eds").mkdir()
    (tmp_path / "eds" / "drive.eds").write_text(SERVO_EDS.read_text())
    spec = BusSpec(name="b", kind="canopen", file=str(tmp_path / "cell.toml"), key="bus[0]",
                   options={"nodes": [{"id": 2, "eds": "eds/drive.eds"}]})
    assert CanopenDriver.check_bus(spec) == []
    dev = make_device("d", "sensor", "b", node=2, index=0x6041)
    assert CanopenDriver.check_device(spec, dev) == []


def test_a_driver_refuses_an_invalid_device_built_in_code_with_its_key() -> None:
    dev = make_device("d", "actuator", "b", key="device[2]", table="discrete", address=1)
    with pytest.raises(ConfigError, match=r"device\[2\]\.address\.table: discrete is read-only"):
        ModbusTcpDriver(bus(ModbusTcpDriver, TCP_OK), [dev], FakeHost())


@pytest.mark.parametrize(("kind", "cls"), [("canopen", CanopenDriver),
                                           ("modbus-tcp", ModbusTcpDriver),
                                           ("modbus-rtu", ModbusRtuDriver)])
def test_registry_finds_the_drivers(kind: str, cls: type[Driver]) -> None:
    assert driver_class(kind) is cls


@pytest.mark.parametrize(("cls", "options", "address"), [
    (CanopenDriver, CO_OK, {"node": 5, "index": 0x607A}),
    (ModbusTcpDriver, TCP_OK, {"table": "holding", "address": 3}),
])
def test_write_to_a_driver_not_running_is_reported(cls: type[Driver], options: dict[str, Any],
                                                   address: dict[str, Any]) -> None:
    host = FakeHost()
    drv = cls(bus(cls, options), [make_device("a", "actuator", "b", **address)], host)
    drv.write("a", 1)
    assert host.error_kinds() == ["stopped"]
    assert "a" in host.errors[0][2] and "not running" in host.errors[0][2]
    assert drv.settle(0.0)
    drv.stop()                                 # stop before start is harmless
