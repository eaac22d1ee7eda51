"""``chcos import eds|dbc|modbus``: device maps from vendor-style files chcos did not write
(vcan_tests/vendor/: an EDS of a CiA 402 drive with CRLF lines, records, a disabled RPDO and
limits; a DBC with an extended id, Motorola signals, value tables and cycle times; a semicolon
register list with decimal commas, and a Modicon-numbered one). Each map passes ``chcos check``
and then carries values both ways against an independent peer: python-can + cantools for the
DBC, pyModbusTCP's server for the register list, canopen's LocalNode (under chcos' slave, which
only adds TPDO transmission) for the EDS."""

from __future__ import annotations

import itertools
import os
import tomllib
from pathlib import Path
from typing import Any

import can
import cantools
import pytest
from pyModbusTCP.server import ModbusServer

from chcos.apps.sim.canopen_slave import CanopenSlave
from chcos.cli import main as cli
from chcos.devices.devmap import check_main
from chcos.devices.importers.modbus_csv import import_modbus_csv
from chcos.errors import ConfigError
from chcos.helpers import free_port
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System

VENDOR = Path(__file__).resolve().parent / "vendor"
_chan = itertools.count()


def _channel(tag: str) -> str:
    return f"i18-{tag}-{os.getpid()}-{next(_chan)}"


def _import(tmp_path: Path, *args: str) -> tuple[Path, dict[str, Any]]:
    out = tmp_path / "imported.toml"
    assert cli.main(["import", *args, "-o", str(out)]) == 0
    assert check_main([str(out)]) == 0  # chcos check accepts it
    doc = tomllib.loads(out.read_text(encoding="utf-8"))
    return out, {d["name"]: d for d in doc["device"]}


def test_eds_import_round_trip(tmp_path: Path) -> None:
    chan = _channel("co")
    out, devs = _import(tmp_path, "eds", str(VENDOR / "acme_amd200.eds"), "--node", "5",
                        "--interface", "virtual", "--channel", chan, "--bus", "axis",
                        "--plain")
    text = out.read_text(encoding="utf-8")
    assert "AMD-200 (ACME Motion GmbH)" in text and "heartbeat_timeout = 0.3" in text
    direction = {n: d["direction"] for n, d in devs.items()}
    assert direction == {
        "statusword": "sensor", "position_actual_value": "sensor",     # TPDO1
        "velocity_actual_value": "sensor", "supply_monitor_dc_bus_voltage": "sensor",  # TPDO2
        "controlword": "actuator", "target_position": "actuator",      # RPDO1
        "heat_sink_temperature": "sensor", "supply_monitor_logic_supply_voltage": "sensor",
        "brake_release": "actuator", "modes_of_operation": "sensor",
        "modes_of_operation_display": "sensor", "target_torque": "actuator",
        "torque_actual_value": "sensor",
        "target_velocity": "actuator",  # mapped only in the disabled RPDO2: SDO
    }
    assert devs["position_actual_value"]["address"] == {"node": 5, "index": 0x6064,
                                                        "subindex": 0}
    assert "index = 0x6064" in text
    assert devs["position_actual_value"]["stale_after"] == 0.05  # 5 x the 10 ms event timer
    assert devs["heat_sink_temperature"]["limits"] == [-40.0, 125.0]
    assert devs["target_torque"]["limits"] == [-3000.0, 3000.0]
    # values both ways against the node
    slave = CanopenSlave(5, VENDOR / "acme_amd200.eds", channel=chan, heartbeat_period=0.0)
    slave.start()
    try:
        mapfile = tmp_path / "nohb.toml"
        # the slave's heartbeat runs on real time: no supervision on virtual time here
        mapfile.write_text(text.replace(", heartbeat_timeout = 0.3", ""), encoding="utf-8")
        with System([mapfile], clock=VirtualClock(), machines=[0]) as s:
            assert slave.wait_state("OPERATIONAL", 10)
            slave.set(0x6064, 0, -12345)
            slave.set(0x2000, 0, 57)
            s.run_for(0.5)
            assert s.devtab.get("position_actual_value").value == -12345  # by TPDO
            assert s.devtab.get("heat_sink_temperature").value == 57      # by SDO
            s.devtab.write("target_position", 4096)
            s.devtab.write("target_torque", -250)
            s.run_for(0.5)
            assert slave.get(0x607A, 0) == 4096   # by RPDO
            assert slave.get(0x6071, 0) == -250   # by SDO download
    finally:
        slave.stop()


def test_dbc_import_round_trip(tmp_path: Path) -> None:
    chan = _channel("can")
    out, devs = _import(tmp_path, "dbc", str(VENDOR / "hpu_press.dbc"), "--node", "CELL_CTRL",
                        "--interface", "virtual", "--channel", chan)
    text = out.read_text(encoding="utf-8")
    assert set(devs) == {"oil_pressure", "oil_temperature", "tank_level", "filter_clogged",
                         "pump_state", "pressure_setpoint", "pump_enable", "reserved_1",
                         "ram_position", "ram_speed", "valve_down", "valve_up"}
    assert {n for n, d in devs.items() if d["direction"] == "actuator"} == {
        "pressure_setpoint", "pump_enable", "reserved_1", "valve_down", "valve_up"}
    assert devs["oil_temperature"]["limits"] == [-40.0, 150.0]
    assert devs["oil_temperature"]["units"] == "degC"
    assert devs["ram_speed"]["units"] == "mm/s" and devs["ram_speed"]["limits"] == [-300.0, 300.0]
    assert devs["oil_pressure"]["stale_after"] == 0.1  # 5 x 20 ms GenMsgCycleTime
    assert "raw * 1 + -40 (applied by the driver)" in text
    assert "values: 0 Off, 1 Starting, 2 Running, 3 Fault" in text
    assert "0xCF000FE, extended" in text
    db = cantools.database.load_file(str(VENDOR / "hpu_press.dbc"))
    with can.Bus(interface="virtual", channel=chan) as peer, \
            System([out], clock=VirtualClock(), machines=[0]) as s:
        status = db.get_message_by_name("HPU_Status")
        peer.send(can.Message(arbitration_id=status.frame_id, is_extended_id=True,
                              data=status.encode({"OilPressure": 212.5, "OilTemperature": 48,
                                                  "TankLevel": 71.5, "PumpState": 2,
                                                  "FilterClogged": 0})))
        s.run_for(0.05)
        assert s.devtab.get("oil_pressure").value == pytest.approx(212.5)
        assert s.devtab.get("oil_temperature").value == 48
        assert s.devtab.get("pump_state").value == 2
        s.devtab.write("pressure_setpoint", 180.25)
        s.run_for(0.05)
        frame = peer.recv(timeout=5)
        assert frame is not None and frame.arbitration_id == 418
        assert db.decode_message(418, frame.data)["PressureSetpoint"] == pytest.approx(180.25)


def test_modbus_register_list_round_trip(tmp_path: Path) -> None:
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True)
    server.start()
    try:
        out, devs = _import(tmp_path, "modbus", str(VENDOR / "plc_registers.csv"), "--port",
                            str(server.port))
        assert devs["tank_level"]["scale"] == 0.1 and devs["tank_level"]["units"] == "cm"
        assert devs["tank_temp"]["offset"] == -50.0
        assert devs["flow_rate"]["address"] == {"unit": 1, "table": "input", "address": 10,
                                                "type": "float32", "word_order": "little"}
        assert devs["total_volume"]["address"]["type"] == "int32"
        assert {n for n, d in devs.items() if d["direction"] == "actuator"} == {
            "inlet_valve", "pump_start"}
        db = server.data_bank
        db.set_input_registers(0, [1234, 700])  # 123.4 cm; 700 * 0.1 - 50 = 20 degC
        db.set_input_registers(10, [0x0000, 0x4248])  # 50.0 as float32, low word first
        db.set_discrete_inputs(0, [True])
        with System([out], clock=VirtualClock(), machines=[0]) as s:
            s.run_for(0.5)
            assert s.devtab.get("tank_level").value == pytest.approx(123.4)
            assert s.devtab.get("tank_temp").value == pytest.approx(20.0)
            assert s.devtab.get("flow_rate").value == pytest.approx(50.0)
            assert s.devtab.get("pump_running").value is True
            s.devtab.write("inlet_valve", 55)
            s.devtab.write("pump_start", True)
            s.run_for(0.5)
            assert db.get_holding_registers(100) == [55]
            assert db.get_coils(0) == [True]
    finally:
        server.stop()


def test_modicon_list_and_bad_rows(tmp_path: Path) -> None:
    _, devs = _import(tmp_path, "modbus", str(VENDOR / "modicon_list.csv"))
    assert devs["pressure"]["address"] == {"unit": 1, "table": "input", "address": 0,
                                           "type": "int16"}
    assert devs["setpoint"]["address"]["table"] == "holding"
    assert devs["setpoint"]["direction"] == "sensor"  # no access column: never written
    assert devs["alarm"]["address"] == {"unit": 1, "table": "discrete", "address": 2,
                                        "type": "bool"}
    bad = tmp_path / "bad.csv"
    bad.write_text("name,table,address,type\nvalve,holding,7,QWORD\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad.csv: row 2: type 'QWORD': expected one of"):
        import_modbus_csv(bad)
    bad.write_text("name,area,address\nx,flash,1\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"row 2: table 'flash'"):
        import_modbus_csv(bad)
    assert cli.main(["import", "modbus", str(bad)]) == 2


def test_import_errors_name_the_file(tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str]) -> None:
    junk = tmp_path / "junk.eds"
    junk.write_text("not an eds\n", encoding="utf-8")
    assert cli.main(["import", "eds", str(junk), "--node", "3"]) == 2
    assert "junk.eds" in capsys.readouterr().err
    assert cli.main(["import", "eds", str(VENDOR / "acme_amd200.eds"), "--node", "200"]) == 2
    assert "expected a CANopen node id 1..127" in capsys.readouterr().err
    assert cli.main(["import", "dbc", str(VENDOR / "hpu_press.dbc"), "--node", "NOPE"]) == 2
    assert "expected one of the DBC's nodes (CELL_CTRL, HPU, PRESS_IO)" in capsys.readouterr().err


def test_awkward_eds_imports_with_warnings_and_passes_check(
        tmp_path: Path, capsys: pytest.CaptureFixture[str],
        caplog: pytest.LogCaptureFixture) -> None:
    awkward = VENDOR / "awkward_ax7.eds"
    import canopen

    with pytest.raises(ValueError):
        canopen.import_od(str(awkward), 3)   # the library alone rejects the whole file
    out, devs = _import(tmp_path, "eds", str(awkward), "--node", "3", "--bus", "ax")
    err = capsys.readouterr().err
    # each empty numeric field named with its file, section and key - a warning, not an error
    assert "awkward_ax7.eds: [DeviceInfo] VendorNumber: empty value" in err
    assert "[Comments] Lines: empty value; read as 0" in err
    assert "[2000] PDOMapping: empty value" in err
    assert "no heartbeat producer (0x1017 default 0)" in err
    assert "TPDO1 (type 1) is synchronous" in err and "sync_period = 0.01 s was chosen" in err
    assert "DefaultValue" not in err               # no warning per object without a default
    # chcos check (run by _import) reads the same file: a logged warning, not a rejection
    assert any("awkward_ax7.eds: [DeviceInfo] VendorNumber: empty value" in r.getMessage()
               for r in caplog.records if r.name == "chcos.eds")
    doc = tomllib.loads(out.read_text(encoding="utf-8"))
    bus = doc["bus"][0]
    assert bus["sync_period"] == 0.01              # the synchronous TPDO gets its SYNC
    assert set(bus["nodes"][0]) == {"id", "eds"}
    assert "heartbeat_timeout" not in bus["nodes"][0]   # a suggestion, as a comment only
    text = out.read_text(encoding="utf-8")
    assert "# Heartbeat: node 3 produces none" in text and "heartbeat_timeout = 0.3" in text
    assert "also mapped in RPDO2" in text
    assert "7 object(s) have no DefaultValue" in text
    assert devs["statusword"]["stale_after"] == 0.05      # 5 x (every SYNC x 10 ms)
    assert devs["velocity_actual_value"]["stale_after"] == 0.25   # 5 x 50 ms event timer
    assert devs["controlword"]["limits"] == [0.0, 65535.0]        # UNSIGNED16, no EDS limits
    assert {n for n, d in devs.items() if d["direction"] == "actuator"} == {
        "controlword", "modes_of_operation"}


def test_eds_communication_cycle_sets_sync_period(tmp_path: Path) -> None:
    text = (VENDOR / "awkward_ax7.eds").read_text(encoding="utf-8")
    cycle = ("[1006]\nParameterName=Communication cycle period\nObjectType=0x7\n"
             "DataType=0x0007\nAccessType=rw\nDefaultValue=4000\nPDOMapping=0\n\n")
    eds = tmp_path / "cycle.eds"
    eds.write_text(text.replace("[1010]", cycle + "[1010]"), encoding="utf-8")
    out, devs = _import(tmp_path, "eds", str(eds), "--node", "3")
    assert tomllib.loads(out.read_text(encoding="utf-8"))["bus"][0]["sync_period"] == 0.004
    assert devs["statusword"]["stale_after"] == 0.02
    # transmission type 4: a PDO every fourth SYNC, stale after five of those
    eds.write_text(text.replace("[1010]", cycle + "[1010]").replace(
        "ParameterName=Transmission type\nObjectType=0x7\nDataType=0x0005\n"
        "AccessType=rw\nDefaultValue=1", "ParameterName=Transmission type\n"
        "ObjectType=0x7\nDataType=0x0005\nAccessType=rw\nDefaultValue=4"),
        encoding="utf-8")
    out, devs = _import(tmp_path, "eds", str(eds), "--node", "3")
    assert devs["statusword"]["stale_after"] == 0.08


def test_eds_empty_required_field_is_an_error_naming_it(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = (VENDOR / "awkward_ax7.eds").read_text(encoding="utf-8")
    eds = tmp_path / "broken.eds"
    eds.write_text(text.replace("[6041]\nParameterName=Statusword\nObjectType=0x7\n"
                                "DataType=0x0006", "[6041]\nParameterName=Statusword\n"
                                "ObjectType=0x7\nDataType="), encoding="utf-8")
    assert cli.main(["import", "eds", str(eds), "--node", "3"]) == 2
    assert "broken.eds: [6041] DataType: empty; expected a number" in capsys.readouterr().err


def test_eds_in_latin1_is_read_with_a_warning(tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    text = (VENDOR / "awkward_ax7.eds").read_text(encoding="utf-8")
    eds = tmp_path / "latin.eds"
    eds.write_bytes(text.replace("ParameterName=Heat sink temperature",
                                 "ParameterName=Kühlkörpertemperatur").encode("latin-1"))
    out, devs = _import(tmp_path, "eds", str(eds), "--node", "3", "--objects", "0x2000")
    assert "latin.eds: not UTF-8; read as Latin-1" in capsys.readouterr().err
    assert "# 0x2000:00 Kühlkörpertemperatur: SDO" in out.read_text(encoding="utf-8")
    assert devs["k_hlk_rpertemperatur"]["address"]["index"] == 0x2000
