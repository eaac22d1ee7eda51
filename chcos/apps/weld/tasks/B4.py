"""B4 - level 2: move 5 mm in direction d at speed s (B4.c).

Reads the present T5 from A4, translates it by ``dist`` (default 5) mm along ``d`` (a 3-vector,
normalised) and moves there (A4) at ``speed`` mm/s with tool yaw ``yaw`` (default: unchanged).
``{"op": "hold"}`` stops the motion where it is. Completes with A4's answer. A newer command from
the same owner while a move is under way (a repeated topen: no new activation) replaces the move:
B4 waits for A4's completion or its owner's next command, whichever comes first, and passes the
new move to A4 (segments join smoothly). Raises MotionFailed if A4 fails.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import MotionFailed, add, as_dict, latest, unit
from chcos.tables.messages import Completion, LinkStatus
from chcos.user.context import TaskContext


async def _order(ctx: TaskContext, command: Any) -> None:
    """Send A4 the motion ``command`` asks for."""
    cmd = as_dict(command)
    if cmd.get("op") == "hold":
        await ctx.invoke("A4", {"op": "hold"})
        return
    here = await latest(ctx, "A4")
    d = unit([float(c) for c in cmd.get("d", (0.0, 0.0, 0.0))])
    p = add(here["pos"], d, float(cmd.get("dist", 5.0)))
    await ctx.invoke("A4", {"op": "move", "p": p, "speed": float(cmd.get("speed", 5.0)),
                            "yaw": float(cmd.get("yaw", here["yaw"]))})


async def main(ctx: TaskContext, command: Any) -> Any:
    """One 5 mm move (or a hold), redirected by every newer command of the owner."""
    await _order(ctx, command)
    while True:
        ev = await ctx.wait_any(completions=["A4"], commands=True)
        if ev.kind == "command":
            await _order(ctx, ev.value)
            continue
        done: Completion = ev.value
        break
    if done.status is LinkStatus.ABNORMAL:
        raise MotionFailed(f"B4: A4 failed: {done.error}")
    return {"status": done.status.value, "result": done.result}
