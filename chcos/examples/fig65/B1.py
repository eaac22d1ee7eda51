"""B1 - level 2: commands A1, A2 and A3, condenses A1 and A2 for C1 (figure 6.5).

Invoked by C1 at high priority (``setpri -9 C1 B1``), it takes over the A-level tasks: its own
invocations of A1, A2 and A3 run at the B1 links' priorities and pre-empt lower owners. A task
held at an equal or higher priority (A3 may already serve B2) answers "busy" at once; B1 notes it
in its world model and goes on with the others.
"""

from typing import Any

from chcos.errors import Busy
from chcos.examples.fig65.common import condense
from chcos.usrmgr import TaskContext


async def main(ctx: TaskContext, command: Any) -> None:
    """Invoke the A tasks, then condense their reports upward."""
    for task in ("A1", "A2", "A3"):
        try:
            await ctx.invoke(task, {"by": ctx.name}, wait=False)
            ctx.world.command[task] = "owned"
        except Busy as exc:
            ctx.world.command[task] = f"busy: {exc}"
    await condense(ctx)
