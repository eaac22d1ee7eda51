"""A6 - level 1: stop/memorize position (A6.c), and the joint drives' power.

A6 owns the joint drives, CiA 402 axes ``joint1``..``joint5``, and the safe-torque-off relay
``drives_enable``. Its command is a :class:`chcos.apps.weld.tasks.messages.DrivesCommand`:

* ``stop`` - quick-stop the joint drives (each decelerates; the stop is confirmed by the drive's
  statusword; a drive already in its safe stop after an e-stop joins it) and drop the relay;
* ``enable`` - switch the relay on, then put each drive in cyclic synchronous position and
  enable it (confirmed by its statusword): the joints follow the targets A4 streams;
* ``memorize`` tag - store the present theta1..theta5 and T5 under ``tag`` in the world model,
  where other tasks ask for it (``ctx.ask("A6", "position", tag)``).

No command (None) memorizes under ``last``. Completes with the stored record, a
:class:`chcos.apps.weld.tasks.results.Memorized` (tag, pos, yaw, thetas, t, stopped, drives:
each drive's state after a stop or an enable). Raises MessageError for a command of another
type, SensorFailure if a joint sensor has failed, ServoFailure naming a drive that did not stop
or enable (the relay is then off). While A6 runs it owns the axes: its abnormal completion runs
their safe stop (quick stop, then disable voltage).
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import (
    AXES,
    enable_joints,
    latest,
    pose_of,
    quick_stop_joints,
)
from chcos.apps.weld.tasks.messages import DrivesCommand, refused
from chcos.apps.weld.tasks.results import Memorized
from chcos.errors import MessageError
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task


class MemoryModel(WorldModel):
    """A6's world model: the memorized positions by tag."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``position <tag>``: the record stored under ``tag`` (MessageError if none);
        ``tags``: the stored tags."""
        positions: dict[str, Memorized] = self.sensory.setdefault("positions", {})
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
async def main(ctx: TaskContext, command: Any) -> Memorized:
    """Stop, enable and/or memorize, then complete with the memorized record."""
    match command:
        case DrivesCommand():
            cmd = command
        case None:
            cmd = DrivesCommand()
        case _:
            raise refused("A6", command, "a DrivesCommand (stop, enable, memorize)")
    drives: dict[str, str] = {}
    if cmd.stop:
        drives = await quick_stop_joints(ctx, "A6")
    if cmd.enable:
        await enable_joints(ctx, "A6")
        drives = {name: str(getattr(ctx.axis(name).state, "name", "unknown")) for name in AXES}
    thetas = [float(await latest(ctx, f"theta{j}", timeout=0.1)) for j in range(1, 6)]
    pose = pose_of(thetas)
    record = Memorized(tag=cmd.memorize or "last", pos=pose.position, yaw=pose.yaw,
                       thetas=thetas, t=ctx.now, stopped=cmd.stop, drives=drives)
    if cmd.memorize is not None:
        positions: dict[str, Memorized] = ctx.world.sensory.setdefault("positions", {})
        positions[cmd.memorize] = record
        positions["last"] = record
    return record
