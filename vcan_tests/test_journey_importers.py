"""Importers whose output always passes ``chcos check`` (issue 39): DBC and register-list corpora
written to hold every awkward feature (multi-line and quoted comments, value tables with quotes,
multiplexing, signed and float signals, rolling counters and CRCs, Modicon, hexadecimal, zero-
and one-based addresses, vendor headers such as ``Parameter``), and a simulator that serves
sparse register spaces (holding 64512) read by an independent client (pyModbusTCP)."""

from __future__ import annotations

import string
import tomllib
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pyModbusTCP.client import ModbusClient

from chcos.apps.sim.from_map import simulate
from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.cli.main import main as cli_main
from chcos.devices.devmap import check, load
from chcos.devices.importers.dbc import import_dbc
from chcos.devices.importers.draft import render
from chcos.devices.importers.modbus_csv import import_modbus_csv
from chcos.errors import ConfigError
from chcos.helpers import free_port
from vcan_tests.support_import import needs_can_messages

VENDOR = Path(__file__).resolve().parent / "vendor" / "journey"


def _imported(tmp_path: Path, capsys: pytest.CaptureFixture[str],
              *args: str) -> tuple[str, dict[str, Any], str]:
    out = tmp_path / "imported.toml"
    capsys.readouterr()
    assert cli_main(["import", *args, "-o", str(out)]) == 0
    err = capsys.readouterr().err
    text = out.read_text(encoding="utf-8")
    dmap, errors, _warnings = check([out])
    assert dmap is not None, errors
    doc = tomllib.loads(text)
    return text, {d["name"]: d for d in doc["device"]}, err


# ---- DBC --------------------------------------------------------------------------------------
def _drafted(path: Path, **kw: Any) -> tuple[str, dict[str, Any], list[str]]:
    """The map an import writes (its text, devices by name, warnings), not checked: for what
    the map says whatever the drivers of this branch accept."""
    draft = import_dbc(path, **kw)
    text = render(draft)
    return text, {d["name"]: d for d in tomllib.loads(text)["device"]}, draft.warnings


def test_dbc_with_every_awkward_feature(tmp_path: Path) -> None:
    text, devs, _warnings = _drafted(VENDOR / "awkward.dbc", node="ECU", dbc_ref="awkward.dbc")
    # the three-line comment: every line a comment, the quotes and the '#' kept as text
    assert "# Measured at the encoder, not the load." in text
    assert '# Third line: [brackets] = "quoted" # hash' in text
    assert '7 Fault "hard"' in text
    # signed, float and extended
    assert "Float_Sig: 32 bit float" in text and "0x18FF50E5, extended" in text
    assert "Temperature: 8 bit signed" in text
    # the multiplexer and what each multiplexed signal is carried with
    assert "multiplexed: carried when Mux = 0" in text
    assert "multiplexed: carried when Mux = 1" in text
    assert devs["voltage"]["direction"] == "sensor"


@needs_can_messages
def test_dbc_with_counters_passes_check(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    text, devs, _err = _imported(tmp_path, capsys, "dbc", str(VENDOR / "awkward.dbc"),
                                 "--node", "ECU")
    assert "[[bus.message]]" in text and devs["setpoint"]["direction"] == "actuator"


def test_dbc_counters_and_crcs_are_declared_for_the_driver(tmp_path: Path) -> None:
    text, devs, warnings = _drafted(VENDOR / "awkward.dbc", node="ECU", dbc_ref="awkward.dbc")
    doc = tomllib.loads(text)
    tables = {m["name"]: m for m in doc["bus"][0]["message"]}
    # the message chcos sends: the driver computes them, they are not devices
    assert "rolling_counter" not in devs and "crc8" not in devs
    assert devs["setpoint"]["direction"] == "actuator"
    assert tables["Command"] == {"name": "Command", "counter": "RollingCounter",
                                 "checksum": {"signal": "CRC8",
                                              "algorithm": "crc8-sae-j1850"}}
    assert "# checksum algorithm crc8-sae-j1850: a GUESS" in text
    assert any("Command: checksum CRC8: algorithm crc8-sae-j1850 is a guess" in w
               for w in warnings)
    # the message chcos receives: the driver checks them; they stay sensors, noted
    assert tables["Status"]["counter"] == "AliveCounter"
    assert tables["Status"]["checksum"]["signal"] == "Checksum"
    assert devs["alive_counter"]["direction"] == "sensor"
    assert devs["checksum"]["direction"] == "sensor"
    assert "a checksum the sender computes per frame" in text
    # the algorithm given on the command line replaces the guess, and is not warned about
    text, _devs, warnings = _drafted(VENDOR / "awkward.dbc", node="ECU",
                                     checksums={"Command": {"algorithm": "xor"}})
    assert 'checksum = { signal = "CRC8", algorithm = "xor" }' in text
    assert not any("Command: checksum" in w for w in warnings)


def test_dbc_signals_picks_by_pattern(tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    _text, devs, _err = _imported(tmp_path, capsys, "dbc", str(VENDOR / "awkward.dbc"),
                                  "--signals", "Diag.*")
    assert set(devs) == {"mux", "voltage", "current"}
    _text, devs, _warnings = _drafted(VENDOR / "awkward.dbc", signals=["Diag.*", "Setpoint"])
    assert set(devs) == {"mux", "voltage", "current", "setpoint"}
    with pytest.raises(ConfigError, match="--signals Nope matched none"):
        import_dbc(VENDOR / "awkward.dbc", signals=["Nope"])


_COMMENT = st.text(alphabet=st.characters(codec="utf-8", exclude_characters='"\\'),
                   min_size=1, max_size=60)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(_COMMENT, min_size=1, max_size=4))
def test_any_dbc_comment_gives_a_map_that_passes_check(tmp_path: Path,
                                                       lines: list[str]) -> None:
    comment = "\n".join(lines).replace("\r", "\n")
    dbc = tmp_path / "c.dbc"
    dbc.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\n'
                   'BO_ 256 M: 8 A\n SG_ S : 0|8@1+ (1,0) [0|255] "" A\n\n'
                   f'CM_ SG_ 256 S "{comment}";\n', encoding="utf-8")
    try:
        draft = import_dbc(dbc, dbc_ref="c.dbc")
    except ConfigError:
        return  # cantools could not read it: refused with the file named, fine
    out = tmp_path / "c.toml"
    out.write_text(render(draft), encoding="utf-8")
    dmap, errors, _ = check([out])
    assert dmap is not None, (comment, errors)


# ---- register lists ---------------------------------------------------------------------------
def test_meter_list_with_vendor_headers_and_modicon_numbers(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.csv"
    bad.write_text((VENDOR / "meter.csv").read_text(encoding="utf-8"), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"row 9: no table column and address '0x0010'"):
        import_modbus_csv(bad)
    good = tmp_path / "meter.csv"
    good.write_text("\n".join(bad.read_text(encoding="utf-8").splitlines()[:-1]) + "\n",
                    encoding="utf-8")
    _text, devs, err = _imported(tmp_path, capsys, "modbus", str(good))
    addr = {n: (d["address"]["table"], d["address"]["address"], d["address"]["type"])
            for n, d in devs.items()}
    assert addr == {"voltage_l1": ("input", 0, "float32"), "current_l1": ("input", 2, "float32"),
                    "energy_import": ("input", 72, "uint32"), "frequency": ("input", 70, "uint16"),
                    "demand_setpoint": ("holding", 0, "int16"),
                    "reset_counters": ("holding", 2, "uint16"),
                    "tariff": ("holding", 64512, "uint16")}
    assert {n for n, d in devs.items() if d["direction"] == "actuator"} == {
        "demand_setpoint", "reset_counters", "tariff"}
    assert devs["demand_setpoint"]["limits"] == [-3276.8, 3276.7]   # what int16 * 0.1 carries
    assert "no --host" in err and "without a word order" in err


@pytest.mark.parametrize(("how", "expected"), [
    ("zero", [0, 1, 16]), ("one", [0, 1, 16]), ("modicon", [0, 1, 16]), ("auto", [0, 1, 16])])
def test_addresses_counted_every_way_land_on_the_same_registers(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], how: str,
        expected: list[int]) -> None:
    numbers = {"zero": ["0", "0x1", "10h"], "one": ["1", "2", "17"],
               "modicon": ["40001", "40002", "40017"], "auto": ["400001", "400002", "400017"]}
    rows = [f"Tag{i},holding,{n},uint16,RW" for i, n in enumerate(numbers[how])]
    csv = tmp_path / f"{how}.csv"
    csv.write_text("Name,Table,Address,Type,Access\n" + "\n".join(rows) + "\n", encoding="utf-8")
    _text, devs, _err = _imported(tmp_path, capsys, "modbus", str(csv), "--addressing", how,
                                  "--host", "127.0.0.1")
    assert [d["address"]["address"] for d in devs.values()] == expected


def test_rtu_output_and_what_will_not_work_on_a_real_bus(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv = tmp_path / "drive.csv"
    csv.write_text("Tag,Table,Address,Type,Slave,Access\n"
                   "speed,holding,0,float32,3,RW\n"
                   "torque,holding,1,uint16,3,R\n"
                   "temp,input,5,uint16,3,RW\n", encoding="utf-8")
    text, devs, err = _imported(tmp_path, capsys, "modbus", str(csv), "--rtu", "/dev/ttyUSB0",
                                "--baudrate", "38400", "--parity", "E")
    assert 'kind = "modbus-rtu"' in text and 'port = "/dev/ttyUSB0"' in text
    assert "baudrate = 38400" in text and 'parity = "E"' in text
    assert "row 3: torque: holding 1 of unit 3 is also read by row 2" in err
    assert "row 4: temp: access 'RW' on a read-only input table" in err
    assert devs["temp"]["direction"] == "sensor"
    csv.write_text("Tag,Table,Address,Slave\nx,holding,0,0\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"row 2: unit id 0: an RTU slave answers only"):
        import_modbus_csv(csv, rtu="/dev/ttyUSB0")
    csv.write_text("Tag,Table,Address,Type\nx,holding,65535,uint32\n", encoding="utf-8")
    with pytest.raises(ConfigError, match=r"row 2: address '65535'.*beyond 65535"):
        import_modbus_csv(csv)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.tuples(st.sampled_from(["coil", "discrete", "input", "holding", "4x", "IR"]),
                          st.integers(0, 70000),
                          st.sampled_from(["", "int16", "U32", "REAL", "float64", "WORD"]),
                          st.sampled_from(["", "R", "RW", "W"]),
                          st.text(alphabet=string.ascii_letters + " #\"'[]=", min_size=1,
                                  max_size=12)),
                min_size=1, max_size=6))
def test_any_register_list_imports_to_a_checked_map_or_is_refused_by_row(
        tmp_path: Path, rows: list[tuple[str, int, str, str, str]]) -> None:
    csv = tmp_path / "any.csv"
    lines = ["Parameter,Area,Address,Data Type,Access,Description"]
    lines += [f"p{i},{t},{a},{ty},{acc},\"{desc.replace(chr(34), chr(39))}\""
              for i, (t, a, ty, acc, desc) in enumerate(rows)]
    csv.write_text("\n".join(lines) + "\n", encoding="utf-8")
    try:
        draft = import_modbus_csv(csv, host="127.0.0.1", addressing="zero")
    except ConfigError as exc:
        assert "any.csv: row " in str(exc)
        return
    out = tmp_path / "any.toml"
    out.write_text(render(draft), encoding="utf-8")
    dmap, errors, _ = check([out])
    assert dmap is not None, errors


# ---- sparse register spaces in the simulator --------------------------------------------------
def test_simulator_serves_holding_64512_to_an_independent_client(tmp_path: Path) -> None:
    csv = tmp_path / "meter.csv"
    csv.write_text("Parameter,Register Address,Data Type,R/W\n"
                   "Voltage,30001,U16,R\nTariff,464513,U16,RW\nLast,465536,U16,RW\n",
                   encoding="utf-8")
    out = tmp_path / "meter.toml"
    out.write_text(render(import_modbus_csv(csv)), encoding="utf-8")
    slaves = simulate(load([out]), direct=False)     # on a socket: a client of its own
    try:
        slaves.set("tariff", 7)
        slaves.set("voltage", 230)
        bus = slaves.devmap.buses[0]
        client = ModbusClient(host="127.0.0.1", port=int(bus.options["port"]), unit_id=1,
                              auto_open=True, timeout=5.0)
        assert client.read_holding_registers(64512, 1) == [7]
        assert client.read_input_registers(0, 1) == [230]
        assert client.write_single_register(65535, 99)
        assert slaves.get("last") == 99                      # what the client wrote
        # an address nothing maps answers "illegal data address", as a real device does
        assert client.read_holding_registers(1000, 1) is None
        assert client.last_except == 2
        client.close()
    finally:
        slaves.close()


def test_simulator_start_failure_says_what_failed() -> None:
    store = RegisterStore((1,), spans={"holding": [(0, 2)]})
    with ModbusSimServer(store, free_port()) as server:
        other = ModbusSimServer(store, server.port)
        with pytest.raises(Exception, match=rf"cannot listen on 127\.0\.0\.1:{server.port}: \S"):
            other.start()


def test_a_multiplexed_dbc_message_is_simulated_one_multiplexer_value_per_frame(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The simulator of an imported DBC serves a multiplexed message as the DBC describes it
    (it used to refuse: "cannot encode mux=0"): a frame per multiplexer value, each carrying
    only that value's signals, as cantools decodes them off the wire on its own."""
    import uuid

    import can
    import cantools

    channel = f"mux-{uuid.uuid4().hex}"
    _imported(tmp_path, capsys, "dbc", str(VENDOR / "awkward.dbc"), "--signals", "Diag.*",
              "--interface", "virtual", "--channel", channel)
    listener = can.Bus(interface="virtual", channel=channel)
    slaves = simulate(load([tmp_path / "imported.toml"]), rewrite=False)
    try:
        slaves.values(["voltage=230", "current=-1.5"], tmp_path)
        for step in range(1, 41):          # 0.4 s of the simulator's clock
            slaves.tick(step * 0.01)
        db = cantools.database.load_file(str(VENDOR / "awkward.dbc"))
        diag = db.get_message_by_name("Diag")
        seen: dict[int, dict[str, Any]] = {}
        while (frame := listener.recv(timeout=0)) is not None:
            if frame.arbitration_id == diag.frame_id:
                decoded = diag.decode(frame.data)
                seen[int(decoded["Mux"])] = decoded
    finally:
        slaves.close()
        listener.shutdown()
    assert set(seen) == {0, 1}, seen
    assert seen[0]["Voltage"] == pytest.approx(230) and "Current" not in seen[0]
    assert seen[1]["Current"] == pytest.approx(-1.5) and "Voltage" not in seen[1]


def test_a_multiplexed_dbc_map_runs_on_virtual_time(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """`chcos run --virtual` of the map: both multiplexed sensors get their values."""
    _imported(tmp_path, capsys, "dbc", str(VENDOR / "awkward.dbc"), "--signals", "Diag.*")
    (tmp_path / "install.chcos").write_text("install -m0 sysfile\n", encoding="utf-8")
    (tmp_path / "system.toml").write_text('[system]\nname = "mux"\ndevmaps = ["imported.toml"]\n'
                                          'install = "install.chcos"\n', encoding="utf-8")
    assert cli_main(["run", str(tmp_path / "system.toml"), "--virtual", "--duration", "1",
                     "--value", "voltage=230", "--value", "current=-1.5"]) == 0
    summary = capsys.readouterr().out.split("summary")[-1]
    assert "sensor   voltage          last 230 V" in summary, summary
    assert "sensor   current          last -1.5 A" in summary, summary
    assert "healthy" in summary


def test_canopen_bus_takes_a_udp_multicast_port(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A CANopen bus shared by two processes: the importer writes the port, check accepts it
    only with interface udp_multicast, naming the key otherwise."""
    eds = Path(__file__).resolve().parent.parent / "docs" / "vendor" / "drive.eds"
    text, _devs, _err = _imported(tmp_path, capsys, "eds", str(eds), "--node", "5",
                                  "--interface", "udp_multicast", "--channel", "239.74.163.9",
                                  "--udp-port", "43119")
    bus = tomllib.loads(text)["bus"][0]
    assert (bus["interface"], bus["port"]) == ("udp_multicast", 43119)
    wrong = tmp_path / "wrong.toml"
    wrong.write_text((tmp_path / "imported.toml").read_text(encoding="utf-8").replace(
        'interface = "udp_multicast"', 'interface = "virtual"'), encoding="utf-8")
    dmap, errors, _ = check([wrong])
    assert dmap is None
    assert any("bus[0].port: the UDP port of interface \"udp_multicast\"" in e for e in errors), \
        errors
    assert cli_main(["import", "eds", str(eds), "--node", "5", "--udp-port", "43119",
                     "-o", str(tmp_path / "x.toml")]) == 2
    assert "--udp-port 43119: only with --interface udp_multicast" in capsys.readouterr().err
