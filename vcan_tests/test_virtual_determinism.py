"""A user's virtual cell is deterministic: the tutorial's cell (docs/from-vendor-files.md: a CiA
402 drive on CANopen from an EDS, a gripper on CAN from a DBC, an energy meter on Modbus TCP from
its register table), built twice by the pytest plugin against the simulated slaves generated
from its maps, gives the same values at the same virtual times, run after run and with both
cores loaded: the simulated devices step on the virtual clock, and virtual time does not move on
while a driver or a simulated device still has work in flight."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

from chcos.apps.sim.from_map import SimSlaves
from chcos.testing import TestCell
from vcan_tests.support_docs import doc_commands

ROOT = Path(__file__).resolve().parent.parent
TUTORIAL = ROOT / "docs" / "from-vendor-files.md"
STEP = 0.1          # virtual seconds between two samples
SAMPLES = 50        # five virtual seconds
#: what each sample records: Devtab's value and status of these devices...
DEVICES = ("axis", "axis.state", "axis.position", "axis.velocity", "setpoint", "position",
           "voltage_l1")
#: ...and what the simulated slaves hold for these
PEERS = ("axis", "setpoint")


def tutorial_cell(where: Path) -> Path:
    """The tutorial's cell in ``where``, built by its own commands (sections 1 and 2: import
    the vendor files, write the tasks, the install script and the system file, check it)."""
    for f in ("drive.eds", "gripper.dbc", "meter.csv"):
        shutil.copy(ROOT / "docs" / "vendor" / f, where / f)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env.pop("PYTEST_ADDOPTS", None)
    for cmd in doc_commands(TUTORIAL):
        if cmd.startswith("chcos run"):
            break
        res = subprocess.run(["bash", "-c", cmd], cwd=where, env=env, text=True,
                             capture_output=True, timeout=300)
        assert res.returncode == 0, f"{cmd}\n{res.stdout}\n{res.stderr}"
    return where / "system.toml"


def gripper(t: float, slaves: SimSlaves) -> None:
    """The gripper's plant: its position follows the set-point the cell sent it."""
    slaves.set("position", slaves.get("setpoint") or 0.0)


def trace(cell: TestCell) -> list[tuple[Any, ...]]:
    """Every STEP of virtual time for SAMPLES steps: the time, each device's value and status,
    what the simulated slaves hold."""
    out: list[tuple[Any, ...]] = []
    for _ in range(SAMPLES):
        cell.run_for(STEP)
        out.append((round(cell.now, 6),
                    *((cell.value(d), cell.status(d)) for d in DEVICES),
                    *(cell.peer(p) for p in PEERS)))
    return out


def test_the_same_cell_twice_gives_the_same_trace(tmp_path: Path, chcos_cell: Any) -> None:
    system = tutorial_cell(tmp_path)
    values = {"voltage_l1": "sine(230, 5, 1)"}
    first = trace(chcos_cell(system, values=values, plant=gripper))
    second = trace(chcos_cell(system, values=values, plant=gripper))
    for a, b in zip(first, second, strict=True):
        assert a == b, f"the runs part at t={a[0]} s:\n{a}\n{b}"
    # the trace is worth comparing: the drive went out and back, the gripper followed it
    # over CAN, the meter's voltage was read over Modbus as its script moved it
    positions = [row[1 + DEVICES.index("axis.position")][0] for row in first]
    assert min(positions) == 0.0 and max(positions) == 1000.0, positions
    sent = [row[1 + len(DEVICES) + PEERS.index("setpoint")] for row in first]
    assert max(sent) == 100.0 and min(sent) == 0.0, sent
    followed = [row[1 + DEVICES.index("position")][0] for row in first]
    assert max(followed) > 50.0 > min(followed), followed
    volts = {row[1 + DEVICES.index("voltage_l1")][0] for row in first}
    assert len(volts) > 5 and all(225.0 <= v <= 235.0 for v in volts), volts
    assert all(status == "OK" for row in first for value, status in row[1:1 + len(DEVICES)])
