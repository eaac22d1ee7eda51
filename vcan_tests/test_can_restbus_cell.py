"""A scaffolded cell (``chcos new``) moved onto a CAN bus with a DBC: cyclic messages with
counters and checksums against the simulated ECU on the direct bus, the ECU's command timeout,
and bus faults as test steps through the pytest plugin (``cell.bus_fault``)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import cantools
import pytest

from chcos.cli import scaffold
from chcos.errors import DeviceError
from chcos.testing import TestCell
from drivers.can_direct import DirectBus

DBC = """VERSION ""
NS_ :
BS_:
BU_: PLC CHCOS
BO_ 256 LEVEL_STATUS: 4 PLC
 SG_ CHECKSUM : 0|8@1+ (1,0) [0|255] "" CHCOS
 SG_ COUNTER : 8|4@1+ (1,0) [0|15] "" CHCOS
 SG_ LEVEL : 16|16@1+ (0.1,0) [0|200] "cm" CHCOS
BO_ 512 VALVE_CMD: 3 CHCOS
 SG_ CHECKSUM : 0|8@1+ (1,0) [0|255] "" PLC
 SG_ COUNTER : 8|4@1+ (1,0) [0|15] "" PLC
 SG_ OPENING : 16|8@1+ (1,0) [0|100] "%" PLC
BA_DEF_ BO_ "GenMsgCycleTime" INT 0 65535;
BA_DEF_DEF_ "GenMsgCycleTime" 0;
BA_ "GenMsgCycleTime" BO_ 256 10;
BA_ "GenMsgCycleTime" BO_ 512 20;
"""

DEVICES = """\
[[bus]]
name = "plc"
kind = "can"
interface = "socketcan"
channel = "can0"
dbc = "plc.dbc"

[[bus.message]]
name = "LEVEL_STATUS"
counter = "COUNTER"
checksum = {{ signal = "CHECKSUM", algorithm = "crc8-sae-j1850" }}

[[bus.message]]
name = "VALVE_CMD"
{valve_cycle}counter = "COUNTER"
checksum = {{ signal = "CHECKSUM", algorithm = "crc8-sae-j1850" }}

[[device]]
name = "level"
direction = "sensor"
bus = "plc"
address = {{ message = "LEVEL_STATUS", signal = "LEVEL" }}
units = "cm"
limits = [0.0, 150.0]
stale_after = 0.1

[[device]]
name = "valve"
direction = "actuator"
bus = "plc"
address = {{ message = "VALVE_CMD", signal = "OPENING" }}
units = "%"
limits = [0.0, 100.0]
safe_value = 0.0
"""


def _project(tmp_path: Path, valve_cycle: str = "") -> Path:
    root = tmp_path / "cell"
    scaffold.create(root, port=5020)
    (root / "plc.dbc").write_text(DBC)
    (root / "devices.toml").write_text(DEVICES.format(valve_cycle=valve_cycle))
    return root


@pytest.fixture
def project(tmp_path: Path) -> Path:
    return _project(tmp_path)


def _ecu(cell: TestCell) -> Any:
    assert cell.cell.slaves is not None
    return cell.cell.slaves.peers["plc"]


def test_the_scaffold_on_can_runs_cyclic_with_counters_and_checksums(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    cell.set("level", 90.0)
    cell.run_for(1.0)
    assert cell.value("level") == pytest.approx(90.0) and cell.status("level") == "OK"
    assert cell.peer("valve") == 60                  # the ECU took the command
    ecu = _ecu(cell)
    assert ecu.rejected == {} and ecu.timeouts == 0  # every frame's counter and CRC right
    state = cell.bus_state("plc")
    assert state["state"] == "error-active" and state["bus_offs"] == 0
    cyclic = cell.system.devtab.statuses()["plc"].cyclic
    # VALVE_CMD every 20 ms of virtual time since the task's first command: ~50 in 1 s
    assert cyclic[0].message == "VALVE_CMD" and 45 <= (cyclic[0].frames or 0) <= 51
    assert "cyclic   plc              VALVE_CMD every 20 ms, " in cell.execute("map")


def _devices_only(root: Path) -> Path:
    """A system of the cell's devices alone (no task): commands come from the test."""
    (root / "devices_only.toml").write_text('[system]\nname = "bare"\n'
                                            'devmaps = ["devices.toml"]\n')
    return root / "devices_only.toml"


def test_a_command_not_repeated_at_its_cycle_times_out_at_the_ecu(
        tmp_path: Path, chcos_cell: Callable[..., TestCell]) -> None:
    # the map says VALVE_CMD is event-driven; the ECU (the DBC: 20 ms) drops it after 3 cycles
    cell = chcos_cell(_devices_only(_project(tmp_path, valve_cycle="cycle_time = 0\n")))
    cell.system.devtab.write("valve", 60.0)
    cell.run_for(0.05)
    assert cell.peer("valve") == 60
    cell.run_for(0.1)
    assert cell.value("valve") == 60     # chcos holds 60, sent once ...
    assert cell.peer("valve") == 0       # ... so the ECU fell back to its substitute value
    assert _ecu(cell).timeouts == 1


def test_the_same_command_on_the_dbc_cycle_is_kept_by_the_ecu(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(_devices_only(project))
    cell.system.devtab.write("valve", 60.0)
    cell.run_for(5.0)
    assert cell.peer("valve") == 60 and _ecu(cell).timeouts == 0
    frames = cell.system.devtab.statuses()["plc"].cyclic[0].frames
    assert frames == 251                 # at 0, 0.02, ... 5.0 s: drift-free on virtual time


def test_bus_off_fails_the_bus_and_the_safe_value_goes_first_after_the_restart(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    cell.set("level", 90.0)
    cell.run_for(1.0)
    assert cell.peer("valve") == 60
    seen: list[Any] = []
    ecu = _ecu(cell)
    spy = can.Bus(interface="chcos-direct", channel=ecu.args["channel"])
    spy.set_receiver(lambda f: seen.append((cell.now, f.arbitration_id, bytes(f.data),
                                            f.is_error_frame)))
    try:
        cell.bus_fault("plc", "bus-off", 2.0)
        cell.run_for(0.5)
        assert cell.status("level") == "failed" and cell.status("valve") == "failed"
        assert "bus-off" in cell.system.devtab.get("valve").reason
        assert cell.bus_state("plc")["state"] == "bus-off"
        assert cell.task("fill").abnormal == 1
        cell.run_for(2.0)                # restarted at 2 s: the cell rides through
        state = cell.bus_state("plc")
        assert state["state"] == "error-active" and state["bus_offs"] == 1
        assert state["restarts"] == 1 and state["tx_errors"] == 0
        assert cell.status("level") == "OK" and cell.status("valve") == "OK"
        cell.run_for(1.0)                # fill restarts on recovery, after its 0.5 s back-off
        assert cell.peer("valve") == 60
    finally:
        spy.shutdown()
    db = cantools.database.load_file(str(project / "plc.dbc"))
    valve = [(t, db.decode_message(0x200, d)["OPENING"]) for t, i, d, err in seen
             if i == 0x200 and not err]
    # the spy is a controller of its own on the wire: bus-off too, it heard nothing meanwhile;
    # after the restart the first opening on the wire is the safe value, then the command
    after = [v for t, v in valve if t > 2.0]
    assert after[0] == 0 and 60 in after
    assert all(not 0.0 < t < 2.0 for t, _ in valve[1:] if t > 1.0)


def test_error_frames_drive_the_counters_to_error_passive_and_back(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    cell.set("level", 90.0)
    cell.run_for(0.5)
    cell.bus_fault("plc", "error-frame", 1.5)     # one error frame every 10 ms for 1.5 s
    cell.run_for(1.6)
    state = cell.bus_state("plc")
    # +8 per error frame, -1 (or back to 127) per LEVEL_STATUS received well, both every 10 ms
    assert state["error_passive"] >= 1 and state["rx_errors"] >= 120
    assert cell.status("level") == "OK"           # error-passive still talks
    errors = cell.system.devtab.bus_stats["plc"].errors
    assert errors["error-frame"] >= 150 and errors["error-passive"] == state["error_passive"]
    assert cell.peer("valve") == 60               # and the commands still go out
    cell.run_for(3.0)                             # each frame received well counts one down
    state = cell.bus_state("plc")
    assert state["state"] == "error-active" and state["bus_offs"] == 0


def test_bus_fault_names_the_faults_and_refuses_other_buses(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    cell = chcos_cell(project / "system.toml")
    with pytest.raises(DeviceError, match="no bus fault 'melt'; expected one of error-frame"):
        cell.bus_fault("plc", "melt")
    with pytest.raises(DeviceError, match="bus 'nobus' has no simulated peer"):
        cell.bus_fault("nobus", "bus-off")


def test_sim_fault_syntax_names_bus_faults_and_applies_them_on_the_wire(
        project: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from chcos.apps.sim.from_map import _apply_faults, _fault, simulate
    from chcos.cli import main as cli
    from chcos.devices.devmap import load
    from drivers.codecs.can_errors import ControllerState, decode_error_frame

    scaffold.create(project.parent / "plain", port=5020)
    assert cli.main(["sim", "--from", str(project.parent / "plain" / "devices.toml"),
                     "--fault", "plc:bus-off@1-2"]) == 2
    assert "bus-off is a CAN bus fault; 'plc' is a 'modbus-tcp' bus" in capsys.readouterr().err
    slaves = simulate(load([str(project / "devices.toml")]))
    try:
        with pytest.raises(Exception, match="no fault 'melt'; expected one of silence, "
                                            "error-frame, error-passive, bus-off"):
            _fault("plc:melt@1", slaves)
        faults = [_fault("plc:bus-off@0.5-1.5", slaves)]
        spy = DirectBus(channel=slaves.peers["plc"].args["channel"])
        seen: list[Any] = []
        spy.set_receiver(seen.append)
        active: set[int] = set()
        lines = []
        for k in range(0, 200):                     # the peer's clock, ticked every 10 ms
            t = k / 100
            slaves.tick(t)
            lines += _apply_faults(slaves, faults, active, t)
        states = [decode_error_frame(f.arbitration_id, f.data).state for f in seen
                  if f.is_error_frame]
        assert states == [ControllerState.BUS_OFF, ControllerState.ERROR_ACTIVE]
        assert lines == ["fault: plc bus-off", "fault over: plc bus-off ended (controllers "
                         "restarted)"]
        spy.shutdown()
    finally:
        slaves.close()


def test_the_ecu_rejects_a_command_frame_with_a_wrong_crc_or_counter(
        project: Path, chcos_cell: Callable[..., TestCell]) -> None:
    from vcan_tests.test_can_e2e import j1850

    cell = chcos_cell(_devices_only(project))     # nobody else sends VALVE_CMD
    ecu = _ecu(cell)
    db = cantools.database.load_file(str(project / "plc.dbc"))
    other = DirectBus(channel=ecu.args["channel"])

    def send(counter: int, opening: int, crc_ok: bool = True) -> None:
        data = bytearray(db.encode_message("VALVE_CMD", {"CHECKSUM": 0, "COUNTER": counter,
                                                         "OPENING": opening}))
        data[0] = j1850(bytes(data[1:])) ^ (0 if crc_ok else 0xFF)
        other.send(can.Message(arbitration_id=0x200, data=bytes(data), is_extended_id=False))
    try:
        send(0, 30)
        assert cell.peer("valve") == 30
        send(1, 70, crc_ok=False)                 # refused: the ECU keeps 30
        send(1, 70)
        send(1, 80)                               # the counter repeated: refused
        assert cell.peer("valve") == 70
        assert ecu.rejected == {"checksum": 1, "counter": 1}
    finally:
        other.shutdown()
