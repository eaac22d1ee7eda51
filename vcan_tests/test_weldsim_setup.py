"""WeldSim set-up: the cell's device map and its rebound copies, argument and port errors,
scenarios, the serial line format, and the real-time mode behind ``chcos sim weld``."""

from __future__ import annotations

import re
import socket
import struct
from pathlib import Path

import can
import pytest

from chcos.apps.weld import plant as weld
from chcos.apps.weld import simmap
from chcos.apps.weld.faults import load_scenario
from chcos.apps.weld.model import WeldCell
from chcos.apps.weld.plant import WeldSim
from chcos.apps.weld.simmap import CELL_TOML, cell_devmap
from chcos.apps.weld.slaves import INPUT_REGISTERS, WELD_DBC, WELD_EDS, format_line
from chcos.devices.devmap import check_main, load
from chcos.errors import BusError, ConfigError
from vcan_tests.netutil import free_port, unique_channel
from vcan_tests.support_fb import WAIT
from vcan_tests.support_weldsim import SENSORS, TASKS

ACTUATORS = {a for _, outs in TASKS.values() for a in outs}


def test_the_cell_map_checks_and_matches_the_device_table(capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    assert check_main([str(CELL_TOML)]) == 0
    assert "ok: 4 buses, 61 devices" in capsys.readouterr().out   # 5 axes of 7 devices each
    m = load([CELL_TOML])
    axes = {d.name for d in m.devices if d.address.get("profile") == "cia402"}
    assert axes == {f"joint{n}{r}" for n in range(1, 6)
                    for r in ("", ".state", ".statusword", ".mode", ".position", ".velocity",
                              ".fault")}
    assert {d.name for d in m.devices
            if d.direction == "sensor" and d.name not in axes} == set(SENSORS)
    assert {d.name for d in m.devices if d.direction == "actuator"} == ACTUATORS
    dev = {d.name: d for d in m.devices}
    assert dev["intruder"].priority == 99
    assert min(dev[s].priority for s in SENSORS) > max(dev[a].priority for a in ACTUATORS)
    for name in ("drives_enable", "volts_set", "wire_set", "gas_valve"):
        assert dev[name].safe_value == 0
    assert dev["volts_set"].limits == (0, 40) and dev["wire_set"].limits == (0, 250)
    assert all(dev[f"target{n}"].safe_value is None for n in range(1, 6))
    assert all(dev[s].stale_after for s in SENSORS)
    cell = WeldCell()
    for n, link in enumerate(cell.arm.links, 1):
        assert dev[f"target{n}"].limits == (link.lower, link.upper)
    buses = {b.name: b.options for b in m.buses}
    assert buses["servo"]["channel"] == "weld-canopen"
    assert buses["sensors"]["channel"] == "weld-sensors"
    assert buses["power"]["port"] == 15020
    assert buses["seam"]["url"] == "socket://127.0.0.1:15021"
    # every Modbus sensor sits at its documented input register
    regs = {d.address["address"] for d in m.devices if d.bus == "power"
            and d.address["table"] == "input"}
    assert regs == {a for a, _ in INPUT_REGISTERS.values()}


def test_cell_devmap_rebinds_channels_ports_and_paths(tmp_path: Path) -> None:
    out = cell_devmap(tmp_path / "x", canopen_channel="vcan0", sensor_channel="vcan1",
                      modbus_port=2502, serial_port=2503, interface="socketcan")
    assert out == tmp_path / "x" / "weld_cell.toml"
    m = load([out])
    opts = {b.name: dict(b.options) for b in m.buses}
    assert opts["servo"]["interface"] == opts["sensors"]["interface"] == "socketcan"
    assert (opts["servo"]["channel"], opts["sensors"]["channel"]) == ("vcan0", "vcan1")
    assert opts["power"]["port"] == 2502
    assert opts["seam"]["url"] == "socket://127.0.0.1:2503"
    assert Path(opts["sensors"]["dbc"]) == WELD_DBC
    assert {Path(n["eds"]) for n in opts["servo"]["nodes"]} == {WELD_EDS}
    # the same devices as the original, only the binding differs
    assert [d.name for d in m.devices] == [d.name for d in load([CELL_TOML]).devices]


@pytest.mark.parametrize(("kw", "match"), [
    ({"modbus_port": 0}, "modbus_port=0"),
    ({"serial_port": 70000}, "serial_port=70000"),
    ({"canopen_channel": ""}, "canopen_channel"),
    ({"sensor_channel": 'a"b'}, "sensor_channel"),
])
def test_cell_devmap_rejects_bad_arguments(tmp_path: Path, kw: dict[str, object],
                                           match: str) -> None:
    args: dict[str, object] = {"canopen_channel": "a", "sensor_channel": "b",
                               "modbus_port": 1, "serial_port": 2, **kw}
    with pytest.raises(ConfigError, match=match):
        cell_devmap(tmp_path, **args)  # type: ignore[arg-type]


def test_cell_devmap_names_a_template_line_that_is_missing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    broken = tmp_path / "weld_cell.toml"
    broken.write_text(CELL_TOML.read_text().replace("port = 15020", "port = 1502"))
    monkeypatch.setattr(simmap, "CELL_TOML", broken)
    with pytest.raises(ConfigError, match=r"weld_cell.toml: expected 1 line\(s\) with "
                                          r"'port = 15020' to rebind, found 0"):
        cell_devmap(tmp_path / "out", canopen_channel="a", sensor_channel="b", modbus_port=1,
                    serial_port=2)


@pytest.mark.parametrize(("kw", "match"), [
    ({"tick": 0.0}, "tick=0.0"),
    ({"tick": 0.02}, "tick=0.02"),
    ({"canopen_channel": "same", "sensor_channel": "same"}, "two channels"),
    ({"modbus_port": -1}, "modbus_port=-1"),
    ({"scenario": "tip-stuck@x=3"}, "trigger 'x=3'"),
])
def test_weldsim_rejects_bad_arguments(kw: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        WeldSim(**kw)  # type: ignore[arg-type]


def test_a_port_in_use_is_a_bus_error_and_nothing_stays_open() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        channel = unique_channel("weld-co")
        with pytest.raises(BusError, match=f"cannot listen on 127.0.0.1:{port}"):
            WeldSim(canopen_channel=channel, sensor_channel=unique_channel("weld-can"),
                    modbus_port=free_port(), serial_port=port)
    # the CANopen side was closed again: the channel has no heartbeats any more
    with can.Bus(interface="virtual", channel=channel) as bus:
        assert bus.recv(0.2) is None


def test_scenarios_from_strings_and_toml_files(tmp_path: Path) -> None:
    assert load_scenario(None).faults == ()
    assert load_scenario("gas-empty@t=2s").describe() == "gas-empty@t=2.0s"
    path = tmp_path / "s.toml"
    path.write_text('[[fault]]\nkind = "servo-timeout"\njoint = 3\nt = "1s"\n')
    assert load_scenario(path).describe() == "servo-timeout(joint=3)@t=1.0s"
    assert load_scenario(str(path)) == load_scenario(path)
    with pytest.raises(ConfigError, match=r"missing\.toml: cannot be read"):
        load_scenario(str(tmp_path / "missing.toml"))


def test_line_format_is_what_the_maps_pattern_parses() -> None:
    pattern = re.compile(load([CELL_TOML]).bus("seam").options["pattern"])
    cell = WeldCell()
    cell.move_tip((550.0, -150.0, 30.0), 1.5707963267948966)
    for _ in range(400):
        cell.step(0.005)
    line = format_line(cell.readings())
    m = pattern.fullmatch(line)
    assert m is not None and "1" in m["linear"] and float(m["range"]) == pytest.approx(30.0, 0.01)
    far = format_line(WeldCell().readings())          # at home: 250 mm up, out of range
    m = pattern.fullmatch(far)
    assert m is not None and m["linear"] == "0" * 64 and m["range"] == "-1.00"


def test_realtime_mode_speaks_canopen_and_serial() -> None:
    channel = unique_channel("weld-co")
    port = free_port()
    with WeldSim(canopen_channel=channel, sensor_channel=unique_channel("weld-can"),
                 modbus_port=free_port(), serial_port=port) as sim, \
            can.Bus(interface="virtual", channel=channel) as bus:
        sim.start_realtime()
        with pytest.raises(ConfigError, match="already running"):
            sim.start_realtime()
        bus.send(can.Message(arbitration_id=0, data=[1, 0], is_extended_id=False))  # NMT start
        bus.send(can.Message(arbitration_id=0x201, data=struct.pack("<i", 100),
                             is_extended_id=False))
        seen: set[int] = set()
        while not {0x701, 0x181} <= seen:
            msg = bus.recv(WAIT)
            assert msg is not None, f"only {sorted(map(hex, seen))} within {WAIT} s"
            seen.add(msg.arbitration_id)
        with socket.create_connection(("127.0.0.1", port), timeout=WAIT) as conn:
            data = b""
            while b"\n" not in data:
                data += conn.recv(256)
        assert data.startswith(b"L ") and b" R -1.00" in data


def test_main_runs_for_a_duration_and_reports(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["--canopen-channel", unique_channel("weld-co"), "--sensor-channel",
            unique_channel("weld-can"), "--modbus-port", str(free_port()), "--serial-port",
            str(free_port()), "--scenario", "intruder@t=0.01s", "--duration", "0.15",
            "--status", "0.05"]
    assert weld.main(args) == 0
    out = capsys.readouterr().out
    assert "scenario intruder@t=0.01s" in out and "t=" in out and "drives=off" in out
    assert weld.main(["--scenario", "nonsense"]) == 2
    assert "unknown fault kind 'nonsense'" in capsys.readouterr().err
