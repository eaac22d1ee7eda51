"""C1 - level 3, the top of figure 6.5: commands B1, B2 and the terminal/log driver A4.

Started by the host (``invoke C1``). Lines typed on the terminal come up through A4: ``stop``
releases B1 and B2 (the A tasks are then released in turn) and completes; ``shutdown`` is the
exceptional situation of section 6.1.5: C1's priority-9 command to B1 makes B1 take every A-level
task and shut it down; anything else is written to the log through A4.
"""

from typing import Any

from chcos.user.context import TaskContext


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
            if value == "shutdown":
                await ctx.invoke("A4", "operator: shutdown - B1 takes the A level down")
                done = await ctx.call("B1", {"mode": "shutdown"})
                ctx.world.command["shutdown"] = done.result if done.ok else done.error
                await ctx.invoke("A4", f"A level shut down: {ctx.world.command['shutdown']}")
                continue
            await ctx.invoke("A4", f"operator: {value}")
        else:
            reports += 1
            ctx.world.sensory[src] = value
