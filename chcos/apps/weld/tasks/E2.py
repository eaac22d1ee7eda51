"""E2 - level 5: the job (started by the host with ``invoke E2``).

Switch the joint drives on (A6: the safe-torque-off relay, then each CiA 402 drive enabled);
inspect the gap (D1); if the inspection is OK, weld it (D2) starting from the start D1 found;
then go home (B3). Meanwhile it listens to the exception task D3: an alarm aborts the job at
once (the assassin E1 has made the cell safe; E2 does not move it again). Command (a
:class:`chcos.apps.weld.tasks.messages.Job`; from the console ``invoke E2 key=value...``) or
install parameters: ``start`` [x, y] (probable start of the gap, mm), ``heading`` (rad), ``z`` (tip
height, mm), ``home`` [x, y, z]; ``inspect_only`` skips the weld.

Completes with ``{"outcome": "welded" | "inspection failed" | "inspection aborted" |
"weld failed" | "drives failed" | "aborted", "reason", "drives", "inspection", "weld", "home"}``,
a plain dict for the host (``chcos run``, the viewer): the subordinates' results (A6's
``Memorized``, D1's ``Inspection``, D2's ``Welded``, B3's ``Reached``) in it as records
(``messages.record``). The phase and the outcome are in the world model (``phase``,
``outcome``).
"""

from __future__ import annotations

import math
from typing import Any

from chcos.apps.weld.tasks.common import setting
from chcos.apps.weld.tasks.messages import (
    Alarm,
    DrivesCommand,
    GoHome,
    Inspect,
    Job,
    Weld,
    expect,
    from_host,
    record,
)
from chcos.apps.weld.tasks.results import Inspection, Memorized, Reached, Welded
from chcos.tables.messages import Completion
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task


class JobModel(WorldModel):
    """E2's world model: the phase of the job and its outcome."""


class Aborted(Exception):
    """An alarm from D3 ended the job (internal to E2)."""

    def __init__(self, alarm: Alarm) -> None:
        super().__init__(f"{alarm.kind}: {alarm.detail}")
        self.alarm = alarm


async def _run(ctx: TaskContext, port: str, command: Any) -> Completion:
    """Invoke ``port`` and wait for its completion or an alarm from D3, whichever comes first
    (no polling: E2 runs only on completions and alarms)."""
    await ctx.invoke(port, command)
    while True:
        ev = await ctx.wait_any(["D3"], completions=[port])
        if ev.kind == "completion":
            done: Completion = ev.value
            return done
        match ev.value:
            case Alarm() as alarm:
                raise Aborted(alarm)


@task(world_model=JobModel)
async def main(ctx: TaskContext, command: Any) -> dict[str, Any]:
    """Run the job and report its outcome."""
    match command:
        case Job():
            cmd = command
        case None:
            cmd = Job()
        case _:
            cmd = from_host("E2", command, {"job": Job}, "job", "a Job")
    wm = ctx.world
    wm.command.pop("outcome", None)  # a new job: the last one's outcome is history
    start = [float(v) for v in setting(ctx, cmd.start, "start", [542.0, -164.0])]
    heading = float(setting(ctx, cmd.heading, "heading", math.pi / 2))
    z = float(setting(ctx, cmd.z, "z", 10.0))
    out: dict[str, Any] = {"outcome": "", "reason": "", "drives": None, "inspection": None,
                           "weld": None, "home": None}
    try:
        wm.command["phase"] = "drives"
        done = await _run(ctx, "A6", DrivesCommand(enable=True, memorize="start"))
        out["drives"] = dict(expect("E2", done.result, Memorized).drives) if done.ok \
            else done.error
        if not done.ok:
            out.update(outcome="drives failed", reason=done.error)
            wm.command.update(phase="finished", outcome=out)
            ctx.put(out)
            return out
        wm.command["phase"] = "inspect"
        done = await _run(ctx, "D1", Inspect(start=start, heading=heading, z=z))
        inspection = expect("E2", done.result, Inspection) if done.ok else None
        out["inspection"] = record(inspection) if inspection is not None else done.error
        if inspection is None:
            out.update(outcome="inspection aborted", reason=done.error)
        elif not inspection.ok:
            out.update(outcome="inspection failed", reason=inspection.reason)
        elif setting(ctx, cmd.inspect_only, "inspect_only", False):
            out.update(outcome="inspected")
        else:
            wm.command["phase"] = "weld"
            found, gap = inspection.start, float(inspection.heading)
            weld = Weld(start=[found[0] + 5.0 * math.cos(gap), found[1] + 5.0 * math.sin(gap)],
                        heading=gap, z=z)
            done = await _run(ctx, "D2", weld)
            out["weld"] = record(expect("E2", done.result, Welded)) if done.ok else done.error
            if done.ok:
                out.update(outcome="welded")
            else:
                out.update(outcome="weld failed", reason=done.error)
        wm.command["phase"] = "home"
        home = GoHome(home=setting(ctx, cmd.home, "home", [500.0, 0.0, 250.0]))
        done = await _run(ctx, "B3", home)
        out["home"] = record(expect("E2", done.result, Reached)) if done.ok else done.error
    except Aborted as exc:
        out.update(outcome="aborted", reason=str(exc))
    wm.command.update(phase="finished", outcome=out)
    ctx.put(out)
    return out
