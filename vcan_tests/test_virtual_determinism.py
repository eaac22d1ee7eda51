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
import tomllib
from pathlib import Path
from typing import Any

from chcos.apps.sim.from_map import SimSlaves
from chcos.cli import cellsystem
from chcos.testing import TestCell
from chcos.user.context import TaskContext
from vcan_tests.support_cia402 import imported_sync_drive
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
    volts = {row[1 + DEVICES.index("voltage_l1")][0] for row in first}   # samples on the
    assert len(volts) >= 5 and all(225.0 <= v <= 235.0 for v in volts), volts  # polls' grid
    assert all(status == "OK" for row in first for value, status in row[1:1 + len(DEVICES)])


# -- a CANopen bus with sync_period: SYNC on the virtual clock ------------------------------------

NODE = 4
SYNC_PERIOD = 0.01      # what the importer chooses for synchronous TPDOs
M = "vcan_tests.test_virtual_determinism"
SYNC_STEP = 0.01    # virtual seconds between two samples of the SYNC cell (the move is quick)


async def move_task(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Enables the imported axis and moves it out to 400 and back to 0."""
    x = ctx.axis("axis")
    for op, *args in (("set_mode",), ("enable",), ("move_to", 400.0), ("move_to", 0.0)):
        await getattr(x, op)(*args)


def sync_cell(where: Path) -> Path:
    """A cell of one CiA 402 drive whose TPDOs are synchronous (transmission type 1, no event
    timer), imported from its EDS: the importer gives the bus a ``sync_period``."""
    devmap = imported_sync_drive(where, NODE, "Synchronous servo")
    assert tomllib.loads(devmap.read_text(encoding="utf-8"))["bus"][0]["sync_period"] \
        == SYNC_PERIOD
    (where / "install.chcos").write_text(
        f"install -m0 sysfile\ninstall -m0o1 --code={M}:move_task T axis\n", encoding="utf-8")
    system = where / "system.toml"
    system.write_text(f'[system]\nname = "sync"\ndevmaps = ["{devmap}"]\n'
                      'install = "install.chcos"\n', encoding="utf-8")
    return system


def sync_trace(system: Path, work: Path) -> tuple[list[tuple[Any, ...]], list[int]]:
    """The SYNC cell run for SAMPLES steps of SYNC_STEP: per step the time, the axis's state and
    position as chcos reports them, what the drive publishes, the SYNCs it received and the
    bus's SYNC counters; then the SYNCs the drive received in each of the next ten intervals
    of 0.1 virtual seconds."""
    out: list[tuple[Any, ...]] = []
    with cellsystem.open_cell(system, virtual=True, workdir=work) as cell:
        assert cell.slaves is not None
        drive = cell.slaves.canopen_node("drive", NODE)
        cell.system.invoke("T", {})
        for _ in range(SAMPLES):
            cell.run_for(SYNC_STEP)
            sync = cell.system.devtab.bus_status()["drive"]["sync"]
            out.append((round(cell.now(), 6), cell.device("axis.state").value,
                        cell.device("axis.position").value, drive.published(),
                        drive.stats.syncs, sync["cycles"], sync["complete"], sync["missing"],
                        sync["late"]))
        counts = []
        for _ in range(10):
            before = drive.stats.syncs
            cell.run_for(0.1)
            counts.append(drive.stats.syncs - before)
        stats = cell.system.devtab.bus_status()["drive"]["sync"]
        assert stats["jitter_max"] < 1e-6, stats      # SYNC n at n * period, virtual time
        return out, counts


def test_a_cell_with_sync_is_deterministic(tmp_path: Path) -> None:
    system = sync_cell(tmp_path)
    first, counts = sync_trace(system, tmp_path / "one")
    second, counts2 = sync_trace(system, tmp_path / "two")
    for a, b in zip(first, second, strict=True):
        assert a == b, f"the runs part at t={a[0]} s:\n{a}\n{b}"
    # SYNC follows virtual time: exactly period by period, each one seen by the drive
    assert counts == counts2 == [round(0.1 / SYNC_PERIOD)] * 10
    # the drive went out to 400 and back, reported through its synchronous TPDOs only
    positions = [row[2] for row in first]
    assert max(positions) == 400.0 and positions[-1] == 0.0, positions
    assert any(0.0 < p < 400.0 for p in positions), positions    # seen on the way
    # every SYNC was answered in its cycle: none late, no synchronous TPDO missing
    t, _state, _pos, _published, syncs, cycles, complete, missing, late = first[-1]
    assert missing == 0 and late == 0 and complete >= cycles - 2, first[-1]
    # SYNC n at n * period from the start (the driver starts at virtual time 0)
    assert syncs == cycles == round(t / SYNC_PERIOD), first[-1]
