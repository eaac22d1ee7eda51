"""test_cia402_journey - a vendor CiA 402 drive's EDS from import to a moving axis, as a newcomer
takes it: ``chcos import eds`` (one axis, not every object), ``chcos check``, ``chcos run
--virtual`` (the node simulated as a :class:`chcos.apps.sim.cia402_drive.Cia402Drive`), a task
commanding ``ctx.axis`` without touching a bit. The EDS has what broke the newcomer: the
controlword in every RPDO, synchronous TPDOs, objects without a DefaultValue. Every assertion is
on the drive's side (the controlwords it applied, its state and position) or what chcos reports.
"""

from __future__ import annotations

import itertools
import time
import tomllib
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.sim.cia402_drive import Cia402Drive
from chcos.cli import cellsystem
from chcos.cli import main as cli
from chcos.devices.devmap import check_main
from chcos.errors import ChcosError
from chcos.user.context import TaskContext
from vcan_tests.support_cia402 import drive_eds

M = "vcan_tests.test_cia402_journey"
NODE = 4
WALL = 30.0     # wall seconds a wait may take on a loaded machine before the test gives up


async def journey_task(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Runs ``cmd["steps"]`` (``(op, *args)``) on the imported axis; logs (op, "ok" or error)."""
    x = ctx.axis("axis")
    log: list[tuple[str, str]] = cmd["log"]
    for op, *args in cmd["steps"]:
        try:
            await getattr(x, op)(*args)
        except ChcosError as exc:
            log.append((op, str(exc)))
            continue
        log.append((op, "ok"))


def imported(tmp_path: Path, eds: Path, *extra: str) -> tuple[Path, dict[str, Any]]:
    out = tmp_path / "drive.toml"
    assert cli.main(["import", "eds", str(eds), "--node", str(NODE), "--bus", "drive",
                     "-o", str(out), *extra]) == 0
    assert check_main([str(out)]) == 0
    return out, tomllib.loads(out.read_text(encoding="utf-8"))


@pytest.fixture
def vendor_eds(tmp_path: Path) -> Path:
    path = tmp_path / "vendor_drive.eds"
    path.write_text(drive_eds(name="Vendor servo", transmission=1, event_timer=0,
                              extra=((0x2000, "Save current configuration", 0x0007, "rw", 0),
                                     (0x2001, "Execute TML program", 0x0006, "wo", None),
                                     (0x2002, "Heat sink temperature", 0x0003, "ro", None))),
                    encoding="utf-8")
    return path


def test_import_writes_one_axis_with_the_objects_it_needs(vendor_eds: Path,
                                                          tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]
                                                          ) -> None:
    out, doc = imported(tmp_path, vendor_eds)
    err = capsys.readouterr().err
    assert "synchronous" in err and "sync_period = 0.01 s was chosen" in err
    (axis,) = doc["device"]                            # one device, not the dictionary
    assert axis == {"name": "axis", "profile": "cia402", "bus": "drive",
                    "address": {"node": NODE, "axis": 0}, "mode": "PP",
                    "counts_per_unit": 1.0, "quick_stop_option": 2,
                    "safe_stop": "quick_stop_then_disable"}
    assert doc["bus"][0]["sync_period"] == 0.01
    text = out.read_text(encoding="utf-8")
    assert "0x6040 Controlword is mapped in RPDO1" in text and "RPDO4" in text
    assert "set counts_per_unit" in text               # no factor group in this EDS
    # --objects adds exactly those, as plain devices; --all adds every other object
    _out, doc = imported(tmp_path, vendor_eds, "--objects", "0x2002")
    assert [d["name"] for d in doc["device"]] == ["axis", "heat_sink_temperature"]
    _out, doc = imported(tmp_path, vendor_eds, "--all")
    names = {d["name"] for d in doc["device"]}
    assert {"axis", "save_current_configuration", "execute_tml_program",
            "heat_sink_temperature"} <= names
    assert not any(d.get("address", {}).get("index") in (0x6040, 0x6041, 0x607A)
                   for d in doc["device"])            # the axis's objects stay the axis's
    # --plain: the old plain import, with the set-points' missing safe value explained
    _out, doc = imported(tmp_path, vendor_eds, "--plain")
    plain = {d["name"]: d for d in doc["device"]}
    assert plain["target_position"]["safe_value"] == "none"
    assert "would send the axis to position 0" in plain["target_position"]["safe_reason"]
    assert cli.main(["import", "eds", str(vendor_eds), "--node", "4", "--objects",
                     "0x2F00"]) == 2
    assert "--objects 0x2F00: no such object" in capsys.readouterr().err
    assert cli.main(["import", "eds", str(vendor_eds), "--node", "4", "--objects", "x"]) == 2
    assert "--objects 'x': expected an object index" in capsys.readouterr().err


def test_vendor_factor_group_and_multi_axis(tmp_path: Path) -> None:
    second = tuple((i + 0x800, f"Axis 2 {i:04X}", t, a, d) for i, _n, t, a, d in (
        (0x6040, "", 0x0006, "rw", 0), (0x6041, "", 0x0006, "ro", 0),
        (0x6060, "", 0x0002, "rw", 0), (0x6061, "", 0x0002, "ro", 0)))
    path = tmp_path / "two.eds"
    path.write_text(drive_eds(extra=second), encoding="utf-8")
    _out, doc = imported(tmp_path, path)
    assert [(d["name"], d["address"]) for d in doc["device"]] == [
        ("axis1", {"node": NODE, "axis": 0}), ("axis2", {"node": NODE, "axis": 1})]


def test_import_check_run_virtual_and_move_the_axis(vendor_eds: Path, tmp_path: Path) -> None:
    devmap, _doc = imported(tmp_path, vendor_eds)
    system = tmp_path / "system.toml"
    (tmp_path / "install.chcos").write_text(
        f"install -m0 sysfile\ninstall -m0o1 --code={M}:journey_task T axis\n",
        encoding="utf-8")
    system.write_text(f'[system]\nname = "journey"\ndevmaps = ["{devmap}"]\n'
                      'install = "install.chcos"\n', encoding="utf-8")
    log: list[tuple[str, str]] = []
    with cellsystem.open_cell(system, virtual=True, workdir=tmp_path / "work") as cell:
        assert cell.slaves is not None
        drive = cell.slaves.canopen_node("drive", NODE)
        assert isinstance(drive, Cia402Drive)          # a drive, not a bag of objects

        def until(pred: Any) -> bool:
            deadline = time.monotonic() + WALL
            while not pred():
                if time.monotonic() > deadline:
                    return False
                cell.run_for(0.02)
            return True

        assert until(lambda: cell.device("axis.state").value == "SWITCH_ON_DISABLED")
        steps = [("set_mode",), ("enable",), ("move_to", 400.0), ("safe_stop",)]
        cell.system.invoke("T", {"steps": steps, "log": log})
        assert until(lambda: len(log) == len(steps)), log
        assert log == [(s[0], "ok") for s in steps]
        # what the drive applied: the enable walk, the set-point's edge, the quick stop
        cws = drive.received
        walk = [cw for cw, _ in itertools.groupby(cws)]   # resends of a word left aside
        assert walk[walk.index(0x06):walk.index(0x06) + 3] == [0x06, 0x07, 0x0F]
        assert 0x1F in cws and 0x02 in cws[cws.index(0x1F):]
        statusword, mode, position, velocity, _error = drive.published()
        assert statusword & 0x4F == 0x40 and mode == 1     # switch on disabled, PP
        assert position == 400 and velocity == 0
        assert cell.device("axis.position").value == pytest.approx(400.0)
