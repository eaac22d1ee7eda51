"""common - the feedback loop shared by the figure 6.5 tasks: read inputs, act, report up."""

from __future__ import annotations

from typing import Any

from chcos.errors import SensorFailure
from chcos.usrmgr import TaskContext

FAN_IN = 5  # five inputs at level n make one output at level n+1 (thesis 6.4)


async def condense(ctx: TaskContext, actuator: str | None = None, gain: float = 0.5) -> None:
    """Read whichever input has news; drive ``actuator`` proportionally to the newest numeric
    input; every FAN_IN inputs send their mean upward. A failed sensor is reported upward as
    ``("sensor failure", name)`` and the loop goes on with the other inputs."""
    acc: list[float] = []
    while True:
        try:
            port, value = await ctx.read_any()
        except SensorFailure as exc:
            ctx.put(("sensor failure", exc.device))
            ctx.world.sensory[exc.device] = "failed"
            await ctx.sleep(0.1)
            continue
        src = ctx.inputs[port]
        ctx.world.sensory[src] = value
        number = _number(value)
        if number is None:
            continue
        if actuator is not None:
            ctx.write(actuator, max(-100.0, min(100.0, gain * (number - 50.0))))
        acc.append(number)
        if len(acc) >= FAN_IN:
            ctx.put(sum(acc) / len(acc))
            acc.clear()


def _number(value: Any) -> float | None:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    return None
