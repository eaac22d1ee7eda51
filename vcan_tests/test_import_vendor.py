"""Importers that tell the truth about the device (issue 49): every shipped vendor file and the new
ones (a CiA 401 I/O module EDS, an automotive DBC with counters and checksums and no nodes, a
SunSpec inverter device file) imported, checked, simulated and run healthy on virtual time, with
assertions on what the map says (addresses, scales, timeouts, senders); the SunSpec layout
against pysunspec2's own register image; addresses as the device documents them; ranges against
what a signal, register or object carries; refusals that name the line, row or key; and a
property test mutating the shipped files (0 tracebacks, 0 hangs, 0 invalid maps).

Tests marked ``needs_can_messages`` / ``needs_modbus_sunspec`` run once the drivers take the keys
these maps declare (:mod:`vcan_tests.support_import`)."""

from __future__ import annotations

import random
import shutil
import tempfile
import tomllib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chcos.cli.main import main as cli_main
from chcos.devices.importers.dbc import import_dbc
from chcos.devices.importers.draft import MapDraft, render
from chcos.devices.importers.eds import import_eds
from chcos.devices.importers.modbus_csv import import_modbus_csv
from chcos.devices.importers.sunspec import import_sunspec, parse_models, read_device
from chcos.errors import ConfigError
from vcan_tests.support_import import (
    DOCS_VENDOR,
    VENDOR,
    needs_can_messages,
    needs_modbus_sunspec,
)


def _doc(draft: MapDraft) -> tuple[str, dict[str, Any], dict[str, Any]]:
    """A draft's text, its devices by name and its first bus."""
    text = render(draft)
    doc = tomllib.loads(text)
    return text, {d["name"]: d for d in doc["device"]}, doc["bus"][0]


def _cli(tmp_path: Path, capsys: pytest.CaptureFixture[str], *args: str,
         out: str = "map.toml") -> tuple[int, str]:
    capsys.readouterr()
    status = cli_main(["import", *args, "-o", str(tmp_path / out)])
    return status, capsys.readouterr().err


def _run_virtual(tmp_path: Path, capsys: pytest.CaptureFixture[str], maps: list[str],
                 *extra: str, duration: float = 2.0) -> str:
    """``chcos run --virtual`` of ``maps`` (in ``tmp_path``); returns the run's summary."""
    (tmp_path / "install.chcos").write_text("install -m0 sysfile\n", encoding="utf-8")
    (tmp_path / "system.toml").write_text(
        '[system]\nname = "vendor"\ndevmaps = [' + ", ".join(f'"{m}"' for m in maps)
        + ']\ninstall = "install.chcos"\n', encoding="utf-8")
    capsys.readouterr()
    assert cli_main(["run", str(tmp_path / "system.toml"), "--virtual", "--duration",
                     str(duration), *extra]) == 0
    return capsys.readouterr().out.split("summary")[-1]


# ---- a CiA 401 I/O module ---------------------------------------------------------------------
def test_io_module_tpdos_never_sent_are_warned_with_the_fix() -> None:
    draft = import_eds(DOCS_VENDOR / "io_module.eds", 7, bus="io", eds_ref="io_module.eds")
    text, devs, bus = _doc(draft)
    never = [w for w in draft.warnings if "never sends it on its own" in w]
    assert len(never) == 2
    assert "node 7 TPDO2 (0x1801, COB-ID 0x287): transmission type 255 with event timer 0" \
        in never[1]
    assert 'config = {pdos = [{pdo = "tpdo1", event_timer_ms = 100}' in never[1]
    assert "--event-timer MS" in never[1] and "SYNC" in never[1]
    # no timeout can be known for them, and the map says why
    assert "stale_after" not in devs["read_analogue_input_16_bit_analogue_input_1"]
    assert "no event timer: sent only when the node decides" in text
    assert "config" not in bus["nodes"][0]


def test_io_module_with_an_event_timer_runs_healthy(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    shutil.copy(DOCS_VENDOR / "io_module.eds", tmp_path)
    status, err = _cli(tmp_path, capsys, "eds", str(tmp_path / "io_module.eds"), "--node", "7",
                       "--bus", "io", "--names", "short", "--event-timer", "50",
                       "--interface", "virtual", "--channel", "io401",
                       "--rename", "read_input_1h=inputs")
    assert status == 0, err
    _text, devs, bus = _doc_of(tmp_path / "map.toml")
    assert bus["nodes"][0]["eds"] == "io_module.eds"          # relative to the map
    assert bus["nodes"][0]["config"] == {"pdos": [{"pdo": "tpdo1", "event_timer_ms": 50},
                                                  {"pdo": "tpdo2", "event_timer_ms": 50}]}
    assert set(devs) >= {"inputs", "analogue_input_1", "analogue_output_2",
                         "write_output_1h"}
    assert devs["inputs"]["address"] == {"node": 7, "index": 0x6000, "subindex": 1}
    assert devs["analogue_input_4"]["stale_after"] == 0.25    # 5 x the 50 ms event timer
    assert devs["analogue_output_1"]["limits"] == [0.0, 27648.0]   # the EDS's High/LowLimit
    assert devs["write_output_1h"]["limits"] == [0.0, 255.0]       # UNSIGNED8
    assert "never sends it" not in err
    summary = _run_virtual(tmp_path, capsys, ["map.toml"])
    assert "inputs" in summary and "healthy" in summary, summary


def _doc_of(path: Path) -> tuple[str, dict[str, Any], dict[str, Any]]:
    text = path.read_text(encoding="utf-8")
    doc = tomllib.loads(text)
    return text, {d["name"]: d for d in doc["device"]}, doc["bus"][0]


# ---- DBC: who sends what, counters, ranges, freshness ------------------------------------------
def test_vehicle_dbc_without_nodes_send_decides_the_actuators() -> None:
    with pytest.raises(ConfigError, match=r"--node 'EPS': expected one of the DBC's nodes "
                                          r"\(none: name the messages chcos sends with --send"):
        import_dbc(DOCS_VENDOR / "vehicle.dbc", node="EPS")
    draft = import_dbc(DOCS_VENDOR / "vehicle.dbc", send=["STEERING_CONTROL", "BRAKE_*"],
                       checksums={"BRAKE_COMMAND": {"algorithm": "crc8-sae-j1850"}})
    _text, devs, bus = _doc(draft)
    actuators = {n for n, d in devs.items() if d["direction"] == "actuator"}
    assert actuators == {"steer_torque", "steer_torque_request", "set_me_x00",
                         "brake_pressure_req", "brake_request"}
    tables = {m["name"]: m for m in bus["message"]}
    assert tables["STEERING_CONTROL"] == {"name": "STEERING_CONTROL", "counter": "COUNTER",
                                          "checksum": {"signal": "CHECKSUM", "algorithm": "sum"}}
    # found by place: E2E profile 1's CRC in byte 0 named "CS", the counter beside it
    assert tables["BRAKE_COMMAND"] == {"name": "BRAKE_COMMAND", "counter": "BRK_MC",
                                       "checksum": {"signal": "BRK_CS",
                                                    "algorithm": "crc8-sae-j1850"}}
    assert tables["STEER_STATUS"]["counter"] == "COUNTER"     # checked on receive
    assert "brk_cs" not in devs and "brk_mc" not in devs      # computed, not devices
    assert any("STEERING_CONTROL: checksum CHECKSUM: algorithm sum is a guess" in w
               for w in draft.warnings)
    assert not any("BRAKE_COMMAND: checksum" in w for w in draft.warnings)
    # freshness from the cycle times; a message without one is named
    assert devs["steer_torque_sensor"]["stale_after"] == 0.05      # 5 x 10 ms
    assert devs["wheel_speed_rr"]["stale_after"] == 0.1            # 5 x 20 ms
    assert "stale_after" not in devs["door_open_fl"]
    assert any("no cycle time (GenMsgCycleTime) for DOORS_STATUS" in w for w in draft.warnings)
    # opendbc's [-31000|31000] on a 16-bit x -0.1 signal: clamped to what it carries
    assert devs["steer_angle_rate"]["limits"] == [-3276.7, 3276.8]
    assert any("STEER_ANGLE_RATE: limits -31000..31000 exceed what it can carry" in w
               for w in draft.warnings)
    with pytest.raises(ConfigError, match=r"--send 'NOPE': no such message"):
        import_dbc(DOCS_VENDOR / "vehicle.dbc", send=["NOPE"])


@needs_can_messages
def test_vehicle_dbc_imported_checked_and_run_healthy(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    shutil.copy(DOCS_VENDOR / "vehicle.dbc", tmp_path)
    status, err = _cli(tmp_path, capsys, "dbc", str(tmp_path / "vehicle.dbc"), "--bus",
                       "vehicle", "--send", "STEERING_CONTROL", "BRAKE_COMMAND",
                       "--checksum", "BRAKE_COMMAND=crc8-sae-j1850")
    assert status == 0, err
    summary = _run_virtual(tmp_path, capsys, ["map.toml"], "--value", "wheel_speed_fl=42")
    assert "wheel_speed_fl" in summary and "healthy" in summary, summary


def test_node_still_decides_where_the_dbc_has_nodes() -> None:
    _text, devs, _bus = _doc(import_dbc(VENDOR / "hpu_press.dbc", node="CELL_CTRL"))
    by_node = {n for n, d in devs.items() if d["direction"] == "actuator"}
    _text, devs, _bus = _doc(import_dbc(VENDOR / "hpu_press.dbc", node="CELL_CTRL",
                                        send=["HPU_Status"]))
    assert {n for n, d in devs.items() if d["direction"] == "actuator"} == by_node | {
        "oil_pressure", "oil_temperature", "tank_level", "filter_clogged", "pump_state"}


def _dbc(tmp_path: Path, signals: str, extra: str = "") -> Path:
    path = tmp_path / "t.dbc"
    path.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A B\n\nBO_ 256 M: 8 A\n' + signals
                    + "\n" + extra, encoding="utf-8")
    return path


def test_dbc_limits_beyond_the_signal_are_clamped(tmp_path: Path) -> None:
    path = _dbc(tmp_path, ' SG_ S : 0|8@1+ (0.1,0) [0|125] "%" B\n'
                          ' SG_ T : 8|8@1+ (1,0) [10|5] "" B\n')
    draft = import_dbc(path, node="A")
    _text, devs, _bus = _doc(draft)
    assert devs["s"]["limits"] == [0.0, 25.5]         # 8 bits x 0.1 carry 0..25.5, not 125
    assert devs["t"]["limits"] == [0.0, 255.0]        # the wrong way round: its capacity
    assert any("M.S: limits 0..125 exceed what it can carry (0..25.5)" in w
               for w in draft.warnings)


def test_dbc_capacity_beyond_what_limits_hold_is_an_open_end(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A 64-bit or float signal carries more than a map's limits hold (1e15): the end is open,
    and the map passes check."""
    path = _dbc(tmp_path, ' SG_ Big : 0|64@1+ (1,0) [0|0] "" B\n', 'SIG_VALTYPE_ 256 Big : 2;\n')
    status, err = _cli(tmp_path, capsys, "dbc", str(path), "--node", "A")
    assert status == 0, err
    _t, devs, _b = _doc_of(tmp_path / "map.toml")
    assert devs["big"]["limits"] == [-float("inf"), float("inf")]     # a float64


@pytest.mark.parametrize("bits", ["4294967296", "1000000", "65", "0"])
def test_dbc_signal_sizes_are_refused_before_cantools(tmp_path: Path, bits: str) -> None:
    path = _dbc(tmp_path, f' SG_ Huge : 0|{bits}@1+ (1,0) [0|0] "" B\n')
    with pytest.raises(ConfigError, match=rf"t.dbc: line 10: SG_ Huge \(in M\): {bits} bits: "
                                          r"expected a signal of 1..64 bits"):
        import_dbc(path)


def test_dbc_errors_name_the_line(tmp_path: Path) -> None:
    path = _dbc(tmp_path, ' SG_ S : 60|8@1+ (1,0) [0|255] "" B\n')
    with pytest.raises(ConfigError, match=r"t.dbc: line 10 \(SG_ S of M\): not a readable DBC"):
        import_dbc(path)
    path.write_text('VERSION ""\n\nBU_: A\nBO_ 256 M: 99 A\n', encoding="utf-8")
    with pytest.raises(ConfigError, match=r"line 4: BO_ M: 99 bytes: a CAN frame carries at "
                                          r"most 64"):
        import_dbc(path)


def test_every_multiplexer_branch_is_simulated(tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    """A multiplexed message's simulated sender sends every branch each cycle, not only the
    branches a value script sets: the current sensor, never scripted, is delivered too."""
    status, err = _cli(tmp_path, capsys, "dbc", str(VENDOR / "journey" / "awkward.dbc"),
                       "--signals", "Diag.*")
    assert status == 0, err
    summary = _run_virtual(tmp_path, capsys, ["map.toml"], "--value", "voltage=230")
    lines = {line.split()[1]: line for line in summary.splitlines()
             if line.strip().startswith("sensor")}
    assert " 0 readings" not in lines["current"] and "OK" in lines["current"], summary
    assert "last 230 V" in lines["voltage"], summary


# ---- SunSpec ----------------------------------------------------------------------------------
def _image(device_file: Path, base: int) -> tuple[dict[int, int], dict[int, Any]]:
    """pysunspec2's own register image of ``device_file`` at ``base`` ('SunS', each model's
    registers as pysunspec2 encodes them, the end model) and the computed value (scale factors
    applied, None if not implemented) of each point by its address."""
    from sunspec2.file.client import FileClientDevice

    device = FileClientDevice(str(device_file))
    device.scan()
    words = [0x5375, 0x6E53]
    values: dict[int, Any] = {}
    for model in device.model_list:
        at = base + len(words)
        data = model.get_mb()
        words += [int.from_bytes(data[i:i + 2], "big") for i in range(0, len(data), 2)]

        def walk(group: Any, at: int = at) -> None:
            for point in group.points.values():
                values[at + point.offset] = point.cvalue
            for sub in group.groups.values():
                for g in sub if isinstance(sub, list) else [sub]:
                    walk(g)
        walk(model)
    words += [0xFFFF, 0]
    return {base + i: w for i, w in enumerate(words)}, values


def _decode(address: dict[str, Any], image: dict[int, int]) -> Any:
    """What a device of the map reads from ``image``: the register type at its address, "not
    implemented" as None, scaled by its scale-factor register (raw x 10^sf)."""
    from drivers.codecs.modbus import REGISTER_TYPES, from_registers

    at, typ = address["address"], address["type"]
    if typ == "string":
        data = b"".join(image[at + i].to_bytes(2, "big") for i in range(address["count"]))
        return data.rstrip(b"\0").decode("ascii") or None
    regs = [image[at + i] for i in range(REGISTER_TYPES[typ][1])]
    bits = int.from_bytes(b"".join(r.to_bytes(2, "big") for r in regs), "big")
    if address.get("unimplemented") == bits:
        return None
    value = from_registers(typ, regs, address.get("word_order", "ABCD"))
    if "scale_factor" in address:
        sf = from_registers("int16", [image[address["scale_factor"]]])
        value = round(value * 10.0 ** sf, -int(sf))
    return value


def test_sunspec_device_file_reads_what_pysunspec2_encodes() -> None:
    """Every device of the imported map, decoded from pysunspec2's own register image of the
    device file as the map's address, type, word order, scale factor and not-implemented value
    say, gives the value pysunspec2 computes for that point."""
    source = DOCS_VENDOR / "inverter.json"
    draft = import_sunspec(read_device(source), source=str(source), host="127.0.0.1")
    _text, devs, _bus = _doc(draft)
    image, values = _image(source, 40000)
    assert devs["sunspec_marker"]["address"]["address"] == 40000
    assert devs["common_id"]["address"]["address"] == 40002          # model 1 at base + 2
    assert devs["inverter_three_phase_id"]["address"]["address"] == 40070   # + 2 + 66
    assert devs["inverter_three_phase_w"]["address"] == {
        "unit": 1, "table": "holding", "address": 40084, "type": "int16",
        "unimplemented": 0x8000, "scale_factor": 40085}
    assert devs["inverter_three_phase_wh"]["address"]["type"] == "uint32"   # acc32
    assert devs["inverter_three_phase_st"]["address"]["unimplemented"] == 0xFFFF   # enum16
    assert devs["mppt_module2_dcv"]["address"]["scale_factor"] == \
        devs["mppt_dcv_sf"]["address"]["address"]      # a repeating group's SF: the model's
    assert devs["sunspec_end"]["address"]["address"] == 40200
    assert devs["sunspec_end"]["limits"] == [65535.0, 65535.0]
    assert devs["common_da"]["direction"] == "actuator"            # an RW point
    checked = 0
    for name, dev in devs.items():
        at = dev["address"]["address"]
        if at not in values:       # the marker and the end model: not points
            assert name in ("sunspec_marker", "sunspec_end")
            continue
        got, want = _decode(dev["address"], image), values[at]
        if isinstance(want, float) or isinstance(got, float):
            assert got == pytest.approx(want), name
        else:
            assert got == want, (name, got, want)
        checked += 1
    assert checked > 80


def test_sunspec_models_option_and_the_legacy_common_model() -> None:
    draft = import_sunspec(parse_models(["1,103"], ["1=65"]), source="--models", base=40000)
    _text, devs, _bus = _doc(draft)
    # model 1 of 65 registers (no Pad): model 103 at 40069, as such inverters lay it out
    assert devs["common_l"]["limits"] == [65.0, 65.0]
    assert devs["inverter_three_phase_id"]["address"]["address"] == 40069
    assert devs["inverter_three_phase_w"]["address"]["address"] == 40083
    with pytest.raises(ConfigError, match=r"model 160: its group 'module' repeats as the device "
                                          r"says: give the count \(--models 160:N\)"):
        import_sunspec(parse_models(["1,160"]), source="--models")
    with pytest.raises(ConfigError, match=r"model 9: no SunSpec model definition|model 4242"):
        import_sunspec(parse_models(["1,4242"]), source="--models")
    with pytest.raises(ConfigError, match=r"--base 65535: expected a protocol address"):
        import_sunspec(parse_models(["1"]), source="--models", base=65535)


@needs_modbus_sunspec
def test_sunspec_map_reads_pysunspec2_registers_over_modbus(tmp_path: Path) -> None:
    """The imported map run against a Modbus server (pyModbusTCP) holding pysunspec2's register
    image: chcos reads what pysunspec2 computes, scale factors applied by the driver."""
    from pyModbusTCP.server import ModbusServer

    from chcos.helpers import free_port
    from chcos.kernel.clock import VirtualClock
    from chcos.system.embedded import System

    source = DOCS_VENDOR / "inverter.json"
    image, values = _image(source, 40000)
    server = ModbusServer(host="127.0.0.1", port=free_port(), no_block=True)
    server.start()
    try:
        words = [image[a] for a in sorted(image)]
        server.data_bank.set_holding_registers(40000, words)
        out = tmp_path / "inverter.toml"
        draft = import_sunspec(read_device(source), source=str(source), host="127.0.0.1",
                               port=server.port)
        out.write_text(render(draft), encoding="utf-8")
        with System([out], clock=VirtualClock(), machines=[0]) as s:
            s.run_for(2.0)
            assert s.devtab.get("inverter_three_phase_w").value == pytest.approx(values[40084])
            assert s.devtab.get("inverter_three_phase_pf").value == pytest.approx(0.992)
            assert s.devtab.get("common_mn").value == "Helios Power"
    finally:
        server.stop()


# ---- register lists ---------------------------------------------------------------------------
def _csv(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "list.csv"
    path.write_text(text, encoding="utf-8")
    return path


def test_addresses_as_the_list_counts_them(tmp_path: Path) -> None:
    path = _csv(tmp_path, "Name,Address,Type\nW,40084,int16\nW_SF,40085,sunssf\n")
    # auto: a Modicon number names holding 83, with a warning saying how to read it otherwise
    _t, devs, _b = _doc(import_modbus_csv(path))
    assert devs["w"]["address"]["address"] == 83
    # zero/one without a table column name no table: refused naming the row...
    with pytest.raises(ConfigError, match=r"list.csv: row 2: address '40084' with --addressing "
                                          r"one and no table column: which table\?"):
        import_modbus_csv(path, addressing="one")
    # ...and honoured with the table given
    _t, devs, _b = _doc(import_modbus_csv(path, addressing="one", table="holding"))
    assert devs["w"]["address"]["address"] == 40083
    _t, devs, _b = _doc(import_modbus_csv(path, addressing="zero", table="holding"))
    assert devs["w"]["address"]["address"] == 40084
    assert devs["w_sf"]["address"]["type"] == "int16"
    # a table column and a 5-digit Modicon number: ambiguous, refused naming the row
    path = _csv(tmp_path, "Name,Table,Address\nW,holding,40084\n")
    with pytest.raises(ConfigError, match=r"row 2: holding address '40084' is ambiguous: "
                                          r"Modicon 40084 is holding 83"):
        import_modbus_csv(path)
    _t, devs, _b = _doc(import_modbus_csv(path, addressing="modicon"))
    assert devs["w"]["address"]["address"] == 83


def test_register_list_typed_from_sunspec_models(tmp_path: Path) -> None:
    path = _csv(tmp_path, "Name,Table,Address,Type,Size,SF,Units,Access\n"
                          "Mn,holding,40004,string,16,,,R\n"
                          "W,holding,40084,int16,,W_SF,W,R\n"
                          "W_SF,holding,40085,sunssf,,,,R\n"
                          "WH,holding,40094,acc32,2,WH_SF,Wh,R\n"
                          "WH_SF,holding,40096,sunssf,,,,R\n"
                          "St,holding,40108,enum16,,,,R\n"
                          "Evt1,holding,40110,bitfield32,2,,,R\n"
                          "WMaxLimPct,holding,40200,uint16,,-1,%,RW\n")
    _t, devs, _b = _doc(import_modbus_csv(path, addressing="zero", host="10.0.0.5"))
    assert devs["mn"]["address"] == {"unit": 1, "table": "holding", "address": 40004,
                                     "type": "string", "count": 16}
    assert devs["w"]["address"]["scale_factor"] == 40085
    assert "unimplemented" not in devs["w"]["address"]   # int16, a PLC type too: no meaning
    assert devs["wh"]["address"]["type"] == "uint32"
    assert devs["wh"]["address"]["unimplemented"] == 0          # acc32: 0 is not implemented
    assert devs["st"]["address"]["unimplemented"] == 0xFFFF
    assert devs["evt1"]["address"]["type"] == "uint32"
    assert devs["wmax_lim_pct"]["scale"] == 0.1                 # a fixed exponent
    assert devs["wmax_lim_pct"]["limits"] == [0.0, 6553.5]


@pytest.mark.parametrize(("cell", "what"), [("1e400", "address '1e400'"),
                                            ("nan", "address 'nan'"), ("-inf", "address"),
                                            ("40001.5", "address")])
def test_register_list_bad_addresses_are_refused_by_row(tmp_path: Path, cell: str,
                                                        what: str) -> None:
    path = _csv(tmp_path, f"Name,Table,Address\nok,holding,1\nbad,holding,{cell}\n")
    with pytest.raises(ConfigError, match=rf"list.csv: row 3: {what}"):
        import_modbus_csv(path)


def test_register_list_huge_cells_and_numbers_are_refused_by_row(tmp_path: Path) -> None:
    path = _csv(tmp_path, "Name,Table,Address,Scale\nok,holding,1,1\nbig,holding,2,"
                + "9" * 140_000 + "\n")
    with pytest.raises(ConfigError, match=r"list.csv: row 3: a cell (of|longer than) \d+ "
                                          r"characters"):
        import_modbus_csv(path)
    path = _csv(tmp_path, "Name,Table,Address,Scale\nbig,holding,2,1e400\n")
    with pytest.raises(ConfigError, match=r"row 2: scale '1e400': expected a finite number"):
        import_modbus_csv(path)


def test_register_list_limits_within_the_register_type(tmp_path: Path) -> None:
    path = _csv(tmp_path, "Name,Table,Address,Type,Scale,Min,Max,Access\n"
                          "sp,holding,1,int16,0.1,-5000,5000,RW\n")
    draft = import_modbus_csv(path, host="127.0.0.1")
    _t, devs, _b = _doc(draft)
    assert devs["sp"]["limits"] == [-3276.8, 3276.7]
    assert any("row 2: sp: limits -5000..5000 exceed what it can carry" in w
               for w in draft.warnings)


# ---- EDS ranges -------------------------------------------------------------------------------
def test_eds_limits_within_the_object_data_type(tmp_path: Path) -> None:
    text = (DOCS_VENDOR / "io_module.eds").read_text(encoding="utf-8")
    eds = tmp_path / "wide.eds"
    eds.write_text(text.replace("LowLimit=0\nHighLimit=27648", "LowLimit=-40000\n"
                                "HighLimit=27648", 1), encoding="utf-8")
    draft = import_eds(eds, 7)
    _t, devs, _b = _doc(draft)
    assert devs["write_analogue_output_16_bit_analogue_output_1"]["limits"] == [-32768.0,
                                                                               27648.0]
    assert any("0x6411:01" in w and "exceed what it can carry" in w for w in draft.warnings)


# ---- the command line -------------------------------------------------------------------------
@pytest.mark.parametrize(("option", "value"), [("--prefix", "9x"), ("--prefix", "a b"),
                                               ("--bus", ""), ("--bus", "a" * 70)])
def test_prefix_and_bus_are_validated(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                      option: str, value: str) -> None:
    status, err = _cli(tmp_path, capsys, "modbus", str(DOCS_VENDOR / "meter.csv"), option,
                       value)
    assert status == 2 and f"chcos import modbus: {option} " in err and "expected" in err
    assert not (tmp_path / "map.toml").exists()


def test_relative_paths_rename_and_nothing_written_when_check_refuses(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "maps").mkdir()
    status, err = _cli(tmp_path, capsys, "eds", str(DOCS_VENDOR / "drive.eds"), "--node", "5",
                       "--rename", "axis=spindle", out="maps/drive.toml")
    assert status == 0, err
    _text, devs, bus = _doc_of(tmp_path / "maps" / "drive.toml")
    eds_ref = bus["nodes"][0]["eds"]
    assert not Path(eds_ref).is_absolute()
    assert (tmp_path / "maps" / eds_ref).resolve() == (DOCS_VENDOR / "drive.eds").resolve()
    assert "spindle" in devs and "axis" not in devs
    status, err = _cli(tmp_path, capsys, "eds", str(DOCS_VENDOR / "drive.eds"), "--node", "5",
                       "--rename", "nope=x")
    assert status == 2 and "--rename 'nope=x': no device 'nope'" in err
    # an option check refuses (a UDP port beyond 65535): the import refuses, writes nothing
    status, err = _cli(tmp_path, capsys, "eds", str(DOCS_VENDOR / "drive.eds"), "--node", "5",
                       "--interface", "udp_multicast", "--channel", "239.1.1.1",
                       "--udp-port", "70000", out="bad.toml")
    assert status == 2 and "would not pass chcos check, so nothing was written" in err
    assert "bus[0].port" in err and not (tmp_path / "bad.toml").exists()


# ---- the shipped vendor files ------------------------------------------------------------------
def test_shipped_drive_and_meter_imported_checked_and_run_healthy(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    for f in ("drive.eds", "meter.csv"):
        shutil.copy(DOCS_VENDOR / f, tmp_path)
    status, err = _cli(tmp_path, capsys, "eds", str(tmp_path / "drive.eds"), "--node", "5",
                       "--bus", "drive", "--interface", "virtual", "--channel", "d49",
                       out="drive.toml")
    assert status == 0, err
    status, err = _cli(tmp_path, capsys, "modbus", str(tmp_path / "meter.csv"), "--bus",
                       "meter", "--host", "127.0.0.1", "--port", "5021", out="meter.toml")
    assert status == 0, err
    _t, meter, _b = _doc_of(tmp_path / "meter.toml")
    assert meter["voltage_l1"]["address"] == {"unit": 1, "table": "input", "address": 0,
                                              "type": "float32"}
    assert meter["demand_limit"]["address"]["address"] == 64512      # Modicon 464513
    _t, drive, bus = _doc_of(tmp_path / "drive.toml")
    assert bus["nodes"][0]["eds"] == "drive.eds" and drive["axis"]["profile"] == "cia402"
    summary = _run_virtual(tmp_path, capsys, ["drive.toml", "meter.toml"])
    assert "healthy" in summary, summary


@needs_can_messages
def test_shipped_gripper_imported_checked_and_run_healthy(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    shutil.copy(DOCS_VENDOR / "gripper.dbc", tmp_path)
    status, err = _cli(tmp_path, capsys, "dbc", str(tmp_path / "gripper.dbc"), "--node", "PLC",
                       "--bus", "gripper")
    assert status == 0, err
    _t, devs, bus = _doc_of(tmp_path / "map.toml")
    assert {m["name"] for m in bus["message"]} == {"GripCommand", "GripStatus"}
    assert devs["position"]["stale_after"] == 0.1
    summary = _run_virtual(tmp_path, capsys, ["map.toml"])
    assert "healthy" in summary, summary


# ---- mutations of the shipped files: the property ----------------------------------------------
@settings(max_examples=60, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(st.integers(0, 2**32 - 1), st.sampled_from(["eds", "dbc", "modbus", "sunspec"]))
def test_mutated_vendor_files_give_no_traceback_hang_or_invalid_map(seed: int,
                                                                    kind: str) -> None:
    """A mutation of a shipped vendor file (tools/fuzz_importers.py's, seeded) is imported to a
    map that passes check, or refused with the file and its line, row or key named."""
    from tools.fuzz_importers import ROOT as FUZZ_ROOT
    from tools.fuzz_importers import SOURCES, Findings, run_case

    rng = random.Random(seed)
    findings = Findings()
    with tempfile.TemporaryDirectory() as work:
        run_case(kind, FUZZ_ROOT / rng.choice(SOURCES[kind]), rng, Path(work), 60.0,
                 findings)
    bad = {k: findings.examples.get(k) for k in ("traceback", "hang", "invalid output",
                                                 "other status") if findings.counts[k]}
    assert not bad, bad



def test_the_register_types_the_importers_write_are_the_drivers() -> None:
    """What the importers take the modbus driver to read is what its codec reads (with bool and
    the string type of the Modbus branch): a type the driver gains or loses shows here."""
    from chcos.devices.importers.modbus_types import DRIVER_TYPES
    from drivers.codecs.modbus import REGISTER_TYPES

    assert set(DRIVER_TYPES) == set(REGISTER_TYPES) | {"bool", "string"}
