"""B1 - level 2: commands A1, A2 and A3, condenses A1 and A2 for C1 (figure 6.5).

Invoked by C1 (``setpri -9 C1 B1``: C1's command makes B1 run at priority 9). In ``run`` mode it
invokes A1, A2 and A3 without waiting; a task held at an equal or higher priority answers "busy"
at once, which B1 notes in its world model before it goes on condensing their reports. C1's
``{"mode": "shutdown"}`` is the exceptional situation of section 6.1.5: "B1 should therefore take
control of all A-level tasks and perhaps shut them down". C1's command makes B1 run at priority
9, and B1 passes that urgency down (``invoke(..., priority=ctx.priority)``): it takes each A task
from whoever holds it at a lower priority, sends it ``{"op": "shutdown"}`` (actuators to 0, the
loop ends) and completes with what each answered.
"""

from typing import Any

from chcos.apps.fig65.common import condense
from chcos.errors import Busy
from chcos.user.context import TaskContext

A_TASKS = ("A1", "A2", "A3")


async def main(ctx: TaskContext, command: Any) -> Any:
    """Run (invoke the A tasks, condense their reports), or shut the A level down."""
    while True:
        if isinstance(command, dict) and command.get("mode") == "shutdown":
            return await _shutdown(ctx)
        for task in A_TASKS:
            try:
                await ctx.invoke(task, {"by": ctx.name}, wait=False)
                ctx.world.command[task] = "owned"
            except Busy as exc:
                ctx.world.command[task] = f"busy: {exc}"
        command = await condense(ctx)


async def _shutdown(ctx: TaskContext) -> dict[str, str]:
    answers: dict[str, str] = {}
    for task in A_TASKS:
        await ctx.invoke(task, {"op": "shutdown", "by": ctx.name}, priority=ctx.priority)
    for task in A_TASKS:
        done = await ctx.done(task)
        answers[task] = f"{done.status.value}: {done.result if done.ok else done.error}"
    ctx.world.command.update(state="A level shut down", answers=answers)
    ctx.put({"shutdown": answers})
    return answers
