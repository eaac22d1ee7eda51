"""C2 - level 3: find start of gap (C2.c); at start of gap (C2.s).

Puts the linear sensor over the probable start ``start`` ([x, y] mm) with the tool looking along
``heading`` (rad) at height ``z`` (mm), then, unless the start marker is already sighted (A7),
runs a spiral search (pitch ``pitch`` mm, out to ``radius`` mm, at ``speed`` mm/s) until it is;
then B5 centres the tip on it. Completes with ``{"at": pos, "yaw", "searched_mm"}``; raises
SearchFail if the spiral ends without a sighting, MotionFailed if a move fails.
"""

from __future__ import annotations

import math
from typing import Any

from chcos.usrmgr import TaskContext
from chcos.weld.tasks.common import (
    LOOK_AHEAD,
    MotionFailed,
    SearchFail,
    WeldTaskError,
    as_dict,
    param,
    sighted,
)


def spiral(cx: float, cy: float, pitch: float, radius: float, step: float = 2.0) -> list[
        tuple[float, float]]:
    """Points about ``step`` mm apart on an Archimedean spiral around (cx, cy) growing by
    ``pitch`` mm per turn, out to ``radius`` mm."""
    pts: list[tuple[float, float]] = []
    b = pitch / (2.0 * math.pi)
    theta = 1.0 / max(b, 1e-9)
    while b * theta <= radius:
        r = b * theta
        pts.append((cx + r * math.cos(theta), cy + r * math.sin(theta)))
        theta += step / max(r, step)
    return pts


async def main(ctx: TaskContext, command: Any) -> dict[str, Any]:
    """Find and centre on the start-of-gap marker."""
    cmd = as_dict(command)
    sx, sy = (float(v) for v in param(ctx, cmd, "start", [542.0, -164.0]))
    heading = float(param(ctx, cmd, "heading", math.pi / 2))
    z = float(param(ctx, cmd, "z", 10.0))
    speed = float(param(ctx, cmd, "speed", 20.0))
    pitch = float(param(ctx, cmd, "pitch", 6.0))
    radius = float(param(ctx, cmd, "radius", 30.0))
    ux, uy = math.cos(heading), math.sin(heading)

    def tip_for(px: float, py: float) -> list[float]:
        return [px - LOOK_AHEAD * ux, py - LOOK_AHEAD * uy, z]

    wm = ctx.world
    wm.command.update(phase="approach", start=[sx, sy])
    done = await ctx.call("A4", {"op": "move", "p": tip_for(sx, sy), "yaw": heading,
                                 "speed": float(param(ctx, cmd, "travel", 100.0))})
    if not done.ok:
        raise MotionFailed(f"C2: cannot reach the probable start {[sx, sy]}: {done.error}")
    await ctx.sleep(0.05)
    searched = 0.0
    if not sighted(ctx.poll("A7"), "start"):
        wm.command["phase"] = "spiral"
        found = False
        prev = (sx, sy)
        for px, py in spiral(sx, sy, pitch, radius):
            await ctx.call("A4", {"op": "move", "p": tip_for(px, py), "yaw": heading,
                                  "speed": speed})
            searched += math.hypot(px - prev[0], py - prev[1])
            prev = (px, py)
            if sighted(ctx.poll("A7"), "start"):
                found = True
                break
        if not found:
            wm.command["phase"] = "failed"
            raise SearchFail(f"C2: search fail: no start-of-gap marker within {radius} mm of "
                             f"({sx:.1f}, {sy:.1f}) after {searched:.0f} mm of spiral")
    wm.command["phase"] = "align"
    aligned = await ctx.call("B5", {"yaw": heading})
    if not aligned.ok:
        raise WeldTaskError(f"C2: B5 could not align on the target: {aligned.error}")
    wm.command["phase"] = "at start"
    result = {"at": aligned.result["at"], "yaw": aligned.result["yaw"], "searched_mm": searched}
    wm.sensory["found"] = result
    return result
