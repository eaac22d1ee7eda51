"""The simulated slaves on their own: servo physics, datastore, configuration errors, CLI mains."""

from __future__ import annotations

import socket
from pathlib import Path
from typing import Any

import canopen
import pytest

from chcos.apps.sim import canopen_slave, modbus_server
from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave, ServoAxis
from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.errors import BusError, ConfigError
from vcan_tests.netutil import free_port, unique_channel
from vcan_tests.support_fb import WAIT


def test_servo_axis_moves_at_most_max_speed_and_stops_on_target() -> None:
    axis = ServoAxis()
    axis.step(target=250, max_speed=1000, dt=0.1)
    assert (axis.position, axis.velocity) == (100, 1000)
    axis.step(target=250, max_speed=1000, dt=0.1)
    axis.step(target=250, max_speed=1000, dt=0.1)
    assert (axis.position, axis.velocity) == (250, 500)
    axis.step(target=-50, max_speed=3000, dt=0.1)
    assert axis.position == -50 and axis.velocity == pytest.approx(-3000)
    axis.step(target=0, max_speed=1000, dt=0)
    assert axis.velocity == 0


def test_eds_is_read_by_canopen_with_the_pdo_mappings() -> None:
    od: Any = canopen.import_od(str(SERVO_EDS), 7)
    assert od[0x1800][1].default == 0x187 and od[0x1400][1].default == 0x207
    assert od[0x1A00][1].default == 0x60640020 and od[0x1600][1].default == 0x607A0020
    for index in (0x6040, 0x6041, 0x6064, 0x606C, 0x607A):
        assert index in od


def test_slave_rejects_bad_node_and_eds(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="node id 0"):
        CanopenSlave(0, channel="x")
    broken = tmp_path / "broken.eds"
    broken.write_text("[1000]\nDataType=zz\n")
    with pytest.raises(ConfigError, match=r"broken\.eds"):
        CanopenSlave(3, broken, channel="x")
    slave = CanopenSlave(3, channel="x")
    with pytest.raises(ConfigError, match="0x2100:00"):
        slave.set(0x2100, 0, 1)


def test_slave_tick_updates_od_before_and_without_a_master() -> None:
    slave = CanopenSlave(4, channel=unique_channel("fbsim"), heartbeat_period=0)
    with slave:
        slave.set(0x607A, 0, 40)
        slave.set(0x6081, 0, 100)
        slave.tick(0.2)
        assert slave.get(0x6064) == 20 and slave.get(0x606C) == 100
        assert slave.get(0x6041) & 0x0400 == 0
        slave.tick(0.2)
        assert slave.get(0x6064) == 40 and slave.get(0x6041) & 0x0400
        assert slave.nmt_state == "PRE-OPERATIONAL"


def test_store_conversions_bounds_and_wait() -> None:
    store = RegisterStore((1,), size=8)
    store.set_value(1, "holding", 0, 3.5, "float64", "little")
    assert store.get_value(1, "holding", 0, "float64", "little") == 3.5
    store.set_value(1, "coil", 7, True, "bool")
    assert store.get_value(1, "coil", 7, "bool") is True
    with pytest.raises(ConfigError, match=r"outside 0\.\.7"):
        store.read(1, "holding", 6, 4)
    with pytest.raises(ConfigError, match="no unit 2"):
        store.read(2, "holding", 0)
    with pytest.raises(ConfigError, match="not a valid int16"):
        store.set_value(1, "holding", 0, 70000, "int16")
    with pytest.raises(ConfigError, match=r"0\.\.65535"):
        store.write(1, "input", 0, [-1])
    with pytest.raises(ConfigError, match="type 'int8'"):
        store.get_value(1, "input", 0, "int8")
    assert store.wait_for(lambda s: s.read(1, "coil", 7) == [True], WAIT)


def test_server_port_in_use_is_a_bus_error_and_cli_exit_status() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(BusError, match=f"127.0.0.1:{port}"):
            ModbusSimServer(RegisterStore(), port).start()
        assert modbus_server.main(["--port", str(port), "--duration", "0"]) == 2


def test_cli_mains_run_and_return_zero(capsys: pytest.CaptureFixture[str]) -> None:
    assert modbus_server.main(["--port", str(free_port()), "--units", "1", "2",
                               "--duration", "0.01"]) == 0
    assert canopen_slave.main(["--channel", unique_channel("fbcli"), "--node", "9",
                               "--duration", "0.01"]) == 0
    out = capsys.readouterr().out
    assert "units [1, 2]" in out and "node 9" in out
    assert canopen_slave.main(["--channel", "x", "--node", "200"]) == 2
    assert "node id 200" in capsys.readouterr().err


def test_canopen_cli_raises_and_clears_a_fault_on_schedule(
        capsys: pytest.CaptureFixture[str]) -> None:
    import can

    channel = unique_channel("fbfault")
    wire = can.Bus(interface="virtual", channel=channel)
    try:
        assert canopen_slave.main(["--channel", channel, "--node", "9", "--heartbeat", "0",
                                   "--fault", "0x2310@0.1-0.3", "--duration", "0.5"]) == 0
        frames = []
        while (msg := wire.recv(0)) is not None:
            frames.append((msg.arbitration_id, bytes(msg.data)))
    finally:
        wire.shutdown()
    assert frames[0] == (0x709, b"\x00")                                   # boot-up
    assert [d for cob, d in frames if cob == 0x89] == [bytes.fromhex("1023030000000000"),
                                                       bytes(8)]          # EMCY, then reset
    assert "fault 0x2310 raised" in capsys.readouterr().out
    for bad in ("0x2310", "0x10@1", "0x2310@3-1", "x@1"):
        assert canopen_slave.main(["--channel", channel, "--fault", bad]) == 2
    assert "--fault 'x@1': expected CODE@START[-END]" in capsys.readouterr().err
