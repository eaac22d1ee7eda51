"""B2 - level 2: reads A2 and A3 and commands A3 (figure 6.5).

A3 is also commanded by B1; whichever link has the higher priority owns it. B2 asks without
waiting (topen's immediate "busy" answer) and goes on condensing A2 and A3 either way, since A3's
sensory messages reach it whoever owns A3.
"""

from typing import Any

from chcos.apps.fig65.common import condense
from chcos.errors import Busy
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> None:
    """Try to take A3, then condense A2 and A3 upward."""
    try:
        await ctx.invoke("A3", {"by": ctx.name}, wait=False)
        ctx.world.command["A3"] = "owned"
    except Busy as exc:
        ctx.world.command["A3"] = f"busy: {exc}"
    while True:
        await condense(ctx)
