"""A4 - level 1: move to position p at speed s (A4.c); position of T5 (A4.s).

At every sample of the joint sensors (100 Hz: theta1 paces the loop) A4 reads theta1..theta5,
derives T5 by forward kinematics and sends a :class:`~chcos.apps.weld.tasks.sensed.TipPose`
(pos [x, y, z], yaw, moving, t) upward.
Commands (:data:`chcos.apps.weld.tasks.messages.MotionCommand`; from the console, ``invoke A4
op=move p=[x,y,z] speed=... yaw=...``, ``op=hold``...):

* ``MoveTo(p=[x, y, z], speed=mm/s, yaw=rad)`` - a commanded point advances
  along the straight line to ``p`` by ``speed * dt`` each cycle (so the speed is regulated; the
  next position is always within the thesis' 100 ms horizon) and the joint targets come from
  inverse kinematics; completes with ``Reached(at=pos)`` when the tip is within 0.3 mm of ``p``. A
  newer move continues from the commanded point of the last one, so segments join smoothly.
* ``HoldMotion()`` - keep the joints where they are; ``StopMotion()`` - also drop
  ``drives_enable`` (safe torque off); ``Monitor()`` or no command - just report; these
  complete at once with ``Reached(at=pos, op="hold" | "stop" | "monitor")``.

A newer command from the same owner while a move is under way (a repeated topen) is taken up in
the next cycle, without a new activation. Raises ServoFailure (after dropping the drives) when a
joint sensor fails, MotionFailed when the position cannot be reached (inverse kinematics) or the
tip stalls for 2 s, MessageError naming A4 and the message for anything but a motion command.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal, NoReturn

from chcos.apps.weld.kinematics import UnreachableError, wrap_angle
from chcos.apps.weld.tasks.common import (
    ARM,
    MotionFailed,
    ServoFailure,
    dist,
    latest,
    pose_of,
    report_failure,
)
from chcos.apps.weld.tasks.messages import (
    HoldMotion,
    Monitor,
    MotionCommand,
    MoveTo,
    StopMotion,
    from_host,
)
from chcos.apps.weld.tasks.results import Reached
from chcos.apps.weld.tasks.sensed import TipPose
from chcos.errors import SensorFailure
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task

JOINTS = tuple(f"theta{j}" for j in range(1, 6))
TARGETS = tuple(f"target{j}" for j in range(1, 6))
REACHED_MM = 0.3
STALL_S = 2.0
YAW_RATE = 2.0

MOTIONS: dict[str, type[MotionCommand]] = {
    "move": MoveTo, "hold": HoldMotion, "stop": StopMotion, "monitor": Monitor}
"""A4's commands by the ``op`` a console command names."""


class PositionModel(WorldModel):
    """A4's world model: the pose (T5) now, and the motion being executed."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``pos``/``yaw``/``moving`` as last seen; anything else as the base model."""
        if topic == "moving":
            return bool(self.command.get("moving", False))
        return super().answer(topic, *args)


async def _thetas(ctx: TaskContext) -> list[float]:
    return [float(await latest(ctx, j, timeout=0.1)) for j in JOINTS]


async def _next_thetas(ctx: TaskContext) -> list[float]:
    """Wait for the next sample of the joints (theta1 paces the loop), then take them all."""
    first = float(await ctx.read(JOINTS[0], timeout=0.1))
    ctx.world.sensory[f"last:{JOINTS[0]}"] = first
    return [first, *[float(await latest(ctx, j, timeout=0.1)) for j in JOINTS[1:]]]


def _command(ctx: TaskContext, command: Any, thetas: list[float],
             pose: Any) -> tuple[tuple[float, float, float] | None, float, float]:
    """Take up one motion command; returns (goal or None, yaw goal, speed)."""
    cmd = motion_command(command)
    wm = ctx.world
    pos = pose.position
    if isinstance(cmd, MoveTo):
        goal = (float(cmd.p[0]), float(cmd.p[1]), float(cmd.p[2]))
        yaw_goal = float(pose.yaw if cmd.yaw is None else cmd.yaw)
        speed = float(cmd.speed)
        if speed <= 0:
            raise MotionFailed(f"A4: move to {goal} at speed {speed} mm/s: expected a speed > 0")
        try:
            ARM.inverse_down(goal, yaw_goal)
        except UnreachableError as exc:
            raise MotionFailed(f"A4: cannot move to {goal}: {exc}") from exc
        prev = wm.command.get("point")
        fresh = (prev is not None and ctx.now - float(wm.command.get("t", -1e9)) < 0.2
                 and dist(prev, pos) < 2.0)
        wm.command.update(point=tuple(prev) if fresh and prev is not None else pos,
                          yaw=float(wm.command.get("yaw", pose.yaw)) if fresh else pose.yaw,
                          goal=goal, speed=speed, moving=True, t=ctx.now)
        ctx.write("drives_enable", 1.0)
        return goal, yaw_goal, speed
    wm.command.update(goal=None, moving=False, point=pos, yaw=pose.yaw, t=ctx.now)
    op: Literal["hold", "stop", "monitor"]
    match cmd:
        case HoldMotion():
            op = "hold"
            _hold(ctx, thetas)
        case StopMotion():
            op = "stop"
            _hold(ctx, thetas)
            ctx.write("drives_enable", 0.0)
        case Monitor():
            op = "monitor"
    ctx.complete(Reached(pos, op))
    return None, pose.yaw, 0.0


def _hold(ctx: TaskContext, thetas: list[float]) -> None:
    """Keep the joints where they stand (their targets are the angles measured)."""
    for name, angle in zip(TARGETS, thetas, strict=True):
        ctx.write(name, angle)


def motion_command(command: object) -> MotionCommand:
    """A4's command as a :data:`MotionCommand` (no command: :class:`Monitor`; a console dict
    converted by :func:`from_host`, ``op`` defaulting to ``move`` when it has ``p``). Raises
    MessageError naming A4 and the message for anything else."""
    match command:
        case MoveTo() | HoldMotion() | StopMotion() | Monitor():
            return command
        case None:
            return Monitor()
        case _:
            return from_host("A4", command, MOTIONS, _default_op,
                             "a MoveTo, HoldMotion, StopMotion or Monitor")


def _default_op(raw: Mapping[str, Any]) -> str:
    return "move" if "p" in raw else "monitor"


@task(world_model=PositionModel)
async def main(ctx: TaskContext, command: Any) -> None:
    """Execute motion commands (the first, then each newer one its owner sends) and report T5
    forever."""
    wm = ctx.world
    try:
        thetas = await _thetas(ctx)
    except SensorFailure as exc:
        await _servo_failed(ctx, exc)
    pose = pose_of(thetas)
    pos = pose.position
    goal, yaw_goal, speed = _command(ctx, command, thetas, pose)
    last_t = ctx.now
    progress_t, progress_pos = ctx.now, pos
    while True:
        if ctx.has_command:  # the owner's newer command (a repeated topen): no restart
            goal, yaw_goal, speed = _command(ctx, ctx.take_command(), thetas, pose)
            progress_t, progress_pos = ctx.now, pos
        if goal is not None:
            dt = max(0.0, ctx.now - last_t)
            point = wm.command["point"]
            step = speed * dt
            gap = dist(point, goal)
            point = goal if gap <= step else tuple(
                p + (g - p) * step / gap for p, g in zip(point, goal, strict=True))
            yaw = float(wm.command["yaw"])
            dyaw = wrap_angle(yaw_goal - yaw)
            yaw += max(-YAW_RATE * dt, min(YAW_RATE * dt, dyaw))
            try:
                joints = ARM.inverse_down(point, yaw)
            except UnreachableError as exc:
                raise MotionFailed(f"A4: path to {goal} leaves the workspace: {exc}") from exc
            for name, angle in zip(TARGETS, joints, strict=True):
                ctx.write(name, angle)
            wm.command.update(point=point, yaw=yaw, t=ctx.now)
            if dist(pos, goal) <= REACHED_MM and abs(wrap_angle(yaw_goal - pose.yaw)) < 0.01:
                goal = None
                wm.command.update(moving=False, goal=None)
                ctx.complete(Reached(pos))
            elif dist(pos, progress_pos) > 0.05:
                progress_t, progress_pos = ctx.now, pos
            elif ctx.now - progress_t > STALL_S:
                ctx.write("drives_enable", 0.0)
                raise MotionFailed(f"A4: tip stalled at {_fmt(pos)} for {STALL_S} s on the way "
                                   f"to {_fmt(goal)}")
        last_t = ctx.now
        wm.sensory.update(pos=pos, yaw=pose.yaw, thetas=thetas)
        ctx.put(TipPose(pos, pose.yaw, goal is not None, ctx.now))
        try:
            thetas = await _next_thetas(ctx)
        except SensorFailure as exc:
            await _servo_failed(ctx, exc)
        pose = pose_of(thetas)
        pos = pose.position


async def _servo_failed(ctx: TaskContext, exc: SensorFailure) -> NoReturn:
    report_failure(ctx, exc)
    ctx.world.command.update(moving=False, goal=None)
    ctx.write("drives_enable", 0.0)
    raise ServoFailure(f"A4: joint sensor {exc.device} failed ({exc.reason}): drives disabled, "
                       "arm halted")


def _fmt(p: Any) -> str:
    return "(" + ", ".join(f"{float(c):.1f}" for c in p) + ")"
