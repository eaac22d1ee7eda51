"""C1 - level 3, the top of figure 6.5: commands B1, B2 and the terminal/log driver A4.

Started by the host (``invoke C1``). Lines typed on the terminal come up through A4: ``stop``
releases B1 and B2 (the A tasks are then released in turn), anything else is logged.
"""

from typing import Any

from chcos.usrmgr import TaskContext


async def main(ctx: TaskContext, command: Any) -> int:
    """Run the system until the operator types ``stop``; completes with the reports seen."""
    await ctx.invoke("A4", "C1 started")
    await ctx.invoke("B1", {"mode": "run"})
    await ctx.invoke("B2", {"mode": "run"}, wait=False)
    reports = 0
    while True:
        port, value = await ctx.read_any()
        src = ctx.inputs[port]
        if src == "A4":
            if value == "stop":
                ctx.close("B1")
                ctx.close("B2")
                return reports
            await ctx.invoke("A4", f"operator: {value}")
        else:
            reports += 1
            ctx.world.sensory[src] = value
