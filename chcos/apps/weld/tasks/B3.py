"""B3 - level 2: go home (B3.c): place the tip in the home position.

Moves (A4) to ``home`` (install parameter or command, default [500, 0, 250] mm, yaw 0) at
``speed`` (default 100 mm/s) and completes with the pose reached. Raises MotionFailed if A4 does
not get there.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import MotionFailed, as_dict, param
from chcos.apps.weld.tasks.messages import MoveTo
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> Any:
    """Go home."""
    cmd = as_dict(command)
    home = [float(v) for v in param(ctx, cmd, "home", [500.0, 0.0, 250.0])]
    speed = float(param(ctx, cmd, "speed", 100.0))
    done = await ctx.call("A4", MoveTo(p=home, yaw=0.0, speed=speed))
    if not done.ok:
        raise MotionFailed(f"B3: going home to {home}: A4 {done.status.value}: {done.error}")
    return done.result
