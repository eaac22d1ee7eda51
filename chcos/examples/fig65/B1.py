"""B1 - level 2: commands A1, A2 and A3, condenses A1 and A2 for C1 (figure 6.5).

Invoked by C1 at high priority (``setpri -9 C1 B1``), it takes over the A-level tasks: its own
invocations of A1, A2 and A3 run at the B1 links' priorities and pre-empt lower owners.
"""

from typing import Any

from chcos.examples.fig65.common import condense
from chcos.usrmgr import TaskContext


async def main(ctx: TaskContext, command: Any) -> None:
    """Invoke the A tasks, then condense their reports upward."""
    for task in ("A1", "A2", "A3"):
        await ctx.invoke(task, {"by": ctx.name}, wait=False)
    await condense(ctx)
