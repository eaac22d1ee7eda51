"""common - the feedback loop shared by the figure 6.5 tasks: read inputs, act, report up."""

from __future__ import annotations

from typing import Any

from chcos.helpers import is_number
from chcos.user.context import EventKind, TaskContext

FAN_IN = 5  # five inputs at level n make one output at level n+1 (thesis 6.4)


def shutdown_requested(command: Any) -> bool:
    """True for the command that shuts a figure 6.5 task down (``{"op": "shutdown"}``)."""
    return isinstance(command, dict) and command.get("op") == "shutdown"


async def condense(ctx: TaskContext, actuator: str | None = None, gain: float = 0.5) -> Any:
    """Wait for whichever input has news (or a newer command from the owner); drive
    ``actuator`` proportionally to the newest numeric input; every FAN_IN inputs send their
    mean upward. A sensor that fails is reported upward once as ``("sensor failure", name)``
    and the loop goes on with the other inputs. Returns the owner's newer command when it is not
    for this loop (the caller decides), after a shutdown command with ``"shut down"`` (the
    actuator at 0 first)."""
    acc: list[float] = []
    while True:
        ev = await ctx.wait_any(range(len(ctx.inputs)), commands=True)
        if ev.kind is EventKind.COMMAND:
            if shutdown_requested(ev.value):
                if actuator is not None:
                    ctx.write(actuator, 0.0)
                ctx.world.command["state"] = "shut down"
                return "shut down"
            return ev.value
        if ev.kind is EventKind.FAILURE:
            ctx.put(("sensor failure", ev.source))
            ctx.world.sensory[ev.source] = "failed"
            continue
        ctx.world.sensory[ev.source] = ev.value
        number = _number(ev.value)
        if number is None:
            continue
        if actuator is not None:
            ctx.write(actuator, max(-100.0, min(100.0, gain * (number - 50.0))))
        acc.append(number)
        if len(acc) >= FAN_IN:
            ctx.put(sum(acc) / len(acc))
            acc.clear()


def _number(value: Any) -> float | None:
    if is_number(value):
        return float(value)
    return None
