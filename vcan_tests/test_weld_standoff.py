"""The range sensor holds the stand-off: the surface moves under the inspecting (D1) and the
welding (D2) tip, and the tip follows it."""

from __future__ import annotations

from pathlib import Path

from chcos.apps.weld.cell import Cell, open_cell


def _run_until(cell: Cell, task: str, phase: str, travelled: float, limit: float = 120.0) -> None:
    t0 = cell.system.kernel.clock.now()
    while cell.system.kernel.clock.now() - t0 < limit:
        cell.system.run_for(0.2)
        cmd = cell.world(task)["command"]
        sens = cell.world(task)["sensory"]
        done = float(sens.get("travelled", cmd.get("travelled", 0.0)) or 0.0)
        if cmd.get("phase") == phase and done >= travelled:
            return
    raise AssertionError(f"{task} never reached {phase} with {travelled} mm travelled")


def test_the_tip_follows_a_surface_that_rises_and_falls(tmp_path: Path) -> None:
    with open_cell("direct", workdir=tmp_path) as cell:
        cell.start_job()
        _run_until(cell, "D1", "track", 60.0)
        m = cell.model
        held = m.standoff
        z0 = m.pose.position[2]
        m.move_surface(3.0)  # the plate rises 3 mm under the inspecting tip
        assert abs(m.standoff - (held - 3.0)) < 1e-9
        cell.system.run_for(4.0)
        assert cell.world("D1")["command"]["phase"] == "track"
        assert abs(m.standoff - held) < 0.6, (m.standoff, held)
        assert abs(m.pose.position[2] - (z0 + 3.0)) < 0.8
        # and while welding: the plate drops 2 mm, the tip goes down with it, the arc stays
        _run_until(cell, "D2", "weld", 60.0, limit=200.0)
        held = m.standoff
        m.move_surface(-2.0)
        cell.system.run_for(5.0)
        assert cell.world("D2")["command"]["phase"] in ("weld", "unstick")
        assert abs(m.standoff - held) < 0.6, (m.standoff, held)
        cell.run(200.0)
        out = cell.outcome()
        assert out is not None and out["outcome"] == "welded", out
