"""B3 - level 2: go home (B3.c): place the tip in the home position.

Its command is a :class:`chcos.apps.weld.tasks.messages.GoHome` (console: ``invoke B3
home=[x,y,z] speed=...``). Moves (A4) to ``home`` (command or install parameter, default [500, 0,
250] mm, yaw 0) at ``speed`` (default 100 mm/s) and completes with A4's ``Reached``. Raises
MotionFailed if A4 does not get there, MessageError naming B3 and the message for another
message.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import MotionFailed
from chcos.apps.weld.tasks.messages import GoHome, MoveTo, expect, from_host
from chcos.apps.weld.tasks.results import Reached
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> Reached:
    """Go home."""
    match command:
        case GoHome():
            cmd = command
        case None:
            cmd = GoHome()
        case _:
            cmd = from_host("B3", command, {"home": GoHome}, "home", "a GoHome")
    home = [float(v) for v in (ctx.params.get("home", [500.0, 0.0, 250.0]) if cmd.home is None
                               else cmd.home)]
    speed = float(ctx.params.get("speed", 100.0) if cmd.speed is None else cmd.speed)
    done = await ctx.call("A4", MoveTo(p=home, yaw=0.0, speed=speed))
    if not done.ok:
        raise MotionFailed(f"B3: going home to {home}: A4 {done.status.value}: {done.error}")
    return expect("B3", done.result, Reached)
