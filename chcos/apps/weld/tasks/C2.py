"""C2 - level 3: find start of gap (C2.c); at start of gap (C2.s).

Puts the linear sensor over the probable start ``start`` ([x, y] mm) with the tool looking along
``heading`` (rad) at height ``z`` (mm), then, unless the start marker is already sighted (A7),
searches for it with its world model's plans (``chcos.user.plans.Plans``): first a spiral
(pitch ``pitch`` mm, out to ``radius`` mm, at ``speed`` mm/s), and if that finds nothing a wider
raster (lines along the heading ``raster_length`` mm long, ``raster_step`` mm apart, out to
``raster_radius`` mm to either side). The plans' outcomes are learned across runs (beside the
system's map, ``learned/C2.json``), so a plan that kept failing is tried after one that worked.
Then B5 centres the tip on the marker.

C2.s puts a ``GapStartState`` (gap ``start``, ``searching`` or ``not found``; plan, at, t)
upward: where the tip is with respect to the start of the gap. Completes with a ``StartFound``
(at, yaw, searched_mm, plan); raises SearchFail if every plan ends without a sighting, MotionFailed
if a move fails.
"""

from __future__ import annotations

import math
from typing import Any

from chcos.apps.weld.tasks.common import (
    LOOK_AHEAD,
    MotionFailed,
    SearchFail,
    WeldTaskError,
    setting,
    sighted,
)
from chcos.apps.weld.tasks.messages import Approach, FindStart, MoveTo, expect, from_host
from chcos.apps.weld.tasks.results import Aligned, StartFound
from chcos.apps.weld.tasks.sensed import GapStartState
from chcos.user.context import TaskContext
from chcos.user.knowledge import Experience, Store
from chcos.user.plans import Plan, Plans, PlansExhausted


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


def raster(cx: float, cy: float, heading: float, radius: float, length: float, spacing: float,
           step: float = 2.0) -> list[tuple[float, float]]:
    """Points about ``step`` mm apart on a serpentine raster around (cx, cy): lines along
    ``heading``, ``length`` mm long (centred on the point), ``spacing`` mm apart, from
    ``radius`` mm to the right of the heading to ``radius`` mm to its left."""
    ux, uy = math.cos(heading), math.sin(heading)
    lx, ly = -uy, ux
    n_lines = math.floor(radius / spacing)
    offsets = [k * spacing for k in range(-n_lines, n_lines + 1)]
    n_pts = max(1, math.ceil(length / step))
    pts: list[tuple[float, float]] = []
    for i, off in enumerate(offsets):
        along = [-length / 2.0 + length * j / n_pts for j in range(n_pts + 1)]
        if i % 2:
            along.reverse()
        pts.extend((cx + off * lx + a * ux, cy + off * ly + a * uy) for a in along)
    return pts


async def main(ctx: TaskContext, command: Any) -> StartFound:
    """Find and centre on the start-of-gap marker."""
    match command:
        case FindStart():
            cmd = command
        case None:
            cmd = FindStart()
        case _:
            cmd = from_host("C2", command, {"find": FindStart}, "find", "a FindStart")
    sx, sy = (float(v) for v in setting(ctx, cmd.start, "start", [542.0, -164.0]))
    heading = float(setting(ctx, cmd.heading, "heading", math.pi / 2))
    z = float(setting(ctx, cmd.z, "z", 10.0))
    speed = float(setting(ctx, cmd.speed, "speed", 20.0))
    pitch = float(setting(ctx, cmd.pitch, "pitch", 6.0))
    radius = float(setting(ctx, cmd.radius, "radius", 30.0))
    r_radius = float(setting(ctx, cmd.raster_radius, "raster_radius", 60.0))
    r_length = float(setting(ctx, cmd.raster_length, "raster_length", 40.0))
    r_step = float(setting(ctx, cmd.raster_step, "raster_step", 14.0))
    ux, uy = math.cos(heading), math.sin(heading)

    def tip_for(px: float, py: float) -> list[float]:
        return [px - LOOK_AHEAD * ux, py - LOOK_AHEAD * uy, z]

    wm = ctx.world
    wm.command.update(phase="approach", start=[sx, sy])
    done = await ctx.call("A4", MoveTo(p=tip_for(sx, sy), yaw=heading,
                                       speed=float(setting(ctx, cmd.travel, "travel", 100.0))))
    if not done.ok:
        raise MotionFailed(f"C2: cannot reach the probable start {[sx, sy]}: {done.error}")
    await ctx.sleep(0.05)
    searched = [0.0]

    def search(name: str, points: list[tuple[float, float]], extent: str) -> Plan:
        async def run() -> None:
            wm.command["phase"] = name
            ctx.put(GapStartState("searching", name, [sx, sy], ctx.now))
            prev = (sx, sy)
            for px, py in points:
                moved = await ctx.call("A4", MoveTo(p=tip_for(px, py), yaw=heading,
                                                    speed=speed))
                if not moved.ok:
                    raise MotionFailed(f"C2: {name} move failed: {moved.error}")
                searched[0] += math.hypot(px - prev[0], py - prev[1])
                prev = (px, py)
                if sighted(ctx.poll("A7"), "start"):
                    return
            raise SearchFail(f"C2: {name}: no start-of-gap marker {extent} of "
                             f"({sx:.1f}, {sy:.1f})")
        return Plan(name, run)

    plan = "none"
    if not sighted(ctx.poll("A7"), "start"):
        plans = Plans("find start of gap", [
            search("spiral", spiral(sx, sy, pitch, radius), f"within {radius:g} mm"),
            search("raster", raster(sx, sy, heading, r_radius, r_length, r_step),
                   f"within {r_radius:g} mm to either side")],
            Experience(Store.beside(ctx.state_dir, ctx.name)))
        try:
            plan, _ = await plans.attempt(wm)
        except PlansExhausted as exc:
            wm.command["phase"] = "failed"
            ctx.put(GapStartState("not found", None, [sx, sy], ctx.now))
            raise SearchFail(f"C2: search fail after {searched[0]:.0f} mm: {exc}") from exc
    wm.command["phase"] = "align"
    aligned = await ctx.call("B5", Approach(yaw=heading))
    if not aligned.ok:
        raise WeldTaskError(f"C2: B5 could not align on the target: {aligned.error}")
    wm.command["phase"] = "at start"
    at = expect("C2", aligned.result, Aligned)
    result = StartFound(at=at.at, yaw=at.yaw, searched_mm=searched[0], plan=plan)
    wm.sensory["found"] = result
    ctx.put(GapStartState("start", plan, result.at, ctx.now))
    return result
