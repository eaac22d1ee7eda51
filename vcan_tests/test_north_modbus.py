"""The Modbus TCP facade read and written by an independent client (pyModbusTCP): the register
map generated from the device table, values and health as the peer sees them, writes through
limits, status and the owner rule with exception codes that say why, and the printed map."""

from __future__ import annotations

import math
import struct
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from pyModbusTCP.client import ModbusClient
from pyModbusTCP.constants import (
    EXP_DATA_ADDRESS,
    EXP_DATA_VALUE,
    EXP_SLAVE_DEVICE_BUSY,
    EXP_SLAVE_DEVICE_FAILURE,
)

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import VirtualClock
from chcos.north import NorthError
from chcos.north.modbus_facade import ModbusFacade, RegisterMap
from chcos.system.embedded import System

ME = "vcan_tests.support_view"


def cell(workdir: Path) -> System:
    """Sensors P1 (bar), T2 (degC); actuators V1 (north-writable, limits ±100), V2 (not
    writable from the north), V3 (north-writable, but T1 commands it and is invoked)."""
    devmap = DeviceMap((BusSpec("mem", "memory"),), (
        DeviceSpec("P1", "sensor", 0, "mem", units="bar"),
        DeviceSpec("T2", "sensor", 0, "mem", units="degC"),
        DeviceSpec("V1", "actuator", 0, "mem", safe_value=0.0, limits=(-100, 100), units="%",
                   north_writable=True),
        DeviceSpec("V2", "actuator", 0, "mem", safe_value=0.0, units="%"),
        DeviceSpec("V3", "actuator", 0, "mem", safe_value=0.0, limits=(-100, 100),
                   north_writable=True)))
    s = System(devmap, clock=VirtualClock(), base_dir=workdir)
    s.execute("install -m0 sysfile")
    s.execute(f"install -m0i1o1 --code={ME}:follow T1 T2 V3")
    s.execute("invoke T1")
    s.execute("inject P1 2.5")
    s.execute("inject T2 21.25")
    s.run_for(0.5)
    return s


@pytest.fixture
def facade(tmp_path: Path) -> Iterator[tuple[System, ModbusFacade, ModbusClient]]:
    """The cell, its facade on a free loopback port, and a pyModbusTCP client."""
    s = cell(tmp_path)
    f = ModbusFacade(s).start()
    c = ModbusClient(host="127.0.0.1", port=f.port, timeout=10.0, auto_open=True)
    yield s, f, c
    c.close()
    f.stop()
    s.shutdown()


def floats(regs: list[int]) -> list[float]:
    """float32 ABCD pairs as floats."""
    return [struct.unpack(">f", struct.pack(">HH", regs[i], regs[i + 1]))[0]
            for i in range(0, len(regs), 2)]


def pair(value: float) -> list[int]:
    """A float as two registers, high word first."""
    return list(struct.unpack(">HH", struct.pack(">f", value)))


def test_the_peer_reads_values_and_health(facade: tuple[System, ModbusFacade,
                                                        ModbusClient]) -> None:
    system, f, c = facade
    names = [e.device.name for e in f.map.inputs]
    assert names == ["P1", "T2", "V1", "V2", "V3"]
    regs = c.read_input_registers(0, 10)
    assert regs is not None, c.last_error_as_txt
    got = floats(regs)
    assert got[:2] == [2.5, 21.25]
    v3 = system.devtab.get("V3").value  # T1 drives V3 from T2
    assert got[4] == pytest.approx(v3) and not math.isnan(got[4])
    assert all(math.isnan(v) for v in got[2:4]) or got[2] == 0.0
    assert c.read_discrete_inputs(0, 5) == [True] * 5
    system.devtab.fail("P1", "cable cut")
    system.run_for(0.1)
    assert c.read_discrete_inputs(0, 5) == [False, True, True, True, True]
    assert c.read_input_registers(9, 2) is None and c.last_except == EXP_DATA_ADDRESS
    # one float read from the middle: the low word of T2
    assert c.read_input_registers(3, 1) == pair(21.25)[1:]


def test_writes_go_through_limits_status_and_owner(facade: tuple[System, ModbusFacade,
                                                                 ModbusClient]) -> None:
    system, f, c = facade
    assert [e.device.name for e in f.map.holdings] == ["V1", "V3"]
    assert c.write_multiple_registers(0, pair(42.5))
    assert system.devtab.get("V1").value == 42.5
    assert floats(c.read_holding_registers(0, 2) or []) == [42.5]
    # outside the limits: ILLEGAL_VALUE, and V1 unchanged (never clamped)
    assert not c.write_multiple_registers(0, pair(150.0))
    assert c.last_except == EXP_DATA_VALUE
    assert system.devtab.get("V1").value == 42.5
    assert "outside its limits [-100, 100]" in f.refusals[-1][1]
    assert not c.write_multiple_registers(0, pair(math.nan))
    assert c.last_except == EXP_DATA_VALUE
    # half a float, a register past the map: ILLEGAL_ADDRESS
    assert not c.write_single_register(0, 1)
    assert c.last_except == EXP_DATA_ADDRESS
    assert not c.write_multiple_registers(4, pair(1.0))
    assert c.last_except == EXP_DATA_ADDRESS
    # V3 is T1's while T1 runs: DEVICE_BUSY naming the owner
    assert not c.write_multiple_registers(2, pair(5.0))
    assert c.last_except == EXP_SLAVE_DEVICE_BUSY
    assert "commanded by task T1" in f.refusals[-1][1]
    system.execute("suspend T1")
    system.run_for(0.1)
    assert c.write_multiple_registers(2, pair(5.0))
    assert system.devtab.get("V3").value == 5.0
    # a failed actuator: DEVICE_FAILURE
    system.devtab.fail("V1", "drive fault")
    system.run_for(0.1)
    assert not c.write_multiple_registers(0, pair(1.0))
    assert c.last_except == EXP_SLAVE_DEVICE_FAILURE
    assert "drive fault" in f.refusals[-1][1]


def test_the_map_is_printed_and_only_loopback_by_default(tmp_path: Path) -> None:
    m = tmp_path / "cell.toml"
    m.write_text('[[bus]]\nname = "mem"\nkind = "memory"\n\n'
                 '[[device]]\nname = "P1"\ndirection = "sensor"\nbus = "mem"\nunits = "bar"\n\n'
                 '[[device]]\nname = "V1"\ndirection = "actuator"\nbus = "mem"\n'
                 'limits = [0.0, 10.0]\nsafe_value = 0.0\nnorth_writable = true\n\n'
                 '[[device]]\nname = "V2"\ndirection = "actuator"\nbus = "mem"\n',
                 encoding="utf-8")
    out = subprocess.run([sys.executable, "-m", "chcos.cli.main", "facade", "modbus", "--print-map",
                          str(m)], capture_output=True, text=True, check=True).stdout
    lines = out.splitlines()
    assert lines[0].split() == ["table", "address", "count", "type", "device", "kind", "units",
                                "limits", "access"]
    assert lines[2].split()[:6] == ["input", "0", "2", "float32", "ABCD", "P1"]
    assert any(ln.split()[:6] == ["holding", "0", "2", "float32", "ABCD", "V1"]
               and ln.endswith("read/write") for ln in lines)
    assert not any(ln.startswith("holding") and " V2 " in ln for ln in lines)
    bad = tmp_path / "bad.toml"
    bad.write_text(m.read_text().replace("north_writable = true", 'north_writable = "yes"')
                   .replace('units = "bar"\n', 'units = "bar"\nnorth_writable = true\n'))
    r = subprocess.run([sys.executable, "-m", "chcos.cli.main", "facade", "modbus", "--print-map",
                        str(bad)], capture_output=True, text=True)
    assert r.returncode == 1
    assert "north_writable: applies to actuators only" in r.stderr
    assert "north_writable: expected true or false, got string 'yes'" in r.stderr
    s = System(RegisterMap.__init__.__globals__["DeviceMap"](), clock=VirtualClock())
    with pytest.raises(NorthError, match="no authentication"):
        ModbusFacade(s, host="192.0.2.1")
