"""Simulated slaves generated from any device map (``chcos.apps.sim.from_map``, ``chcos sim
--from``):
CAN frames from an imported vendor DBC, a CANopen node from an imported vendor EDS, a Modbus
server from a map; scripted values (constant, ramp, sine, square, CSV trace); faults; the
standalone command serving a map's own address to ``chcos run``."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from chcos.apps.sim.scripts import csv_trace, parse_script
from chcos.cli import cellrun, scaffold
from chcos.cli import main as cli
from chcos.errors import ConfigError, DeviceError
from chcos.helpers import free_port

VENDOR = Path(__file__).resolve().parent / "vendor"


def _system(tmp_path: Path, devmap: Path, install: str) -> Path:
    (tmp_path / "install.chcos").write_text(install, encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text(f'[system]\nname = "sim"\ndevmaps = ["{devmap}"]\n'
                      'install = "install.chcos"\n', encoding="utf-8")
    return system


def test_scripts() -> None:
    assert parse_script("42")(7.0) == 42.0
    ramp = parse_script("ramp(0, 200, 10)")
    assert ramp(0) == 0 and ramp(2.5) == 50 and ramp(12.5) == 50
    sine = parse_script("sine(center=10, amplitude=2, period=4)")
    assert sine(1.0) == pytest.approx(12.0) and sine(3.0) == pytest.approx(8.0)
    sq = parse_script("square(1, 5, 2)")
    assert (sq(0.5), sq(1.5)) == (1, 5)
    with pytest.raises(ConfigError, match=r"missing period"):
        parse_script("sine(1, 2)")
    with pytest.raises(ConfigError, match=r"unknown function 'saw'"):
        parse_script("saw(1, 2, 3)")
    with pytest.raises(ConfigError, match=r"expected a number, ramp"):
        parse_script("fast")


def test_csv_trace(tmp_path: Path) -> None:
    trace = tmp_path / "trace.csv"
    trace.write_text("t,level,temp\n0,10,1\n2,30,2\n4,30,3\n", encoding="utf-8")
    f = csv_trace(trace, "level")
    assert [f(t) for t in (-1, 0, 1, 2, 3, 9)] == [10, 10, 20, 30, 30, 30]
    assert csv_trace(trace)(1) == 20
    assert parse_script("csv(trace.csv, temp)", tmp_path)(3) == pytest.approx(2.5)
    with pytest.raises(ConfigError, match=r"no column 'nope'"):
        csv_trace(trace, "nope")
    trace.write_text("t,v\n0,1\n1,x\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"trace.csv: row 3"):
        csv_trace(trace)


def test_can_slave_from_an_imported_dbc(tmp_path: Path) -> None:
    devmap = tmp_path / "hpu.toml"
    assert cli.main(["import", "dbc", str(VENDOR / "hpu_press.dbc"), "--node", "CELL_CTRL",
                     "-o", str(devmap)]) == 0  # socketcan can0 in the map: --virtual rewrites
    system = _system(tmp_path, devmap, "install -m0 sysfile\n")
    with cellrun.open_cell(system, virtual=True) as cell:
        slaves = cell.slaves
        assert slaves is not None
        slaves.set("oil_pressure", 212.5)
        slaves.script("oil_temperature", "ramp(20, 70, 10)")
        cell.run_for(5.0)
        assert cell.device("oil_pressure").value == pytest.approx(212.5)
        assert cell.device("oil_temperature").value == pytest.approx(45, abs=1)
        # cyclic frames (20 ms GenMsgCycleTime) keep stale_after = 0.1 s satisfied
        assert cell.device("oil_pressure").status.value == "OK"
        cell.system.devtab.write("pressure_setpoint", 180.25)
        cell.run_for(0.1)
        assert slaves.get("pressure_setpoint") == pytest.approx(180.25)
        slaves.silence("can0")
        cell.run_for(0.5)
        assert cell.device("oil_pressure").status.value == "stale"
        slaves.restore("can0")
        cell.run_for(0.5)
        assert cell.device("oil_pressure").status.value == "OK"


def test_canopen_node_from_an_imported_eds(tmp_path: Path) -> None:
    devmap = tmp_path / "axis.toml"
    # --plain: the drive's objects as plain devices (the axis device is tested apart)
    assert cli.main(["import", "eds", str(VENDOR / "acme_amd200.eds"), "--node", "5",
                     "--bus", "axis", "--plain", "-o", str(devmap)]) == 0
    system = _system(tmp_path, devmap, "install -m0 sysfile\n")
    with cellrun.open_cell(system, virtual=True) as cell:
        slaves = cell.slaves
        assert slaves is not None
        cell.run_for(0.5)
        slaves.set("heat_sink_temperature", 57)
        # a CiA 402 EDS is simulated as a drive: its statusword answers the controlword
        assert int(cell.device("statusword").value) & 0x4F == 0x40          # switch on disabled
        for cw in (0x06, 0x07, 0x0F):
            cell.system.devtab.write("controlword", cw)
            cell.run_for(0.2)
        cell.run_for(3.0)  # heartbeats every 0.1 s of virtual time: the node stays alive
        assert cell.device("position_actual_value").status.value == "OK"
        assert int(cell.device("statusword").value) & 0x6F == 0x27          # operation enabled
        assert cell.device("position_actual_value").value == 0         # no mode: holds
        assert cell.device("heat_sink_temperature").value == 57
        cell.system.devtab.write("target_position", 2048)
        cell.system.devtab.write("target_torque", -250)
        cell.run_for(0.5)
        assert slaves.get("target_position") == 2048
        assert slaves.get("target_torque") == -250
        slaves.silence("axis")  # heartbeat and TPDOs stop: the driver's heartbeat supervision
        cell.run_for(1.0)       # runs on the virtual clock, so the node is lost after 0.3 s
        assert cell.device("position_actual_value").status.value == "failed"
        assert "no heartbeat" in cell.device("position_actual_value").reason
        slaves.restore("axis")
        cell.run_for(0.5)
        assert cell.device("position_actual_value").status.value == "OK"


def test_serial_peers_speak_the_maps_framing(tmp_path: Path) -> None:
    devmap = tmp_path / "serial.toml"
    devmap.write_text(r"""
[[bus]]
name = "scale"
kind = "serial"
url = "/dev/ttyUSB0"
protocol = "line"
pattern = 'W=(?P<w>-?[0-9.]+)\s+T=(?P<t>\d+)\s*(?:C)?'
eol = "\r\n"

[[device]]
name = "weight"
direction = "sensor"
bus = "scale"
address = { group = "w" }
scale = 0.001
units = "kg"

[[device]]
name = "temp"
direction = "sensor"
bus = "scale"
address = { group = "t" }

[[device]]
name = "tare"
direction = "actuator"
bus = "scale"
address = { format = "TARE {value:.2f}" }

[[bus]]
name = "gauge"
kind = "serial"
url = "socket://127.0.0.1:9"
protocol = "binary"
sync = "AA 55"
struct = "<hHb"
fields = ["p", "_", "q"]
checksum = "sum8"

[[device]]
name = "pressure"
direction = "sensor"
bus = "gauge"
address = { field = "p" }

[[device]]
name = "valve"
direction = "actuator"
bus = "gauge"
address = { struct = "<h", prefix = "10" }
""", encoding="utf-8")
    system = _system(tmp_path, devmap, "install -m0 sysfile\n")
    with cellrun.open_cell(system, virtual=True) as cell:
        slaves = cell.slaves
        assert slaves is not None
        slaves.set("weight", 12.5)   # raw 12500 g in the line
        slaves.set("temp", 21)
        slaves.script("pressure", "ramp(-100, 100, 2)")
        cell.run_for(1.5)
        assert cell.device("weight").value == pytest.approx(12.5)
        assert cell.device("temp").value == 21
        assert cell.device("pressure").value == pytest.approx(50, abs=1)
        assert cell.system.devtab.bus_errors == {}  # every line and frame was understood
        cell.system.devtab.write("tare", 0.25)
        cell.system.devtab.write("valve", -300)
        cell.run_for(0.2)
        assert slaves.get("tare") == pytest.approx(0.25)
        assert slaves.get("valve") == -300


def test_unsimulatable_serial_is_refused_naming_the_bus(tmp_path: Path) -> None:
    from chcos.apps.sim.from_map import simulate
    from chcos.devices.devmap import load

    devmap = tmp_path / "serial.toml"
    devmap.write_text('[[bus]]\nname = "scale"\nkind = "serial"\nurl = "/dev/ttyUSB0"\n'
                      'protocol = "line"\npattern = "(?P<w>a)\\\\1"\n\n[[device]]\n'
                      'name = "weight"\ndirection = "sensor"\nbus = "scale"\n'
                      'address = { group = "w" }\n', encoding="utf-8")
    dm = load([devmap])
    with pytest.raises(ConfigError, match=r"serial.toml: bus\[0\] \(scale\): url "):
        simulate(dm, rewrite=False)
    with pytest.raises(ConfigError, match=r"bus\[0\] \(scale\): pattern .*back-references"):
        simulate(dm)


def test_sim_from_map_serves_the_maps_own_address(tmp_path: Path) -> None:
    port = free_port()
    scaffold.create(tmp_path / "cell", port=port)
    cell_dir = tmp_path / "cell"
    sim = subprocess.Popen([sys.executable, "-m", "chcos.cli.main", "sim", "--from", "devices.toml",
                            "--value", "level=100"], cwd=cell_dir, stdout=subprocess.PIPE,
                           stderr=subprocess.STDOUT, text=True, env=dict(os.environ))
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert sim.stdout is not None
        for line in sim.stdout:
            lines.append(line)
            if "simulating plc" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert ready.wait(30), "".join(lines)
        assert f"Modbus TCP server on 127.0.0.1:{port}" in "".join(lines)
        out = io.StringIO()
        result = cellrun.run(cell_dir / "system.toml", duration=1.5, out=out)
        assert result.healthy, out.getvalue()
        devs = {d["name"]: d for d in result.snapshot["devices"]}
        assert devs["level"]["value"] == pytest.approx(100.0)
        assert devs["valve"]["commands"] > 1  # 40 % while it ran, then the safe value
        deadline = time.monotonic() + 10
        while "valve=0" not in "".join(lines[-1:]) and time.monotonic() < deadline:
            threading.Event().wait(0.2)
        sim.send_signal(signal.SIGINT)
        assert sim.wait(timeout=20) == 0
        assert any("valve=40" in ln for ln in lines), "".join(lines)
        assert "valve=0" in lines[-1]  # the safe value is what the slave holds at the end
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.wait()


def test_sim_from_map_faults_on_a_schedule(tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    scaffold.create(tmp_path / "cell", port=free_port())
    devices = str(tmp_path / "cell" / "devices.toml")
    assert cli.main(["sim", "--from", devices, "--value", "level=42", "--fault", "plc@0.3-0.6",
                     "--duration", "1"]) == 0
    out = capsys.readouterr().out
    assert "fault: plc silenced" in out and "fault over: plc answers again" in out
    assert "level=42" in out
    assert cli.main(["sim", "--from", devices, "--fault", "plc@5-2"]) == 2
    assert "the end must come after the start" in capsys.readouterr().err
    assert cli.main(["sim", "--from", devices, "--value", "valve=3"]) == 2
    assert "'valve' is not a sensor" in capsys.readouterr().err


def test_vendor_node_with_sync_tpdos_and_no_defaults_runs_virtual(tmp_path: Path) -> None:
    # the awkward EDS: synchronous TPDO1 (statusword, position), objects without a
    # DefaultValue, empty numeric fields. Imported as is, it runs healthy on virtual time: the
    # imported sync_period makes the simulated node send TPDO1 and SDO reads of an object
    # without a default are answered (0)
    devmap = tmp_path / "ax7.toml"
    assert cli.main(["import", "eds", str(VENDOR / "awkward_ax7.eds"), "--node", "3",
                     "--bus", "ax", "--all", "-o", str(devmap)]) == 0
    system = _system(tmp_path, devmap, "install -m0 sysfile\n")
    with cellrun.open_cell(system, virtual=True) as cell:
        slaves = cell.slaves
        assert slaves is not None
        node = slaves.canopen_node("ax", 3)
        assert node.wait_state("OPERATIONAL", 10)
        # simulated as a CiA 402 drive: enabled by the controlword, shown by TPDO1 on SYNC
        for cw in (0x06, 0x07, 0x0F):
            cell.system.devtab.write("controlword", cw)
            cell.run_for(0.1)
        deadline = time.monotonic() + 10
        while cell.device("statusword").value != 0x0237 and time.monotonic() < deadline:
            cell.run_for(0.05)       # SYNC runs on wall time: give it some
        assert cell.device("statusword").value == 0x0237                # by TPDO1, on SYNC
        assert cell.device("position_actual_value").value == 0
        assert node.stats.syncs > 0 and node.stats.tpdos > 0
        cell.run_for(0.5)
        assert cell.device("heat_sink_temperature").value == 0          # no default: zero
        assert cell.device("heat_sink_temperature").status.value == "OK"
        with pytest.raises(DeviceError, match="'nope' has no simulated peer"):
            slaves.canopen_node("nope", 3)
        with pytest.raises(DeviceError, match="no simulated CANopen node 9"):
            slaves.canopen_node("ax", 9)


def test_sim_from_map_raises_emcy_faults_on_a_schedule(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    import can

    from chcos.apps.sim import from_map

    # the observer below is in this very process: the process-local virtual channel, which
    # `chcos sim --from` refuses for a `chcos run` in another process, is heard here
    monkeypatch.setattr(from_map, "process_local", lambda devmap: [])
    channel = f"emcy-{os.getpid()}"
    devmap = tmp_path / "ax7.toml"
    assert cli.main(["import", "eds", str(VENDOR / "awkward_ax7.eds"), "--node", "3",
                     "--bus", "ax", "--interface", "virtual", "--channel", channel,
                     "-o", str(devmap)]) == 0
    wire = can.Bus(interface="virtual", channel=channel)   # what the node puts on the bus
    try:
        assert cli.main(["sim", "--from", str(devmap), "--emcy", "ax:3:0x4210@0.2-0.5",
                         "--duration", "0.8"]) == 0
        frames = []
        while (msg := wire.recv(0)) is not None:
            frames.append(msg)
    finally:
        wire.shutdown()
    out = capsys.readouterr().out
    assert "fault: node 3 EMCY 0x4210" in out and "fault over: node 3 error reset" in out
    assert bytes(frames[0].data) == b"\x00" and frames[0].arbitration_id == 0x703  # boot-up
    emcy = [bytes(m.data) for m in frames if m.arbitration_id == 0x83]
    assert emcy == [bytes.fromhex("1042090000000000"), bytes(8)]
    for bad in ("ax:3:0x10@1", "ax:9:0x4210@1", "nope:3:0x4210@1", "ax:0x4210@1"):
        assert cli.main(["sim", "--from", str(devmap), "--emcy", bad]) == 2
    err = capsys.readouterr().err
    assert "--emcy 'ax:9:0x4210@1': bus 'ax' has no simulated CANopen node 9" in err
