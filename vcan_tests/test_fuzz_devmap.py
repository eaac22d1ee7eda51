"""Device maps under bad input (issue 15, items 8 and 9): ``chcos check`` lists every error of
every file in one pass and warns about maps that are legal but misbehave; every map a fuzzer
broke the loader with is an error naming the file and key; maps that passed and then hung or
crashed are refused with a range error; hypothesis properties over mutated maps and raw TOML
text: no traceback, every error names the file and key, a valid map runs without a hang.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chcos.devices.devmap import check, check_main, load
from chcos.errors import ConfigError
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System

FUZZ = settings(max_examples=120, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture,
                                       HealthCheck.too_slow])
DRIVER_BUG = "could not be checked"    # the loader's net for a driver check that raised


def _toml_value(v: Any) -> str:
    """A minimal TOML emitter for the fuzzer (strings, numbers, booleans, arrays, inline
    tables); enough to write any value tomllib can read back."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) \
            else repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))} = {_toml_value(x)}"
                               for k, x in v.items()) + "}"
    raise TypeError(v)


def _toml(doc: dict[str, list[dict[str, Any]]]) -> str:
    out = []
    for table in ("bus", "device"):
        for t in doc.get(table, []):
            out.append(f"[[{table}]]")
            out.extend(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in t.items())
            out.append("")
    return "\n".join(out)


def _write(tmp: Path, name: str, text: str) -> Path:
    p = tmp / name
    p.write_text(text, encoding="utf-8")
    return p


def _errors(p: Path) -> str:
    with pytest.raises(ConfigError) as info:
        load(p)
    return str(info.value)


MEM = '[[bus]]\nname = "m"\nkind = "memory"\n'
SENSOR = '[[device]]\nname = "S"\ndirection = "sensor"\nbus = "m"\n'
ACT = '[[device]]\nname = "A"\ndirection = "actuator"\nbus = "m"\nsafe_value = 0\n'
BIG = "9" * 400


# ---- the fuzzer's findings, each a regression test ------------------------------------------
@pytest.mark.parametrize("text, key, expected", [
    (MEM + SENSOR + f"scale = {BIG}\n", "device[0].scale", "magnitude"),
    (MEM + SENSOR + f"offset = -{BIG}\n", "device[0].offset", "magnitude"),
    (MEM + SENSOR + f"limits = [0, {BIG}]\n", "device[0].limits[1]", "magnitude"),
    (MEM + ACT + f"limits = [-{BIG}, 1]\n", "device[0].limits[0]", "magnitude"),
    (MEM.replace('"memory"', '"memory"\nhistory = 5') + ACT.replace("safe_value = 0",
                                                                     f"safe_value = {BIG}"),
     "device[0].safe_value", "magnitude"),
    (MEM + SENSOR + f"stale_after = {BIG}\n", "device[0].stale_after", "magnitude"),
    ('[[bus]]\nname = "g"\nkind = "signal"\n[[device]]\nname = "S"\ndirection = "sensor"\n'
     f'bus = "g"\naddress = {{ waveform = "sine", rate_hz = {BIG} }}\n',
     "device[0].address.rate_hz", "magnitude"),
    (MEM + 'x = ' + "[" * 400 + "]" * 400 + "\n", "", "nested"),
    (MEM + SENSOR + 'address = ' + "{a = " * 400 + "1" + "}" * 400 + "\n", "", "nested"),
    (MEM + SENSOR + 'address = {a = ' + "[" * 12 + "]" * 12 + "}\n", "device[0].address.a",
     "nested more than 8"),
    ('[[bus]]\nname = "c"\nkind = "canopen"\ninterface = "virtual"\nchannel = "x"\n'
     'nodes = [{id = [1]}]\n', "bus[0].nodes[0].id", "expected a CANopen node id"),
    ('[[bus]]\nname = "mb"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\n[[device]]\nname = "S"\n'
     'direction = "sensor"\nbus = "mb"\naddress = { table = "holding", address = 1, type = [] }\n',
     "device[0].address.type", "expected one of 'bool', 'int16'"),
    ('[[bus]]\nname = "s"\nkind = "serial"\nurl = "loop://"\nprotocol = "binary"\nsync = "AA"\n'
     'struct = "<h\u00e9"\nfields = ["a"]\n', "bus[0].struct", "ASCII struct format"),
    ('[[bus]]\nname = "s"\nkind = "serial"\nurl = "loop://"\nprotocol = "binary"\nsync = "AA"\n'
     'struct = "<h"\nfields = 5\n', "bus[0].fields", "expected a list of field names"),
    ('[[bus]]\nname = "s"\nkind = "serial"\nurl = "loop://"\nprotocol = "binary"\nsync = "AA"\n'
     'struct = "<999999999s"\nfields = ["a"]\n', "bus[0].struct", "at most 4096"),
    # maps that passed check, then hung or crashed
    ('[[bus]]\nname = "g"\nkind = "signal"\n[[device]]\nname = "S"\ndirection = "sensor"\n'
     'bus = "g"\naddress = { waveform = "sine", rate_hz = 1e308 }\n',
     "device[0].address.rate_hz", "expected samples per second in 1e-06..100000"),
    (MEM + SENSOR + "stale_after = 5e-324\n", "device[0].stale_after",
     "expected seconds in 0.0001..3.2e+07"),
    (MEM.replace('"memory"', '"memory"\nhistory = 18446744073709551616'), "bus[0].history",
     "integer"),
    (MEM.replace('"memory"', '"memory"\nhistory = 9223372036854775807'), "bus[0].history",
     "expected an integer 1..1000000"),
    (MEM + SENSOR + "scale = inf\n", "device[0].scale", "expected a finite number"),
    (MEM + SENSOR + "scale = 5e-324\n", "device[0].scale", "non-zero number of magnitude"),
    ('[[bus]]\nname = "mb"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\npoll_period = 5e-324\n',
     "bus[0].poll_period", "expected seconds in 0.0001..1e+06"),
    ('[[bus]]\nname = "mb"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\ntimeout = inf\n',
     "bus[0].timeout", "expected a finite number"),
    ('[[bus]]\nname = "m\\n"\nkind = "memory"\n', "bus[0].name", "expected a name"),
    (MEM + SENSOR.replace('"S"', '"S\\n"'), "device[0].name", "expected a name"),
    (MEM + SENSOR + f"machine = {BIG}\n", "device[0].machine", "expected an integer 0..9999"),
], ids=lambda v: v[-30:] if isinstance(v, str) else str(v))
def test_fuzzer_findings_are_errors_naming_file_and_key(tmp_path: Path, text: str, key: str,
                                                        expected: str) -> None:
    p = _write(tmp_path, "f.toml", text)
    err = _errors(p)
    assert DRIVER_BUG not in err
    line = next(ln for ln in err.splitlines() if expected in ln)
    assert line.startswith(str(p)), line
    if key:
        assert f": {key}: " in line, line
    assert len(line) < 400


def test_every_error_of_every_file_in_one_pass(tmp_path: Path) -> None:
    a = _write(tmp_path, "a.toml", (
        '[[bus]]\nname = "mb"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\n'
        '[[device]]\nname = "S1"\ndirection = "sensor"\nbus = "mb"\nscale = 0\n'
        'address = { table = "holding", address = 70000 }\n'
        '[[device]]\nname = "A1"\ndirection = "actuator"\nbus = "mb"\nlimits = [5, 1]\n'
        'address = { table = "input", address = 1 }\n'))
    b = _write(tmp_path, "b.toml", MEM + SENSOR + "priority = 100\nbogus = 1\n")
    dmap, errors, _ = check([a, b])
    assert dmap is None
    text = "\n".join(errors)
    for where, what in [
        (f"{a}:5: device[0].scale", "non-zero"),
        (f"{a}:5: device[0].address.address", "expected an integer 0..65535"),   # address too
        (f"{a}:11: device[1].limits", "expected lo <= hi"),
        (f"{a}:11: device[1].address.table", "read-only"),
        (f"{b}:4: device[0].priority", "0..99"),
        (f"{b}:4: device[0]", "unknown key 'bogus'"),
    ]:
        assert any(e.startswith(where) and what in e for e in errors), (where, what, text)


def test_check_warns_about_legal_maps_that_misbehave(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cell = _write(tmp_path, "cell.toml", (
        '[[bus]]\nname = "mb"\nkind = "modbus-tcp"\nhost = "127.0.0.1"\npoll_period = 0.2\n'
        '[[device]]\nname = "T"\ndirection = "sensor"\nbus = "mb"\nstale_after = 0.1\n'
        'address = { table = "input", address = 0 }\n'
        '[[device]]\nname = "Heater"\ndirection = "actuator"\nbus = "mb"\n'
        'limits = [0, 70000]\nsafe_value = 0\naddress = { table = "holding", address = 1 }\n'
        '[[device]]\nname = "Valve"\ndirection = "actuator"\nbus = "mb"\n'
        'address = { table = "coil", address = 0 }\nlimits = [0, 1]\n'
        '[[device]]\nname = "Scaled"\ndirection = "actuator"\nbus = "mb"\nscale = 0.1\n'
        'limits = [0, 6553.5]\nsafe_value = 0\naddress = { table = "holding", address = 2 }\n'))
    empty = _write(tmp_path, "empty.toml", "# nothing yet\n")
    assert check_main([str(cell), str(empty)]) == 0
    out, err = capsys.readouterr()
    assert "ok: 1 buses, 4 devices, 4 warning(s)" in out
    warnings = [ln for ln in err.splitlines() if ln.startswith("warning: ")]
    assert len(warnings) == 4, err
    assert f"warning: {cell}:6: device[0].stale_after: 0.1 s is shorter than the poll period " \
           "0.2 s" in err
    assert f"warning: {cell}:12: device[1].limits: [0, 70000] reach outside what the address " \
           "can carry ([0, 65535]" in err
    assert f"warning: {cell}:19: device[2].safe_value: actuator has no safe value" in err
    assert f"warning: {empty}: declares no bus and no device" in err
    assert "device[3]" not in err               # 0..6553.5 is exactly what uint16 * 0.1 carries


_DBC = """VERSION ""

NS_ :

BS_:

BU_: GW

BO_ 256 Cmd: 8 GW
 SG_ Power : 0|8@1+ (0.5,0) [0|100] "%" GW
 SG_ Speed : 8|16@1- (1,0) [0|0] "" GW
 SG_ Gain : 32|32@1- (1,0) [0|0] "" GW

SIG_VALTYPE_ 256 Gain : 1;
"""


def _actuator(name: str, bus: str, limits: str, address: str, extra: str = "") -> str:
    return (f'[[device]]\nname = "{name}"\ndirection = "actuator"\nbus = "{bus}"\n'
            f'limits = {limits}\nsafe_value = 0\n{extra}address = {address}\n')


def test_check_warns_about_limits_beyond_can_canopen_and_serial_types(tmp_path: Path) -> None:
    dbc = _write(tmp_path, "cell.dbc", _DBC)
    eds = (Path(__file__).resolve().parent.parent / "chcos" / "apps" / "sim" / "eds"
           / "servo_drive.eds")
    text = (
        f'[[bus]]\nname = "c"\nkind = "can"\ninterface = "virtual"\nchannel = "x"\n'
        f'dbc = "{dbc}"\n'
        f'[[bus]]\nname = "o"\nkind = "canopen"\ninterface = "virtual"\nchannel = "y"\n'
        f'nodes = [{{ id = 5, eds = "{eds}" }}]\n'
        f'[[bus]]\nname = "s"\nkind = "serial"\nurl = "loop://"\nprotocol = "binary"\n'
        f'sync = "AA"\nstruct = "<h"\nfields = ["a"]\n'
        # raw CAN: 8 bits unsigned carry 0..255; signed 12 bits -2048..2047 with scale 0.5
        + _actuator("RawOver", "c", "[0, 256]", "{ id = 0x10, start = 0, length = 8 }")
        + _actuator("RawFit", "c", "[0, 255]", "{ id = 0x11, start = 0, length = 8 }")
        + _actuator("RawSignedFit", "c", "[-1024, 1023.5]",
                    "{ id = 0x12, start = 0, length = 12, signed = true }", "scale = 0.5\n")
        + _actuator("RawSignedOver", "c", "[-1025, 0]",
                    "{ id = 0x13, start = 0, length = 12, signed = true }", "scale = 0.5\n")
        # DBC: Power 0..127.5 on the wire but the DBC allows 0..100; Speed int16; Gain float32
        + _actuator("PowerOver", "c", "[0, 101]", '{ message = "Cmd", signal = "Power" }')
        + _actuator("PowerFit", "c", "[0, 100]", '{ message = "Cmd", signal = "Power" }')
        + _actuator("SpeedOver", "c", "[-40000, 0]", '{ message = "Cmd", signal = "Speed" }')
        + _actuator("SpeedFit", "c", "[-32768, 32767]", '{ message = "Cmd", signal = "Speed" }')
        + _actuator("GainFit", "c", "[-1e15, 1e15]", '{ message = "Cmd", signal = "Gain" }')
        + _actuator("GainOver", "c", "[0, inf]", '{ message = "Cmd", signal = "Gain" }')
        # CANopen: 0x6040 UNSIGNED16, 0x607A INTEGER32, 0x6081 UNSIGNED32 (scale 0.001)
        + _actuator("CwOver", "o", "[0, 70000]", "{ node = 5, index = 0x6040 }")
        + _actuator("CwFit", "o", "[0, 65535]", "{ node = 5, index = 0x6040 }")
        + _actuator("TargetOver", "o", "[-3e9, 0]", "{ node = 5, index = 0x607A }")
        + _actuator("TargetFit", "o", "[-2147483648, 2147483647]", "{ node = 5, index = 0x607A }")
        + _actuator("VelOver", "o", "[-1, 10]", "{ node = 5, index = 0x6081 }",
                    "scale = 0.001\n")
        + _actuator("VelFit", "o", "[0, 4294967.295]", "{ node = 5, index = 0x6081 }",
                    "scale = 0.001\n")
        # serial binary: <b int8, <H uint16, <f float32 (only open limits exceed it), <? bool
        + _actuator("ByteOver", "s", "[-129, 0]", '{ struct = "<b" }')
        + _actuator("ByteFit", "s", "[-128, 127]", '{ struct = "<b" }')
        + _actuator("WordOver", "s", "[0, 65536]", '{ struct = "<H" }')
        + _actuator("WordFit", "s", "[0, 65535]", '{ struct = "<H" }')
        + _actuator("FloatOver", "s", "[0, inf]", '{ struct = "<f" }')
        + _actuator("FloatFit", "s", "[-1e15, 1e15]", '{ struct = "<f" }')
        + _actuator("FlagOver", "s", "[0, 2]", '{ struct = "<?" }')
        + _actuator("DoubleFit", "s", "[-inf, inf]", '{ struct = "<d" }'))
    cell = _write(tmp_path, "cell.toml", text)
    dmap, errors, warnings = check(cell)
    assert dmap is not None and not errors, errors
    names = [d.name for d in dmap.devices]
    warned = {names[int(w.split("device[")[1].split("]")[0])] for w in warnings}
    assert warned == {n for n in names if n.endswith("Over")}, warnings
    assert all("reach outside what the address can carry" in w for w in warnings), warnings
    by_name = {names[int(w.split("device[")[1].split("]")[0])]: w for w in warnings}
    assert "[0, 255] after scale and offset" in by_name["RawOver"]
    assert "[-1024, 1023.5] after" in by_name["RawSignedOver"]
    assert "[0, 100] after" in by_name["PowerOver"]          # the DBC's own maximum counts
    assert "[-32768, 32767] after" in by_name["SpeedOver"]
    assert "[0, 65535] after" in by_name["CwOver"]
    assert "[-2.14748e+09, 2.14748e+09] after" in by_name["TargetOver"]
    assert "[0, 4.29497e+06] after" in by_name["VelOver"]
    assert "[-128, 127] after" in by_name["ByteOver"]
    assert "[0, 1] after" in by_name["FlagOver"]


def test_check_parses_each_dbc_and_eds_once(tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    import canopen
    import cantools

    loads: list[str] = []
    real_dbc, real_od = cantools.database.load_file, canopen.import_od

    def load_dbc(path: Any, **kw: Any) -> Any:
        loads.append("dbc")
        return real_dbc(path, **kw)

    def import_od(path: Any, node_id: Any = None) -> Any:
        loads.append("eds")
        return real_od(path, node_id)

    monkeypatch.setattr(cantools.database, "load_file", load_dbc)
    monkeypatch.setattr(canopen, "import_od", import_od)
    dbc = _write(tmp_path, "once.dbc", _DBC)
    eds = (Path(__file__).resolve().parent.parent / "chcos" / "apps" / "sim" / "eds"
           / "servo_drive.eds")
    eds_copy = _write(tmp_path, "once.eds", eds.read_text())
    text = (f'[[bus]]\nname = "c"\nkind = "can"\ninterface = "virtual"\nchannel = "x"\n'
            f'dbc = "{dbc}"\n'
            f'[[bus]]\nname = "o"\nkind = "canopen"\ninterface = "virtual"\nchannel = "y"\n'
            f'nodes = [{{ id = 5, eds = "{eds_copy}" }}]\n'
            + "".join(_actuator(f"P{i}", "c", "[0, 100]", '{ message = "Cmd", signal = "Power" }')
                      for i in range(5))
            + "".join(_actuator(f"C{i}", "o", "[0, 100]", "{ node = 5, index = 0x6040 }")
                      for i in range(5)))
    dmap, errors, warnings = check(_write(tmp_path, "once.toml", text))
    assert dmap is not None and not errors and not warnings, (errors, warnings)
    assert loads.count("eds") <= 2 and loads.count("dbc") <= 2, loads   # bus check + devices


def test_shipped_maps_still_check(tmp_path: Path) -> None:
    root = Path(__file__).resolve().parent.parent
    for name in ("chcos/apps/fig65/fig65.toml", "chcos/apps/weld/maps/weld_cell.toml",
                 "chcos/apps/weld/maps/weld_direct.toml", "busconfig/examples/serial_cell.toml",
                 "busconfig/examples/bench.toml"):
        dmap, errors, warnings = check(root / name)
        assert dmap is not None and not errors, errors
        assert all("limits" not in w and "stale_after" not in w for w in warnings), warnings


# ---- properties ------------------------------------------------------------------------------
_KEYS = st.sampled_from(["name", "kind", "direction", "machine", "bus", "address", "priority",
                         "stale_after", "scale", "offset", "limits", "safe_value", "units",
                         "history", "rate_hz", "waveform", "table", "type", "unit", "host",
                         "poll_period", "timeout", "nodes", "id", "fields", "struct", "sync",
                         "protocol", "url", "pattern", "group", "field", "format", "x"])
_SCALARS = st.one_of(
    st.integers(), st.sampled_from([2**63, 2**64, -(2**64), 10**400, 0, -1, 1]),
    st.floats(), st.sampled_from([1e308, 5e-324, -0.0]), st.booleans(),
    st.text(st.characters(blacklist_categories=("Cs",)), max_size=12),
    st.sampled_from(["sensor", "actuator", "m", "g", "mb", "memory", "signal", "modbus-tcp",
                     "serial", "canopen", "can", "holding", "coil", "uint16", "sine", "\u00e9",
                     "S\n", "<h", "AA", "binary", "line", "loop://", "127.0.0.1"]))
_VALUES = st.recursive(_SCALARS, lambda c: st.one_of(
    st.lists(c, max_size=3), st.dictionaries(_KEYS, c, max_size=3)), max_leaves=8)


def _base() -> dict[str, list[dict[str, Any]]]:
    return {
        "bus": [{"name": "m", "kind": "memory", "history": 10},
                {"name": "g", "kind": "signal"},
                {"name": "mb", "kind": "modbus-tcp", "host": "127.0.0.1", "poll_period": 0.1},
                {"name": "s", "kind": "serial", "url": "loop://", "protocol": "binary",
                 "sync": "AA", "struct": "<h", "fields": ["v"]}],
        "device": [
            {"name": "S1", "direction": "sensor", "bus": "m", "stale_after": 0.5,
             "scale": 2.0, "offset": 1.0, "limits": [0.0, 10.0]},
            {"name": "S2", "direction": "sensor", "bus": "g",
             "address": {"waveform": "sine", "rate_hz": 20, "period": 1.0}},
            {"name": "A1", "direction": "actuator", "bus": "m", "limits": [-5.0, 5.0],
             "safe_value": 0.0},
            {"name": "R1", "direction": "sensor", "bus": "mb",
             "address": {"table": "holding", "address": 3, "type": "int16"}},
            {"name": "V1", "direction": "sensor", "bus": "s", "address": {"field": "v"}},
        ]}


@st.composite
def _mutated(draw: st.DrawFn) -> dict[str, list[dict[str, Any]]]:
    doc = _base()
    for _ in range(draw(st.integers(1, 4))):
        table = draw(st.sampled_from(["bus", "device"]))
        entry = draw(st.sampled_from(doc[table]))
        op = draw(st.sampled_from(["set", "set", "del", "nest"]))
        key = draw(_KEYS)
        if op == "del":
            entry.pop(key, None)
        elif op == "nest" and isinstance(entry.get("address"), dict):
            entry["address"][key] = draw(_VALUES)
        else:
            entry[key] = draw(_VALUES)
    return doc


def _assert_clean(p: Path, errors: list[str], warnings: list[str]) -> None:
    for line in errors + warnings:
        assert line.startswith(str(p)), line
        assert DRIVER_BUG not in line, line
        assert "\n" not in line and len(line) < 600, line


@pytest.fixture
def fuzz_dir(tmp_path: Path) -> Iterator[Path]:
    yield tmp_path


@FUZZ
@given(_mutated())
def test_any_mutated_map_is_loaded_or_refused_by_file_and_key(
        fuzz_dir: Path, doc: dict[str, list[dict[str, Any]]]) -> None:
    p = _write(fuzz_dir, "fuzz.toml", _toml(doc))
    dmap, errors, warnings = check(p)
    _assert_clean(p, errors, warnings)
    if dmap is None:
        assert errors
        return
    # a valid map runs: its memory and signal devices on virtual time, bounded
    local = dmap.merged(type(dmap)())
    kinds = {b.name: b.kind for b in local.buses}
    runnable = type(dmap)(tuple(b for b in local.buses if b.kind in ("memory", "signal")),
                          tuple(d for d in local.devices if kinds[d.bus] in ("memory", "signal")))
    s = System(runnable, clock=VirtualClock(), machines=sorted({d.machine for d in runnable.devices}
                                                               | {0}), base_dir=fuzz_dir)
    try:
        s.run_for(0.2)
        assert s.kernel.clock.now() == pytest.approx(0.2)
    finally:
        s.shutdown()


@FUZZ
@given(st.data())
def test_any_edit_of_a_map_text_gives_errors_never_a_traceback(fuzz_dir: Path,
                                                              data: st.DataObject) -> None:
    text = _toml(_base())
    for _ in range(data.draw(st.integers(1, 4))):
        at = data.draw(st.integers(0, len(text)))
        cut = data.draw(st.integers(0, 6))
        ins = data.draw(st.one_of(st.text(max_size=6), st.sampled_from(
            ["[", "]", "{", "}", "=", "\"", "\n", "[[device]]\n", "[[bus]]\n", "inf", "nan",
             BIG, "[" * 300, "{a=" * 300])))
        text = text[:at] + ins + text[at + cut:]
    p = _write(fuzz_dir, "edit.toml", text)
    dmap, errors, warnings = check(p)
    _assert_clean(p, errors, warnings)
    assert (dmap is None) == bool(errors)
