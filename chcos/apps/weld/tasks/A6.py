"""A6 - level 1: stop/memorize position (A6.c).

Command ``{"stop": true}`` drops ``drives_enable`` (the motors stop where they are);
``{"memorize": tag}`` stores the present theta1..theta5 and T5 under ``tag`` in the world model,
where other tasks ask for it (``ctx.ask("A6", "position", tag)``). Completes with the stored
record ``{"tag", "pos", "yaw", "thetas", "t"}``. Raises SensorFailure if a joint sensor has failed.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import as_dict, latest, pose_of
from chcos.errors import MessageError
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task


class MemoryModel(WorldModel):
    """A6's world model: the memorized positions by tag."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``position <tag>``: the record stored under ``tag`` (MessageError if none);
        ``tags``: the stored tags."""
        positions: dict[str, Any] = self.sensory.setdefault("positions", {})
        if topic == "position":
            tag = args[0] if args else "last"
            if tag not in positions:
                raise MessageError(f"A6 has memorized no position {tag!r} "
                                   f"(has: {', '.join(positions) or 'none'})")
            return positions[tag]
        if topic == "tags":
            return list(positions)
        return super().answer(topic, *args)


@task(world_model=MemoryModel)
async def main(ctx: TaskContext, command: Any) -> dict[str, Any]:
    """Stop and/or memorize, then complete with the memorized record."""
    cmd = as_dict(command)
    if cmd.get("stop"):
        ctx.write("drives_enable", 0.0)
    thetas = [float(await latest(ctx, f"theta{j}", timeout=0.1)) for j in range(1, 6)]
    pose = pose_of(thetas)
    record = {"tag": str(cmd.get("memorize", "last")), "pos": pose.position, "yaw": pose.yaw,
              "thetas": thetas, "t": ctx.now, "stopped": bool(cmd.get("stop"))}
    positions: dict[str, Any] = ctx.world.sensory.setdefault("positions", {})
    positions[str(record["tag"])] = record
    positions["last"] = record
    return record
