"""Device-map loading: the happy path, a table of bad files, merged files, python-can config."""

from __future__ import annotations

from pathlib import Path

import pytest

from chcos.devices.devmap import check_main, load
from chcos.errors import ConfigError
from vcan_tests.support_dev import CELL_DBC, EXAMPLES

ROOT = Path(__file__).resolve().parent.parent

MEM_BUS = '[[bus]]\nname = "m"\nkind = "memory"\n'


def write(tmp: Path, name: str, text: str) -> Path:
    p = tmp / name
    p.write_text(text, encoding="utf-8")
    return p


def test_fig65_loads_with_defaults_and_open_limits(tmp_path: Path) -> None:
    dm = load(ROOT / "chcos" / "apps" / "fig65" / "fig65.toml")
    assert [d.name for d in dm.devices] == ["S1", "S2", "S3", "M1", "M2"]
    assert {d.name: d.machine for d in dm.devices} == {"S1": 0, "S2": 0, "S3": 1, "M1": 0,
                                                        "M2": 1}
    m1 = next(d for d in dm.devices if d.name == "M1")
    assert m1.direction == "actuator" and m1.safe_value == 0.0 and m1.priority == 8
    assert m1.key == "device[3]" and m1.file.endswith("fig65.toml")
    p = write(tmp_path, "open.toml", MEM_BUS + '[[device]]\nname = "A"\ndirection = "actuator"\n'
              'bus = "m"\nlimits = [-inf, 5]\nsafe_value = -1e9\n')
    a = load(p).devices[0]
    assert a.limits == (None, 5.0) and a.scale == 1.0 and a.offset == 0.0 and a.units == ""


BAD = [
    ("unknown device key", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\n'
     'colour="red"\n', "f.toml:4: device[0]: unknown key 'colour'; valid keys: name, direction"),
    ("bad direction", MEM_BUS + '[[device]]\nname="A"\ndirection="input"\nbus="m"\n',
     "f.toml:4: device[0].direction: expected \"sensor\" or \"actuator\", got 'input'"),
    ("priority range", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\n'
     'priority=100\n', "device[0].priority: expected an integer 0..99, got 100"),
    ("lo > hi", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\nlimits=[5, 1]\n',
     "device[0].limits: expected lo <= hi, got [5, 1]"),
    ("safe outside", MEM_BUS + '[[device]]\nname="A"\ndirection="actuator"\nbus="m"\n'
     'limits=[0, 1]\nsafe_value=2\n', "device[0].safe_value: expected a value within limits"),
    ("no such bus", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="x"\n',
     "device[0].bus: no bus named 'x'; expected one of: m"),
    ("machine type", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\n'
     'machine="one"\n', "device[0].machine: expected an integer 0..9999, got 'one'"),
    ("scale zero", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\nscale=0\n',
     "device[0].scale: expected a non-zero number"),
    ("stale on actuator", MEM_BUS + '[[device]]\nname="A"\ndirection="actuator"\nbus="m"\n'
     'stale_after=1\n', "device[0].stale_after: applies to sensors only"),
    ("duplicate device", MEM_BUS + '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\n'
     '[[device]]\nname="A"\ndirection="sensor"\nbus="m"\n',
     "f.toml:8: device[1].name: device name 'A' is already used by"),
    ("toml syntax", MEM_BUS + "[[device]\n", "f.toml:4: invalid TOML"),
    ("top key", 'title = "x"\n' + MEM_BUS, "f.toml: unknown key 'title'; valid keys: bus, device"),
    ("unknown kind", '[[bus]]\nname="q"\nkind="profibus"\n',
     "f.toml:1: bus[0].kind: bus kind 'profibus' has no usable driver"),
    ("memory option", MEM_BUS + "speed = 3\n",
     "bus[0].speed: unknown key; expected one of history"),
    ("signal waveform", '[[bus]]\nname="s"\nkind="signal"\n[[device]]\nname="S"\n'
     'direction="sensor"\nbus="s"\naddress={waveform="saw", rate_hz=10}\n',
     "f.toml:4: device[0].address.waveform: expected one of 'sine', 'square', 'ramp'"),
    ("can dbc signal", f'[[bus]]\nname="c"\nkind="can"\ninterface="virtual"\nchannel="x"\n'
     f'dbc="{CELL_DBC}"\n[[device]]\nname="T"\ndirection="sensor"\nbus="c"\n'
     'address={message="Temps", signal="T9"}\n',
     "device[0].address.signal: no signal 'T9' in message Temps; expected one of: T1, T2"),
    ("can raw id", '[[bus]]\nname="c"\nkind="can"\ninterface="virtual"\nchannel="x"\n'
     '[[device]]\nname="T"\ndirection="sensor"\nbus="c"\naddress={id=0x800, start=0, length=8}\n',
     "device[0].address.id: expected a CAN id 0..0x7FF, got 2048"),
    ("can missing dbc", '[[bus]]\nname="c"\nkind="can"\ninterface="virtual"\nchannel="x"\n'
     'dbc="nope.dbc"\n', "bus[0].dbc: DBC file "),
    ("serial group", '[[bus]]\nname="s"\nkind="serial"\nurl="loop://"\nprotocol="line"\n'
     "pattern='T=(?P<t>\\d+)'\n[[device]]\nname=\"T\"\ndirection=\"sensor\"\nbus=\"s\"\n"
     'address={group="u"}\n', "device[0].address.group: expected one of t, got 'u'"),
    ("serial struct", '[[bus]]\nname="s"\nkind="serial"\nurl="loop://"\nprotocol="binary"\n'
     'sync="AA"\nstruct="<hh"\nfields=["a"]\n',
     "bus[0].fields: struct '<hh' has 2 items, expected as many names, got 1"),
]


@pytest.mark.parametrize(("text", "expected"), [(t, e) for _, t, e in BAD],
                         ids=[n for n, _, _ in BAD])
def test_bad_device_maps_name_file_key_and_expectation(tmp_path: Path, text: str,
                                                       expected: str) -> None:
    p = write(tmp_path, "f.toml", text)
    with pytest.raises(ConfigError) as info:
        load(p)
    assert expected in str(info.value).replace(str(p), "f.toml")


def test_all_errors_of_a_set_are_collected(tmp_path: Path) -> None:
    a = write(tmp_path, "a.toml", MEM_BUS + '[[device]]\nname="A"\ndirection="up"\nbus="m"\n')
    b = write(tmp_path, "b.toml", MEM_BUS + '[[device]]\nname="B"\ndirection="sensor"\n'
              'bus="m"\npriority=-1\n')
    with pytest.raises(ConfigError) as info:
        load([a, b])
    msg = str(info.value)
    assert f"{a}:4: device[0].direction" in msg
    assert f"{b}:1: bus[0].name: bus name 'm' is already used by {a} bus[0]" in msg
    assert f"{b}:4: device[0].priority" in msg
    assert msg.startswith("3 error(s)")


def test_merged_files_share_buses_and_resolve_paths(tmp_path: Path) -> None:
    sub = tmp_path / "cell"
    sub.mkdir()
    (sub / "cell.dbc").write_text(CELL_DBC.read_text())
    buses = write(sub, "buses.toml", '[[bus]]\nname="c"\nkind="can"\ninterface="virtual"\n'
                  'channel="x"\ndbc="cell.dbc"\nrecord="out/s.log"\n')
    devs = write(tmp_path, "devs.toml", '[[device]]\nname="T1"\ndirection="sensor"\nbus="c"\n'
                 'machine=2\naddress={message="Temps", signal="T1"}\n')
    dm = load([buses, devs])
    assert dm.bus("c").options["dbc"] == str((sub / "cell.dbc").resolve())
    assert dm.bus("c").options["record"] == str((sub / "out" / "s.log").resolve())
    assert dm.devices_on("c")[0].machine == 2 and dm.files == (str(buses), str(devs))


def test_can_bus_takes_interface_and_channel_from_python_can_env(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    p = EXAMPLES / "can_cell.toml"
    monkeypatch.delenv("CAN_INTERFACE", raising=False)
    monkeypatch.delenv("CAN_CHANNEL", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))          # no ~/.canrc or ~/can.conf
    monkeypatch.chdir(tmp_path)                       # no ./can.ini
    with pytest.raises(ConfigError, match=r"bus\[0\].interface: expected interface and channel"):
        load(p)
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "cell")
    dm = load(p)
    assert "interface" not in dm.bus("cellcan").options
    assert [d.name for d in dm.devices] == ["T1", "P1", "Door", "Spindle", "SpindleOn"]


def test_check_main_prints_ok_or_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                        ) -> None:
    assert check_main([str(ROOT / "chcos" / "apps" / "fig65" / "fig65.toml"),
                       str(EXAMPLES / "bench.toml")]) == 0
    assert capsys.readouterr().out == "ok: 2 buses, 7 devices\n"
    bad = write(tmp_path, "bad.toml", MEM_BUS + '[[device]]\nname="A"\nbus="m"\n')
    assert check_main([str(bad)]) == 1
    assert f"{bad}:4: device[0].direction" in capsys.readouterr().err
    assert check_main([str(tmp_path / "missing.toml")]) == 1
    assert "cannot read the file" in capsys.readouterr().err
