"""A5 - level 1: advance/retard the electrode (wire) speed (A5.c); electrode speed (A5.s).

Command ``{"speed": mm/s}`` sets the wire feed, ``{"step": mm/s}`` advances (positive) or
retards (negative) it; either is completed at once. The loop reads ``wire_speed`` (20 Hz) and
sends ``{"wire", "set"}`` upward; a failed sensor is reported as ``{"fail": "wire_speed"}``.
"""

from __future__ import annotations

from typing import Any

from chcos.errors import SensorFailure
from chcos.usrmgr import TaskContext
from chcos.weld.tasks.common import as_dict, await_recovery, clear_failure, report_failure

WIRE_MAX = 250.0


async def main(ctx: TaskContext, command: Any) -> None:
    """Set and report the electrode speed."""
    cmd = as_dict(command)
    wm = ctx.world
    speed = float(wm.command.get("speed", 0.0))
    if "speed" in cmd:
        speed = float(cmd["speed"])
    if "step" in cmd:
        speed += float(cmd["step"])
    if "speed" in cmd or "step" in cmd:
        speed = max(0.0, min(WIRE_MAX, speed))
        wm.command["speed"] = speed
        ctx.write("wire_set", speed)
    ctx.complete({"speed": speed})
    while True:
        try:
            wire = float(await ctx.read("wire_speed"))
        except SensorFailure as exc:
            report_failure(ctx, exc)
            await await_recovery(ctx, exc)
            continue
        clear_failure(ctx, "wire_speed")
        wm.sensory["wire"] = wire
        ctx.put({"wire": wire, "set": wm.command.get("speed", 0.0)})
