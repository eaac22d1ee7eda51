"""No latch on Modbus (issue 38): one failed write - exception 6 "busy" from a pyModbusTCP
server, one answer a libmodbus RTU slave's relay drops - fails the actuator, and the driver's own
read-back of the actuator's register ends the failure without any user command. Each test
asserts what the PEER holds after the recovery: the safe value written first, then the next
command."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from pyModbusTCP.constants import EXP_DATA_ADDRESS, EXP_SLAVE_DEVICE_BUSY
from pyModbusTCP.server import DataBank, DataHandler, ModbusServer

from chcos.devices.spec import BusSpec
from chcos.errors import DeviceError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from drivers.modbus import ModbusRtuDriver
from vcan_tests.netutil import free_port
from vcan_tests.support_faults import run_until
from vcan_tests.support_fb import WAIT, FakeHost, make_device
from vcan_tests.support_rtu import FaultRelay, PtyPair, RtuSlave, build_slave

HEATER = 100

MAP = """
[[bus]]
name = "mb"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {port}
timeout = 0.3
retries = 0
reconnect_delay = 0.05

[[device]]
name = "heater"
direction = "actuator"
bus = "mb"
address = {{ table = "holding", address = {heater}, type = "uint16" }}
limits = [0, 1000]
safe_value = 5
"""


class BusyOnce(DataHandler):  # type: ignore[misc]
    """pyModbusTCP's data handler answering exception 6 (busy) to the first ``busy`` writes and
    exception 2 to reads of ``unreadable`` holding registers; logs every write as (address,
    values, outcome)."""

    def __init__(self, bank: DataBank, busy: int = 1, unreadable: frozenset[int] = frozenset()
                 ) -> None:
        super().__init__(bank)
        self.busy = busy
        self.unreadable = unreadable
        self.log: list[tuple[int, list[int], str]] = []
        self.lock = threading.Lock()

    def write_h_regs(self, address: int, words_l: list[int], srv_info: Any) -> Any:
        with self.lock:
            refuse = self.busy > 0
            self.busy -= refuse
            self.log.append((address, list(words_l), "busy" if refuse else "ok"))
        if refuse:
            return DataHandler.Return(exp_code=EXP_SLAVE_DEVICE_BUSY)
        return super().write_h_regs(address, words_l, srv_info)

    def read_h_regs(self, address: int, count: int, srv_info: Any) -> Any:
        if address in self.unreadable:
            return DataHandler.Return(exp_code=EXP_DATA_ADDRESS)
        return super().read_h_regs(address, count, srv_info)

    def writes(self) -> list[tuple[int, list[int], str]]:
        with self.lock:
            return list(self.log)


@pytest.fixture(params=[frozenset(), frozenset({HEATER})], ids=["readable", "write-only"])
def busy_server(request: pytest.FixtureRequest) -> Iterator[tuple[ModbusServer, BusyOnce]]:
    bank = DataBank()
    bank.set_holding_registers(HEATER, [555])
    handler = BusyOnce(bank, busy=1, unreadable=request.param)
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True, data_hdl=handler)
    server.start()
    try:
        yield server, handler
    finally:
        server.stop()


def test_tcp_busy_write_recovers_by_itself_and_the_next_command_reaches_the_server(
        tmp_path: Path, busy_server: tuple[ModbusServer, BusyOnce]) -> None:
    """The register may even refuse to be read (exception 2): that is the unit answering."""
    server, handler = busy_server
    path = tmp_path / "mb.toml"
    path.write_text(MAP.format(port=server.port, heater=HEATER), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    try:
        s.run_for(0.1)
        heater = s.devtab.get("heater")
        s.devtab.write("heater", 300)                         # answered busy
        assert run_until(s, lambda: heater.status.value == "failed")
        assert "exception code 6" in heater.reason
        with pytest.raises(DeviceError, match=r"heater is failed .*exception code 6"):
            s.devtab.write("heater", 400)                     # refused, saying why
        assert run_until(s, lambda: heater.status.value == "OK")   # no command in between
        assert run_until(s, lambda: heater.value == 5)        # the safe value first
        s.devtab.write("heater", 250)
        assert run_until(s, lambda: heater.value == 250)
        assert server.data_bank.get_holding_registers(HEATER) == [250]
        assert handler.writes() == [(HEATER, [300], "busy"), (HEATER, [5], "ok"),
                                    (HEATER, [250], "ok")]
    finally:
        s.shutdown()


@pytest.fixture(scope="session")
def slave_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_slave(tmp_path_factory.mktemp("rtu-slave"))


def test_rtu_write_not_answered_recovers_by_itself_and_the_next_write_reaches_the_slave(
        slave_exe: Path, tmp_path: Path) -> None:
    a = PtyPair(tmp_path, "master")
    b = PtyPair(tmp_path, "slave")
    relay = FaultRelay(a.b, b.a)
    slave = RtuSlave(slave_exe, b.b, 1)
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[0]",
                  options={"port": str(a.a), "timeout": 0.6, "retries": 0})
    host = FakeHost()
    driver = ModbusRtuDriver(bus, [make_device("out", "actuator", "rtu", table="holding",
                                               address=3)], host)
    driver.start()
    try:
        host.tick(1.0)                                        # the liveness probe: unit there
        assert driver.settle(WAIT) and host.recoveries == ["out"]
        relay.damage("silence")                               # the write's answer is dropped
        driver.write("out", 77)
        assert driver.settle(WAIT)
        assert host.writes == [("out", 77, host.writes[0][2])] and host.writes[0][2]
        assert any("write not answered" in r for r in host.failed("out")[1:])
        for _ in range(3):                                    # poll periods, no command
            host.tick(0.1)
            assert driver.settle(WAIT)
        assert host.recoveries == ["out", "out"]
        driver.write("out", 78)
        assert driver.settle(WAIT)
        assert host.writes[-1] == ("out", 78, "")
        assert slave.wait(lambda sl: sl.last_registers()[0][3:4] == [78])
        assert relay.damaged == {"silence": 1}
    finally:
        driver.stop()
        slave.close()
        relay.close()
        a.close()
        b.close()


def test_tcp_read_back_survives_a_lost_link(tmp_path: Path) -> None:
    """The server goes away right after the busy answer: the read-back meets the lost link,
    and once the server is back (same port) the read-back goes on and the actuator recovers."""
    bank = DataBank()
    handler = BusyOnce(bank, busy=1)
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True, data_hdl=handler)
    server.start()
    path = tmp_path / "mb.toml"
    path.write_text(MAP.format(port=server.port, heater=HEATER), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    try:
        s.run_for(0.1)
        heater = s.devtab.get("heater")
        s.devtab.write("heater", 300)
        assert run_until(s, lambda: heater.status.value == "failed", step=0.01)
        server.stop()                                     # before the first read-back
        requests = s.devtab.bus_stats["mb"].counts["requests"]
        assert run_until(s, lambda: s.devtab.bus_stats["mb"].counts["requests"] > requests)
        server.start()
        assert run_until(s, lambda: heater.status.value == "OK" and heater.value == 5)
        assert server.data_bank.get_holding_registers(HEATER) == [5]
    finally:
        s.shutdown()
        server.stop()
