"""Two stock libmodbus RTU slaves on one line (issue 38): units 1 and 2 behind a hub that passes
every frame to every side, as an RS-485 line does, each slave with libmodbus' default response
timeout. Unit 2 is killed and restarted: unit 1 keeps its readings, unit 2's devices (its
actuator too) fail and recover, a write queued before unit 2 failed never reaches the line, and
the master keeps 3.5 characters of silence before every request. Needs gcc, libmodbus-dev."""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from chcos.devices.spec import BusSpec
from drivers.codecs.modbus import LineTiming, crc16
from drivers.modbus import ModbusRtuDriver
from vcan_tests.support_fb import WAIT, FakeHost, make_device
from vcan_tests.support_rtu import LineHub, RtuSlave, build_slave

STOCK = "default"          # the slaves keep libmodbus' own response timeout (500 ms)


@pytest.fixture(scope="session")
def slave_exe(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_slave(tmp_path_factory.mktemp("rtu-slave"))


@dataclass
class Line:
    hub: LineHub
    slaves: dict[int, RtuSlave]
    driver: ModbusRtuDriver
    host: FakeHost
    exe: Path

    def poll(self, n: int = 1) -> None:
        for _ in range(n):
            self.host.tick(0.1)
            assert self.driver.settle(WAIT)

    def start_unit(self, unit: int) -> None:
        self.slaves[unit] = RtuSlave(self.exe, Path(self.hub.port(unit)), unit, STOCK)

    def sent(self, unit: int) -> list[bytes]:
        """The master's chunks addressed to ``unit`` (each request is one chunk here)."""
        return [data for _, side, data in self.hub.chunks() if side == 0 and data[:1] == bytes(
            [unit])]


@pytest.fixture
def line(slave_exe: Path) -> Iterator[Line]:
    hub = LineHub(3)
    devices = [
        make_device("level", "sensor", "rtu", key="device[0]", unit=1, table="input",
                    address=2),
        make_device("temp2", "sensor", "rtu", key="device[1]", unit=2, table="input",
                    address=3),
        make_device("out2", "actuator", "rtu", key="device[2]", unit=2, table="holding",
                    address=4)]
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[0]",
                  options={"port": hub.port(0), "retries": 0})       # timeout: 1 s, the default
    host = FakeHost()
    ln = Line(hub, {}, ModbusRtuDriver(bus, devices, host), host, slave_exe)
    ln.start_unit(1)
    ln.start_unit(2)
    ln.driver.start()
    try:
        yield ln
    finally:
        ln.driver.stop()
        for s in ln.slaves.values():
            s.close()
        hub.close()


def write_frame(unit: int, address: int, value: int) -> bytes:
    frame = bytes([unit, 6, address >> 8, address & 0xFF, value >> 8, value & 0xFF])
    return frame + crc16(frame).to_bytes(2, "big")


def test_a_dead_unit_costs_the_live_one_nothing_for_good(line: Line) -> None:
    line.poll(3)
    assert line.host.values("level")[-2:] == [102, 102]
    assert line.host.values("temp2")[-2:] == [103, 103]
    assert sorted(line.host.recoveries) == ["level", "out2", "temp2"]

    line.slaves[2].close()                              # unit 2 dies
    line.host.tick(0.1)                                 # its poll is queued...
    line.driver.write("out2", 9)                        # ...then a write for it
    assert line.driver.settle(WAIT)
    assert line.host.writes[-1][:2] == ("out2", 9)
    assert "stopped answering after the write was queued: not sent" in line.host.writes[-1][2]
    assert "unit 2 input 3..3 (device out2): no response" in line.host.failed("out2")[-1]
    level_before, tries_before = len(line.host.values("level")), len(line.sent(2))
    line.poll(11)
    assert len(line.host.values("level")) - level_before >= 9        # unit 1 keeps its polls
    assert len(line.sent(2)) - tries_before < 8                      # unit 2 tried less often
    assert line.host.recoveries.count("out2") == 1                   # out2 stays failed

    line.start_unit(2)                                  # unit 2 is back
    for _ in range(40):
        line.poll(1)
        if line.host.recoveries.count("out2") == 2:
            break
    assert line.host.recoveries.count("out2") == 2 and line.host.recoveries.count("temp2") == 2
    got = len(line.host.values("level")), len(line.host.values("temp2"))
    line.poll(3)                                        # both units answer every poll again
    assert (len(line.host.values("level")) - got[0], len(line.host.values("temp2")) - got[1]) \
        == (3, 3)
    line.driver.write("out2", 10)
    assert line.driver.settle(WAIT) and line.host.writes[-1] == ("out2", 10, "")
    assert line.slaves[2].wait(lambda s: s.last_registers()[0][4:5] == [10])
    assert write_frame(2, 4, 9) not in line.sent(2)     # the stale write never reached the line
    assert write_frame(2, 4, 10) in line.sent(2)


def test_the_master_keeps_the_inter_frame_silence(line: Line) -> None:
    line.poll(10)
    silence = LineTiming(19200).silence
    chunks = line.hub.chunks()
    gaps = [cur[0] - prev[0] for prev, cur in itertools.pairwise(chunks)
            if prev[1] != 0 and cur[1] == 0]               # a slave's answer, then a request
    assert len(gaps) >= 10
    assert min(gaps) >= silence, f"{min(gaps) * 1e3:.3f} ms < t3.5 {silence * 1e3:.3f} ms"
