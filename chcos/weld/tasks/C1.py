"""C1 - level 3: unstick tip (C1.c); tip stuck/free (C1.s).

``{"op": "watch"}`` (the sensory part, run while D2 welds): reads the arc temperature (A1), the arc
voltage and current (A2) and the tip position (A4). The tip is stuck when, with the voltage on,
the arc voltage has collapsed (below 2 V) with a short-circuit current (over 200 A), or the tip
has not moved for 0.5 s although a motion is commanded while the temperature falls. Reports
``{"tip": "stuck" | "free", "since"}`` on every change.

``{"op": "idle"}`` stops watching. ``{"op": "unstick"}``: stop the motors and memorize the
position (A6), turn the voltage off (A2), move the tip ``lift`` mm (default 10) straight up,
90 degrees away from the gap (A4), and check that it moved. Completes with ``{"freed": true,
"memorized": record, "lift"}``; raises TipStillStuck if the tip did not come free,
MotionFailed if a lower task failed.
"""

from __future__ import annotations

from typing import Any

from chcos.usrmgr import TaskContext
from chcos.weld.tasks.common import (
    MotionFailed,
    TipStillStuck,
    as_dict,
    dist,
    latest,
    param,
)


async def main(ctx: TaskContext, command: Any) -> Any:
    """Watch for a stuck tip, or free it."""
    cmd = as_dict(command)
    if cmd.get("op") == "unstick":
        return await _unstick(ctx, float(param(ctx, cmd, "lift", 10.0)))
    if cmd.get("op") == "idle":
        return "idle"
    await _watch(ctx)
    return None


async def _watch(ctx: TaskContext) -> None:
    wm = ctx.world
    ctx.complete("watching")
    state = "free"
    short_since: float | None = None
    still_since: float | None = None
    last_pos: Any = None
    temps: list[float] = []
    while True:
        port, msg = await ctx.read_any(["A1", "A2", "A4"])
        src = ctx.inputs[port]
        if not isinstance(msg, dict) or "fail" in msg:
            continue
        now = ctx.now
        if src == "A2":
            shorted = msg["set"] > 0.0 and msg["volts"] < 2.0 and msg["amps"] > 200.0
            short_since = (short_since if short_since is not None else now) if shorted else None
        elif src == "A1":
            temps = [*temps[-24:], float(msg["temp"])]
        elif src == "A4":
            pos = msg["pos"]
            if msg["moving"] and last_pos is not None and dist(pos, last_pos) < 0.01:
                still_since = still_since if still_since is not None else now
            else:
                still_since = None
            last_pos = pos
        cooling = len(temps) >= 25 and temps[-1] < temps[0] - 30.0
        stuck = ((short_since is not None and now - short_since >= 0.1)
                 or (still_since is not None and now - still_since >= 0.5 and cooling))
        new = "stuck" if stuck else "free"
        if new != state:
            state = new
            wm.sensory.update(tip=state, since=now)
            ctx.put({"tip": state, "since": now})


async def _unstick(ctx: TaskContext, lift: float) -> dict[str, Any]:
    wm = ctx.world
    wm.command["unstick"] = "stopping"
    mem = await ctx.call("A6", {"stop": True, "memorize": "stuck"})
    if not mem.ok:
        raise MotionFailed(f"C1: A6 could not stop/memorize: {mem.error}")
    off = await ctx.call("A2", {"volts": 0.0})
    if not off.ok:
        raise MotionFailed(f"C1: A2 could not turn the voltage off: {off.error}")
    record = await ctx.ask("A6", "position", "stuck")
    p0 = record["pos"]
    wm.command["unstick"] = "lifting"
    up = await ctx.call("A4", {"op": "move", "p": [p0[0], p0[1], p0[2] + lift],
                               "yaw": record["yaw"], "speed": 10.0})
    here = await latest(ctx, "A4")
    if not up.ok or here["pos"][2] - p0[2] < 0.8 * lift:
        raise TipStillStuck(f"C1: tip still stuck at {p0} after the lift "
                            f"({up.status.value} {up.error})")
    wm.command["unstick"] = "freed"
    wm.sensory.update(tip="free", since=ctx.now)
    return {"freed": True, "memorized": record, "lift": lift}
