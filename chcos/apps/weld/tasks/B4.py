"""B4 - level 2: move 5 mm in direction d at speed s (B4.c).

Its command is a :data:`chcos.apps.weld.tasks.messages.StepCommand` (console: ``op=step d=[...]
dist=... speed=... yaw=...``, ``op=hold``). ``Step``: reads the present T5 from A4, translates it
by ``dist`` (default 5) mm along ``d`` (a 3-vector, normalised) and moves there (A4
``MoveTo``) at ``speed`` mm/s with tool yaw ``yaw`` (default: unchanged). ``HoldMotion()``
stops the motion where it is. Completes with A4's answer (a ``Stepped``: A4's status and
result). A newer command from the same owner while a move is under way (a repeated topen: no
new activation) replaces the move: B4 waits for A4's completion or its owner's next command,
whichever comes first, and passes the new move to A4 (segments join smoothly). Raises
MotionFailed if A4 fails, MessageError naming B4 and the message for anything but a
StepCommand.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import MotionFailed, add, tip_pose, unit
from chcos.apps.weld.tasks.messages import HoldMotion, MoveTo, Step, StepCommand, from_host
from chcos.apps.weld.tasks.results import Reached, Stepped
from chcos.tables.messages import Completion, LinkStatus
from chcos.user.context import TaskContext

STEPS: dict[str, type[StepCommand]] = {"step": Step, "hold": HoldMotion}
"""B4's commands by the ``op`` a console command names."""


def step_command(command: object) -> StepCommand:
    """B4's command as a :data:`StepCommand` (no command: a ``Step`` of the defaults, a console
    dict converted by :func:`from_host`). Raises MessageError naming B4 and the message for
    anything else."""
    match command:
        case Step() | HoldMotion():
            return command
        case None:
            return Step()
        case _:
            return from_host("B4", command, STEPS, "step", "a Step or HoldMotion")


async def _order(ctx: TaskContext, command: object) -> None:
    """Send A4 the motion ``command`` asks for."""
    match step_command(command):
        case HoldMotion() as hold:
            await ctx.invoke("A4", hold)
        case Step(d=d, dist=dist, speed=speed, yaw=yaw):
            here = await tip_pose(ctx, "B4")
            p = add(here.pos, unit([float(c) for c in d]), float(dist))
            await ctx.invoke("A4", MoveTo(p=p, speed=float(speed),
                                          yaw=float(here.yaw if yaw is None else yaw)))


async def main(ctx: TaskContext, command: Any) -> Stepped:
    """One 5 mm move (or a hold), redirected by every newer command of the owner."""
    await _order(ctx, command)
    while True:
        ev = await ctx.wait_any(completions=["A4"], commands=True)
        if ev.kind == "command":
            await _order(ctx, ev.value)
            continue
        done: Completion = ev.value
        break
    if done.status is LinkStatus.ABNORMAL:
        raise MotionFailed(f"B4: A4 failed: {done.error}")
    match done.result:
        case Reached() | None as result:
            return Stepped(done.status.value, result)
        case other:
            raise MotionFailed(f"B4: A4 completed with {other!r}, expected a Reached")
