"""The Modbus watchdog register (issue 38): a bus option the driver writes every period so the
PLC's comm-loss logic can act when the controller stops. Against a pyModbusTCP server on the
virtual clock: the server sees the register change every period (counter) or written every
period (fixed value); a server that refuses the write fails the devices of its unit until it
takes it again; a bad watchdog table is refused naming the key."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from typing import Any

import pytest
from pyModbusTCP.constants import EXP_DATA_ADDRESS
from pyModbusTCP.server import DataBank, DataHandler, ModbusServer

from chcos.devices.spec import BusSpec
from drivers.modbus import ModbusRtuDriver, ModbusTcpDriver
from vcan_tests.netutil import free_port
from vcan_tests.support_fb import WAIT, FakeHost, make_device

WD = 900


class Recorder(DataHandler):  # type: ignore[misc]
    """Logs every holding-register write as (address, value); refuses writes to ``WD`` with
    exception 2 while ``refuse`` is set."""

    def __init__(self, bank: DataBank) -> None:
        super().__init__(bank)
        self.lock = threading.Lock()
        self.log: list[tuple[int, int]] = []
        self.refuse = False

    def write_h_regs(self, address: int, words_l: list[int], srv_info: Any) -> Any:
        with self.lock:
            self.log.append((address, words_l[0]))
            if self.refuse and address == WD:
                return DataHandler.Return(exp_code=EXP_DATA_ADDRESS)
        return super().write_h_regs(address, words_l, srv_info)

    def at(self, address: int) -> list[int]:
        with self.lock:
            return [v for a, v in self.log if a == address]


@pytest.fixture
def peer() -> Iterator[tuple[ModbusServer, Recorder]]:
    handler = Recorder(DataBank())
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True, data_hdl=handler)
    server.start()
    try:
        yield server, handler
    finally:
        server.stop()


def driver_for(server: ModbusServer, watchdog: dict[str, Any]) -> tuple[ModbusTcpDriver,
                                                                        FakeHost]:
    bus = BusSpec(name="mb", kind="modbus-tcp", key="bus[0]",
                  options={"host": "127.0.0.1", "port": server.port, "timeout": 0.5,
                           "retries": 0, "poll_period": 10.0, "watchdog": watchdog})
    host = FakeHost()
    driver = ModbusTcpDriver(bus, [make_device("level", "sensor", "mb", table="holding",
                                               address=5, poll_period=10.0)], host)
    driver.start()
    return driver, host


def test_the_counter_changes_every_period(peer: tuple[ModbusServer, Recorder]) -> None:
    server, rec = peer
    driver, host = driver_for(server, {"address": WD, "period": 0.5})
    try:
        for beat in range(1, 6):
            host.tick(0.25)                          # half a period: nothing new
            assert driver.settle(WAIT)
            assert len(rec.at(WD)) == beat - 1
            host.tick(0.25)
            assert driver.settle(WAIT)
            assert server.data_bank.get_holding_registers(WD) == [beat]
    finally:
        driver.stop()
    assert rec.at(WD) == [1, 2, 3, 4, 5]
    assert host.stats["watchdog"] == 5 and host.errors == []


def test_a_fixed_value_is_written_every_period(peer: tuple[ModbusServer, Recorder]) -> None:
    server, rec = peer
    driver, host = driver_for(server, {"address": WD, "period": 1.0, "value": 0x55AA})
    try:
        for _ in range(3):
            host.tick(1.0)
            assert driver.settle(WAIT)
    finally:
        driver.stop()
    assert rec.at(WD) == [0x55AA] * 3


def test_a_refused_watchdog_fails_its_units_devices_until_taken(
        peer: tuple[ModbusServer, Recorder]) -> None:
    server, rec = peer
    driver, host = driver_for(server, {"address": WD, "period": 0.5})
    try:
        host.tick(0.5)
        assert driver.settle(WAIT) and host.failed("level") == []
        rec.refuse = True
        host.tick(0.5)
        assert driver.settle(WAIT)
        assert "watchdog unit 1 holding 900: write refused with exception code 2" in \
            host.failed("level")[-1]
        rec.refuse = False
        host.tick(0.5)
        assert driver.settle(WAIT)
        assert host.recoveries[-1] == "level"
    finally:
        driver.stop()
    assert rec.at(WD) == [1, 2, 3]
    assert server.data_bank.get_holding_registers(WD) == [3]


@pytest.mark.parametrize("wd, key, text", [
    ({"period": 1.0}, "watchdog.address", "required; expected an integer"),
    ({"address": 70000}, "watchdog.address", "expected an integer 0..65535, got 70000"),
    ({"address": 1, "table": "input"}, "watchdog.table", "expected one of 'holding', 'coil'"),
    ({"address": 1, "period": 0}, "watchdog.period", "seconds > 0"),
    ({"address": 1, "table": "coil", "value": 2}, "watchdog.value", "integer 0..1"),
    ({"address": 1, "value": "tick"}, "watchdog.value", "'counter' or an integer, got 'tick'"),
    ({"address": 1, "value": 70000}, "watchdog.value", "\"counter\" or an integer 0..65535"),
    ({"address": 1, "every": 1}, "watchdog.every", "unknown key"),
    (5, "watchdog", "expected an inline table"),
])
def test_a_bad_watchdog_is_refused_naming_the_key(wd: Any, key: str, text: str) -> None:
    for cls, opts in ((ModbusTcpDriver, {"host": "x"}), (ModbusRtuDriver, {"port": "/dev/x"})):
        errs = cls.check_bus(BusSpec(name="mb", kind=cls.kind, key="bus[2]",
                                     options={**opts, "watchdog": wd}))
        assert len(errs) == 1 and errs[0].startswith(f"bus[2].{key}: ") and text in errs[0], errs
