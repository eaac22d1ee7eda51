"""Device-state coverage of a CANopen cell (issue 52): a CiA 402 drive imported from its EDS, on
virtual time against the simulated node generated from its map; a task enables the axis and
moves it, the node raises an EMCY (0x2310, over-current) and resets it. The axis's catalogue is
its state machine, its node's NMT states and EMCYs (no stale state: no ``stale_after``); what the
run reached is what the drive reported: the CiA 402 states it went through to OPERATION_ENABLED,
OPERATIONAL, the EMCY with its code and the error reset, the safe stop at shutdown."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chcos.cli import cellsystem
from chcos.hil.catalogue import CIA402_STATES, NMT_STATES, State, StateClass
from chcos.hil.coverage import CellCoverage, Coverage, table_lines
from chcos.hil.observe import Observer
from chcos.user.context import TaskContext
from vcan_tests.support_cia402 import imported_sync_drive

NODE = 4
M = "vcan_tests.test_hil_canopen"


async def move_task(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Enables the axis and moves it out to 400 and back to 0."""
    x = ctx.axis("axis")
    for op, *args in (("set_mode",), ("enable",), ("move_to", 400.0), ("move_to", 0.0)):
        await getattr(x, op)(*args)


def test_a_cia402_cell_reaches_its_state_machine_nmt_and_emcy(tmp_path: Path) -> None:
    devmap = imported_sync_drive(tmp_path, NODE, "Synchronous servo")
    (tmp_path / "install.chcos").write_text(
        f"install -m0 sysfile\ninstall -m0o1 --code={M}:move_task T axis\n", encoding="utf-8")
    system = tmp_path / "system.toml"
    system.write_text(f'[system]\nname = "axis"\ndevmaps = ["{devmap}"]\n'
                      'install = "install.chcos"\n', encoding="utf-8")
    watched: list[tuple[Observer, CellCoverage]] = []

    def watch(cell: cellsystem.Cell) -> None:
        obs = Observer(cell.system, start=cell.start, poll=0.02)
        cov = CellCoverage(cell.system, "the run")
        obs.sinks.append(cov)
        watched.append((obs.attach(), cov))

    with cellsystem.open_cell(system, virtual=True, workdir=tmp_path / "w",
                              observe=[watch]) as cell:
        assert cell.slaves is not None
        cell.slaves.schedule_emcy([f"drive:{NODE}:0x2310@2-3"])
        cell.system.invoke("T", {})
        cell.run_for(4.0)
        assert cell.device("axis.position").value == 0.0
    obs, cell_cov = watched[0]
    obs.detach()
    cov = Coverage()
    cov.add_cell(cell_cov)
    axis = cov.subjects["device:axis"]
    assert axis.subject.role == "axis" and set(axis.subject.devices) >= {"axis", "axis.state"}
    catalogued = {st for st, e in axis.states.items() if e.catalogued}
    assert {State(StateClass.CIA402, s) for s in CIA402_STATES} <= catalogued
    assert {State(StateClass.NMT, s) for s in NMT_STATES} <= catalogued
    assert State(StateClass.FAILURE, "drive-fault") in catalogued
    assert State(StateClass.STATUS, "stale") not in catalogued   # no stale_after
    assert State(StateClass.FAILURE, "emcy") not in catalogued   # an axis: drive-fault
    reached = {st: e for st, e in axis.states.items() if e.tests}
    for s in ("SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON", "SWITCHED_ON", "OPERATION_ENABLED"):
        assert State(StateClass.CIA402, s) in reached, sorted(map(str, reached))
    assert State(StateClass.CIA402, "FAULT") not in reached
    assert State(StateClass.NMT, "OPERATIONAL") in reached
    assert reached[State(StateClass.EMCY, "EMCY")].details == {"0x2310"}
    assert State(StateClass.EMCY, "error reset") in reached
    assert State(StateClass.SAFE, "shutdown") in reached
    assert State(StateClass.NMT, "reboot") not in reached
    # the EMCY is the node's, not a bus error of the bus; the bus reached nothing
    bus = cov.subjects["bus:drive"]
    assert not [e for e in bus.states.values() if e.tests]
    lines = table_lines(cov, verbose=True)
    assert any(line.startswith("device axis (axis)") for line in lines), lines
