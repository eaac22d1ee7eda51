"""E1 - level 5: stop / assassin (E1.c), role ``assassin``.

Waits for an alarm (:class:`chcos.apps.weld.tasks.messages.Alarm`) from the exception task D3.
On one, at top priority: e-stop (every actuator
with a safe value gets it at once: the relay drives_enable off, voltage, wire and gas to 0, and
each joint drive's safe stop: quick stop, then disable voltage once it stands), suspend the command
tasks that could command motion or the arc again (D1, D2, C1, C2, B1, B3, B4, B5), then call B2
to stop the motors, voltage and gas through the level-1 tasks (so none of them re-applies an old
set-point) and A6 to memorize the position. Each reaction is kept in the world model
(``reactions``: alarm, time seen, actuators written, B2's and A6's answers) and E1 stays armed.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.messages import Alarm, DrivesCommand, expect
from chcos.apps.weld.tasks.results import Memorized, Stopped
from chcos.errors import MessageError
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task

FREEZE = ("D1", "D2", "C1", "C2", "B1", "B3", "B4", "B5")


class AssassinModel(WorldModel):
    """E1's world model: the reactions so far."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``reactions``: every alarm handled, oldest first."""
        if topic == "reactions":
            return list(self.sensory.get("reactions", []))
        return super().answer(topic, *args)


@task(world_model=AssassinModel)
async def main(ctx: TaskContext, command: Any) -> None:
    """Stay armed; react to every alarm."""
    ctx.complete("armed")
    wm = ctx.world
    reactions: list[dict[str, Any]] = wm.sensory.setdefault("reactions", [])
    while True:
        alarm = await ctx.read("D3")
        if not isinstance(alarm, Alarm):    # D3 reports nothing else, but only an alarm stops
            continue
        seen = ctx.now
        written = ctx.estop(f"{alarm.kind}: {alarm.detail}")
        frozen = []
        for name in FREEZE:
            try:
                ctx.suspend_task(name)
                frozen.append(name)
            except MessageError:
                continue
        record: dict[str, Any] = {"alarm": alarm.kind, "detail": alarm.detail,
                                  "raised": alarm.t, "seen": seen,
                                  "estop_writes": written, "suspended": frozen}
        reactions.append(record)
        stop = await ctx.call("B2")
        record["b2"] = (dict(expect("E1", stop.result, Stopped).answers) if stop.ok
                        else f"{stop.status.value}: {stop.error}")
        mem = await ctx.call("A6", DrivesCommand(memorize="alarm"))
        record["position"] = (expect("E1", mem.result, Memorized).pos if mem.ok
                              else f"{mem.status.value}: {mem.error}")
        record["done"] = ctx.now
