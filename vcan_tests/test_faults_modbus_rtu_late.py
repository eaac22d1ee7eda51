"""A late RTU answer never becomes the answer to the next request (issue 46): a libmodbus slave
that answers 0.3 s after each request (tools/peer_rtu.py, rtu_slave.c's reply delay) while the
master's timeout is 0.2 s without retries. RTU answers carry no transaction id: with pymodbus'
client three sensors of that unit each delivered another's value. Here the unit fails and no
value reaches a sensor; the late answers are counted and thrown away (the unit that missed is
held quiet for its late answer before another request goes to it, and the input is flushed
before each request). The same slave answering in time (0.05 s) delivers each sensor its own
register. Needs gcc, libmodbus-dev."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.devices.spec import BusSpec
from drivers.modbus import ModbusRtuDriver
from vcan_tests.support_fb import WAIT, FakeHost, make_device
from vcan_tests.support_rtu import LineHub, RtuSlave, build_slave

#: input registers with gaps: one request each; the slave's input register i holds 100 + i
SENSORS = {"a": 2, "b": 4, "c": 6}


@pytest.fixture(scope="session")
def slave_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_slave(tmp_path_factory.mktemp("rtu-slave"))


@contextlib.contextmanager
def line(slave_exe: Path, delay_ms: int) -> Iterator[tuple[LineHub, ModbusRtuDriver, FakeHost]]:
    hub = LineHub(2)
    slave = RtuSlave(slave_exe, Path(hub.port(1)), 1, reply_delay_ms=delay_ms)
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[0]",
                  options={"port": hub.port(0), "timeout": 0.2, "retries": 0})
    host = FakeHost()
    driver = ModbusRtuDriver(bus, [make_device(n, "sensor", "rtu", key=f"device[{i}]",
                                               table="input", address=a)
                                   for i, (n, a) in enumerate(SENSORS.items())], host)
    driver.start()
    try:
        yield hub, driver, host
    finally:
        driver.stop()
        slave.close()
        hub.close()


def poll(driver: ModbusRtuDriver, host: FakeHost, n: int) -> None:
    for _ in range(n):
        host.tick(0.1)
        assert driver.settle(WAIT)


def test_late_answers_are_thrown_away_never_taken_for_the_next_request(
        slave_exe: Path) -> None:
    with line(slave_exe, 300) as (hub, driver, host):
        poll(driver, host, 12)
        answers = [d for _, side, d in hub.chunks() if side == 1]
        assert len(answers) >= 3                         # the slave did answer, late
        assert host.delivered == []                      # and none of it became a value
        assert all("no response (silence)" in host.failed(n)[-1] for n in SENSORS)
        assert host.stats.get("late-answers", 0) >= 3
        assert host.recoveries == []


def test_answers_in_time_give_each_sensor_its_own_register(slave_exe: Path) -> None:
    with line(slave_exe, 50) as (_, driver, host):
        poll(driver, host, 5)
        for name, address in SENSORS.items():
            assert host.values(name) == [100 + address] * 5, name
        assert host.errors == [] and "late-answers" not in host.stats
