"""Two stock libmodbus RTU slaves on one line (issue 38): units 1 and 2 behind a hub that passes
every frame to every side, as an RS-485 line does, each slave with libmodbus' default response
timeout. Unit 2 is killed and restarted: unit 1 keeps its readings, unit 2's devices (its
actuator too) fail and recover, a write queued before unit 2 failed never reaches the line, and
the master keeps 3.5 characters of silence before every request; a dead unit is backed off from
its first miss (no second try at full cost while the live unit would pay for it) and a unit that
comes back is read again within one backoff cycle. Needs gcc, libmodbus-dev."""

from __future__ import annotations

import contextlib
import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from chcos.devices.spec import BusSpec
from drivers.codecs.modbus import LineTiming, UnitBackoff, crc16
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


def make_line(slave_exe: Path, **options: object) -> Line:
    """Units 1 and 2 (stock slaves) on one line and the driver on it (timeout: 1 s, the
    default; retries 0), with the bus ``options`` given."""
    hub = LineHub(3)
    devices = [
        make_device("level", "sensor", "rtu", key="device[0]", unit=1, table="input",
                    address=2),
        make_device("temp2", "sensor", "rtu", key="device[1]", unit=2, table="input",
                    address=3),
        make_device("out2", "actuator", "rtu", key="device[2]", unit=2, table="holding",
                    address=4)]
    bus = BusSpec(name="rtu", kind="modbus-rtu", key="bus[0]",
                  options={"port": hub.port(0), "retries": 0, **options})
    host = FakeHost()
    ln = Line(hub, {}, ModbusRtuDriver(bus, devices, host), host, slave_exe)
    ln.start_unit(1)
    ln.start_unit(2)
    ln.driver.start()
    return ln


@contextlib.contextmanager
def running(ln: Line) -> Iterator[Line]:
    """``ln`` until the test ends; then the driver, the slaves and the hub are closed."""
    try:
        yield ln
    finally:
        ln.driver.stop()
        for s in ln.slaves.values():
            s.close()
        ln.hub.close()


@pytest.fixture
def line(slave_exe: Path) -> Iterator[Line]:
    """The line with the default backoff (timeout 1 s: a dead unit is tried every 190 polls)."""
    with running(make_line(slave_exe)) as ln:
        yield ln


@pytest.fixture
def short_line(slave_exe: Path) -> Iterator[Line]:
    """The line with ``dead_unit_backoff = 8``: a dead unit is tried every 8th poll."""
    with running(make_line(slave_exe, dead_unit_backoff=8)) as ln:
        yield ln


def write_frame(unit: int, address: int, value: int) -> bytes:
    frame = bytes([unit, 6, address >> 8, address & 0xFF, value >> 8, value & 0xFF])
    return frame + crc16(frame).to_bytes(2, "big")


def test_a_dead_unit_costs_the_live_one_nothing_for_good(short_line: Line) -> None:
    line = short_line
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
    for _ in range(8):                                  # within one backoff cycle (8 polls)
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


def test_a_dead_unit_is_backed_off_from_its_first_miss(line: Line) -> None:
    """At the defaults (timeout 1 s, poll period 0.1 s) a try of a dead unit holds the line
    for ten polls: after its first miss unit 2 is not asked again for 190 polls, so unit 1
    answers its polls meanwhile and the line carries nothing for unit 2."""
    line.poll(3)
    line.slaves[2].close()
    line.poll(1)                                        # unit 2's first miss
    assert "no response" in line.host.failed("temp2")[-1]
    level, tries = len(line.host.values("level")), len(line.sent(2))
    line.poll(30)
    assert len(line.host.values("level")) - level >= 27   # (a loaded machine may lose one)
    assert len(line.sent(2)) == tries                   # not one request for unit 2
    assert line.host.recoveries.count("temp2") == 1     # still failed: never tried again


def gaps_of_a_dead_unit_2(units: UnitBackoff) -> list[int]:
    tried = []
    for turn in range(100):
        if units.due(2):
            tried.append(turn)
            units.silent(2)
    return [b - a for a, b in itertools.pairwise(tried)]


def test_the_backoff_starts_at_first_while_another_unit_answers() -> None:
    units = UnitBackoff(cap=16, first=4, units=(1, 2))
    units.answered(1)                                    # unit 1 answers
    gaps = gaps_of_a_dead_unit_2(units)
    assert gaps[:3] == [4, 8, 16] and set(gaps[3:]) == {16}
    assert units.due(1)                                  # the live unit is never held back
    assert UnitBackoff(cap=8, first=50).first == 8      # never beyond the cap


def test_a_unit_alone_on_its_line_is_tried_again_at_once() -> None:
    """Nobody else pays for its tries: the next poll, then ever less often (also when the
    line's other units are dead too, or have not answered yet)."""
    gaps = gaps_of_a_dead_unit_2(UnitBackoff(cap=16, first=4, units=(2,)))
    assert gaps[:5] == [1, 2, 4, 8, 16]
    assert gaps_of_a_dead_unit_2(UnitBackoff(cap=16, first=4, units=(1, 2)))[:2] == [1, 2]
    both = UnitBackoff(cap=16, first=4, units=(1, 2))    # unit 1 never heard from, then dead
    both.answered(1)
    both.silent(1)
    assert gaps_of_a_dead_unit_2(both)[:2] == [1, 2]
