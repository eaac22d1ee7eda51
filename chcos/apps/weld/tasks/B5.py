"""B5 - level 2: approach target (B5.c); target sighted/not sighted (B5.s).

Centres the tip over the start-of-gap marker with the linear sensor (A7): waits up to 0.5 s for a
sighting, moves sideways by the marker's offset from the image centre, then creeps forward along
the tool yaw until the marker leaves the sensor (which is 5 mm ahead of the tip, and the marker
reaches 6 mm past the gap start), and backs off ``backoff`` mm so the tip stands at the gap
start. Its command is a :class:`chcos.apps.weld.tasks.messages.Approach` (yaw, backoff; console:
``invoke B5 yaw=...``). Completes with an ``Aligned`` (at, yaw). Raises TargetNotSighted if no
marker is seen, MotionFailed if a move fails, MessageError naming B5 and the message for another
message.

B5.s decides from the present and the previous binary image whether the gap-start marker has
been sighted (both show it: one stray image is not a sighting) and puts a ``TargetState``
(target ``sighted``, ``not sighted``, ``passed`` or ``centred``; marker, at, t) upward.
"""

from __future__ import annotations

import math
from typing import Any

from chcos.apps.weld.tasks.common import (
    MotionFailed,
    TargetNotSighted,
    add,
    left,
    sighted,
    tip_pose,
)
from chcos.apps.weld.tasks.messages import Approach, MoveTo, from_host
from chcos.apps.weld.tasks.results import Aligned
from chcos.apps.weld.tasks.sensed import GapImage, TargetState
from chcos.errors import ReadTimeout
from chcos.user.context import TaskContext


async def _move(ctx: TaskContext, p: Any, yaw: float, speed: float) -> None:
    done = await ctx.call("A4", MoveTo(p=p, yaw=yaw, speed=speed))
    if not done.ok:
        raise MotionFailed(f"B5: A4 {done.status.value}: {done.error}")


async def main(ctx: TaskContext, command: Any) -> Aligned:
    """Centre on the start marker."""
    match command:
        case Approach():
            cmd = command
        case None:
            cmd = Approach()
        case _:
            cmd = from_host("B5", command, {"approach": Approach}, "approach", "an Approach")
    backoff = float(ctx.params.get("backoff", 1.5) if cmd.backoff is None else cmd.backoff)
    seen: GapImage | None = None
    previous: object = None
    t0 = ctx.now
    while ctx.now - t0 < 0.5:
        try:
            msg = await ctx.read("A7", timeout=0.5)
        except ReadTimeout:
            break
        match msg:
            case GapImage(start=True) as image if sighted(previous, "start"):
                seen = image
                if image.marker is not None:
                    break
        previous = msg
    if seen is None:
        ctx.put(TargetState("not sighted", None, None, ctx.now))
        raise TargetNotSighted("B5: no start-of-gap marker under the linear sensor (two "
                               "successive images)")
    ctx.put(TargetState("sighted", seen.marker, None, ctx.now))
    here = await tip_pose(ctx, "B5")
    yaw = float(here.yaw if cmd.yaw is None else cmd.yaw)
    ctx.world.sensory["sighted"] = seen
    off = seen.marker
    if off is None:
        off = seen.centre or 0.0
    lx, ly = left(yaw)
    await _move(ctx, add(here.pos, (lx, ly, 0.0), float(off)), yaw, 10.0)
    # creep forward until the marker leaves the sensor
    here = await tip_pose(ctx, "B5")
    fwd = (math.cos(yaw), math.sin(yaw), 0.0)
    await ctx.invoke("A4", MoveTo(p=add(here.pos, fwd, 20.0), yaw=yaw, speed=4.0))
    while True:
        msg = await ctx.read("A7", timeout=6.0)
        if not sighted(msg, "start"):
            break
    here = await tip_pose(ctx, "B5")
    ctx.put(TargetState("passed", None, here.pos, ctx.now))
    await _move(ctx, add(here.pos, fwd, -backoff), yaw, 4.0)
    here = await tip_pose(ctx, "B5")
    result = Aligned(here.pos, yaw)
    ctx.world.sensory["aligned"] = result
    ctx.put(TargetState("centred", None, here.pos, ctx.now))
    return result
