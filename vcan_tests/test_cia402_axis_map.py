"""The device-map schema of a CiA 402 axis (issue 37): ``profile = "cia402"`` tables checked
offline (errors name the file, line and key; the node's EDS must hold the axis's objects), the
devices an axis becomes, and ``safe_value = "none"`` with its reason instead of a warning."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from chcos.devices.devmap import check
from vcan_tests.support_cia402 import drive_eds

AXIS = """
[[device]]
name = "x"
profile = "cia402"
bus = "drives"
address = {{ node = 5{axis} }}
mode = "PP"
counts_per_unit = 1000.0
{extra}
"""


def write_map(tmp_path: Path, extra: str = "", *, axis: str = "", eds_text: str | None = None,
              more: str = "") -> Path:
    eds = tmp_path / "drive.eds"
    eds.write_text(eds_text if eds_text is not None else drive_eds(), encoding="utf-8")
    path = tmp_path / "cell.toml"
    path.write_text(f"""
[[bus]]
name = "drives"
kind = "canopen"
interface = "virtual"
channel = "unused"
nodes = [{{ id = 5, eds = "{eds}" }}]
""" + AXIS.format(axis=axis, extra=extra) + more, encoding="utf-8")
    return path


def test_an_axis_becomes_its_actuator_and_sensors(tmp_path: Path) -> None:
    dmap, errors, warnings = check(write_map(tmp_path, 'units = "mm"\nsafe_stop = '
                                                       '"halt_then_disable"'))
    assert errors == [] and warnings == [] and dmap is not None
    devs = {d.name: d for d in dmap.devices}
    assert set(devs) == {"x", "x.state", "x.statusword", "x.mode", "x.position", "x.velocity",
                         "x.fault"}
    x = devs["x"]
    assert x.direction == "actuator" and x.safe_value == 0.0 and x.bus == "drives"
    assert x.address["config"]["safe_stop"] == "halt_then_disable" and x.address["mode"] == 1
    assert all(devs[n].direction == "sensor" for n in devs if n != "x")
    assert devs["x.position"].units == "mm" and devs["x.velocity"].units == "mm/s"


@pytest.mark.parametrize(("extra", "key", "words"), [
    ("timeouts = { enabel = 1.0 }", "device[0].timeouts.enabel", "unknown timeout"),
    ("counts_per_unit_ = 3", "device[0]", "unknown key 'counts_per_unit_'"),
    ('safe_stop = "coast"', "device[0].safe_stop", "quick_stop_then_disable"),
    ("position_limits = [5.0, 1.0]", "device[0].position_limits", "not below"),
    ('mode = "XX"', "device[0].mode", "mode of operation"),
    ("direction = \"actuator\"", "device[0]", "unknown key 'direction'"),
])
def test_a_bad_axis_key_is_named_with_file_and_line(tmp_path: Path, extra: str, key: str,
                                                    words: str) -> None:
    path = write_map(tmp_path, extra)
    if extra.startswith("mode"):    # replace the map's own mode
        path.write_text(path.read_text().replace('mode = "PP"\n', ""), encoding="utf-8")
    dmap, errors, _ = check(path)
    assert dmap is None
    assert any(e.startswith(f"{path}:") and f": {key}" in e and words in e for e in errors), errors


def test_the_nodes_eds_must_hold_the_axis_objects(tmp_path: Path) -> None:
    path = write_map(tmp_path, eds_text=drive_eds(without=(0x6061,), tpdos=((0x6041,),)))
    _, errors, _ = check(path)
    assert any("device[0].address" in e and "0x6061" in e for e in errors), errors
    path = write_map(tmp_path, axis=", axis = 1")       # objects at 0x6840...: not in the EDS
    _, errors, _ = check(path)
    assert any("0x6840" in e and "0x6841" in e for e in errors), errors


def test_the_axis_node_must_be_on_the_bus(tmp_path: Path) -> None:
    path = write_map(tmp_path)
    path.write_text(path.read_text().replace("node = 5 }", "node = 9 }"), encoding="utf-8")
    _, errors, _ = check(path)
    assert any("device[0].address.node" in e and "9" in e for e in errors), errors


PLAIN_TARGET = """
[[device]]
name = "target"
direction = "actuator"
bus = "drives"
address = {{ node = 5, index = 0x607A }}
limits = [-1000000.0, 1000000.0]
{safe}
"""


def test_no_safe_value_is_said_once_with_its_reason(tmp_path: Path) -> None:
    path = write_map(tmp_path, more=PLAIN_TARGET.format(safe=""))
    _, errors, warnings = check(path)
    assert errors == [] and any("device[1].safe_value" in w for w in warnings)
    path = write_map(tmp_path, more=PLAIN_TARGET.format(
        safe='safe_value = "none"\nsafe_reason = "a target position: 0 sends the axis home"'))
    dmap, errors, warnings = check(path)
    assert errors == [] and warnings == [] and dmap is not None
    target = next(d for d in dmap.devices if d.name == "target")
    assert target.safe_value is None and "sends the axis home" in target.safe_reason
    path = write_map(tmp_path, more=PLAIN_TARGET.format(safe='safe_value = "none"'))
    _, errors, _ = check(path)
    assert any("device[1].safe_reason" in e and "needs the reason" in e for e in errors)
    path = write_map(tmp_path, more=PLAIN_TARGET.format(
        safe='safe_value = 0\nsafe_reason = "x"'))
    _, errors, _ = check(path)
    assert any("device[1].safe_reason" in e and "only with" in e for e in errors)


def test_chcos_check_on_an_axis_map(tmp_path: Path) -> None:
    path = write_map(tmp_path, "timeouts = { enable = -1.0 }")
    out = subprocess.run([sys.executable, "-m", "chcos.cli.main", "check", str(path)],
                         capture_output=True, text=True, timeout=120, check=False)
    assert out.returncode == 1
    assert "device[0].timeouts.enable" in out.stderr + out.stdout
