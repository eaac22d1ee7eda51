"""C1 - level 3: unstick tip (C1.c); tip stuck/free (C1.s).

Commands: :data:`chcos.apps.weld.tasks.messages.TipCommand` (console: ``op=watch``,
``op=idle``, ``op=unstick lift=...``).

``WatchTip()`` or no command (the sensory part, run while D2 welds): reads the arc temperature (A1),
the arc voltage and current (A2) and the tip position (A4). The tip is stuck when, with the voltage
on, the arc voltage has collapsed (below 2 V) with a short-circuit current (over 200 A), or the tip
has not moved for 0.5 s although a motion is commanded while the temperature falls. Reports a
``TipState`` (tip ``stuck`` or ``free``, since) on every change; a sensor failure reported by
A1, A2 or A4 is skipped, any other message refused (MessageError naming C1 and the message).

Besides these hard-coded tests C1 learns (thesis 5.4, App. 2 C1.s: temperature and position
over time): when a short circuit shows the tip stuck, the arc voltage's trend over the half
second before it is kept as an example if it differs from the trends of normal welding (a
freeze without a precursor teaches nothing; ``chcos.user.knowledge.LearnedPattern``, in
``learned/C1-tip.json`` beside the system's map). On later runs, when the burning arc's voltage
leaves its normal trends and follows a learned one, C1 reports ``TipState("sticking")`` before
the tip freezes (its commander can cut the wire feed), and ``TipState("free")`` 1 s later; an
example that keeps firing with no freeze counts false alarms and is forgotten. Every reaction is
kept in the world model's ``reactions`` (``{"t", "kind": "learned" | "hard-coded"}``).

``IdleTip()`` stops watching. ``Unstick(lift)``: stop the motors (the joint drives
quick-stop) and memorize the position (A6), turn the voltage off (A2), enable the drives again
(A6), move the tip ``lift`` mm (default 10) straight up,
90 degrees away from the gap (A4), and check that it moved. Completes with a ``Freed``
(memorized: A6's record of where it stuck, lift); raises TipStillStuck if the tip did not come free,
MotionFailed if a lower task failed, MessageError naming C1 and the message for anything but a
TipCommand.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

from chcos.apps.weld.tasks.common import (
    MotionFailed,
    TipStillStuck,
    dist,
    tip_pose,
)
from chcos.apps.weld.tasks.messages import (
    DrivesCommand,
    IdleTip,
    MoveTo,
    SetVolts,
    TipCommand,
    Unstick,
    WatchTip,
    expect,
    from_host,
    refused,
)
from chcos.apps.weld.tasks.results import Freed, Memorized
from chcos.apps.weld.tasks.sensed import ArcTemp, ArcVolts, SensorFailed, TipPose, TipState
from chcos.user.context import TaskContext
from chcos.user.knowledge import LearnedPattern, Store

LEAD_S = 0.5
"""How much history before a stuck tip is learned (s)."""

TIP_COMMANDS: dict[str, type[TipCommand]] = {
    "watch": WatchTip, "idle": IdleTip, "unstick": Unstick}
"""C1's commands by the ``op`` a console command names."""


async def main(ctx: TaskContext, command: Any) -> Any:
    """Watch for a stuck tip, or free it."""
    match command:
        case WatchTip() | IdleTip() | Unstick():
            cmd: TipCommand = command
        case None:
            cmd = WatchTip()
        case _:
            cmd = from_host("C1", command, TIP_COMMANDS, "watch",
                            "a WatchTip, IdleTip or Unstick")
    match cmd:
        case Unstick(lift=lift):
            return await _unstick(ctx, float(ctx.params.get("lift", 10.0) if lift is None
                                             else lift))
        case IdleTip():
            return "idle"
        case WatchTip():
            await _watch(ctx)
    return None


async def _watch(ctx: TaskContext) -> None:
    wm = ctx.world
    ctx.complete("watching")
    state: Literal["stuck", "free", "sticking"] = "free"
    short_since: float | None = None
    still_since: float | None = None
    last_pos: Sequence[float] | None = None
    temps: list[float] = []
    learned = LearnedPattern(["volts"], Store.beside(ctx.state_dir, f"{ctx.name}-tip"),
                             lead=LEAD_S, guard=0.05, tolerance=0.5)
    reactions: list[dict[str, Any]] = wm.sensory.setdefault("reactions", [])
    sticking_until: float | None = None
    last_set: float | None = None
    while True:
        _, msg = await ctx.read_any(["A1", "A2", "A4"])
        now = ctx.now
        match msg:
            case SensorFailed():
                continue
            case ArcVolts(volts=volts, amps=amps, setpoint=setpoint):
                shorted = setpoint > 0.0 and volts < 2.0 and amps > 200.0
                # the freeze: learn the trend that led to it
                if shorted and short_since is None and state == "free" \
                        and learned.learn(now) is not None:
                    wm.sensory["learned_examples"] = len(learned.examples)
                short_since = (short_since if short_since is not None else now) if shorted \
                    else None
                burning = setpoint > 0.0 and volts > 2.0 and amps > 50.0
                if not burning or setpoint != last_set:
                    learned.history.clear()
                last_set = setpoint
                if burning and learned.push(now, {"volts": float(volts)}) and state == "free":
                    state, sticking_until = "sticking", now + 1.0
                    reactions.append({"t": now, "kind": "learned"})
                    wm.sensory.update(tip=state, since=now)
                    ctx.put(TipState(state, now))
                    learned.history.clear()
                    continue
            case ArcTemp(temp=temp):
                temps = [*temps[-24:], float(temp)]
            case TipPose(pos=pos, moving=moving):
                if moving and last_pos is not None and dist(pos, last_pos) < 0.01:
                    still_since = still_since if still_since is not None else now
                else:
                    still_since = None
                last_pos = pos
            case other:
                raise refused("C1", other, "an ArcTemp, ArcVolts, TipPose or SensorFailed")
        cooling = len(temps) >= 25 and temps[-1] < temps[0] - 30.0
        stuck = ((short_since is not None and now - short_since >= 0.1)
                 or (still_since is not None and now - still_since >= 0.5 and cooling))
        if state == "sticking" and not stuck:
            if sticking_until is not None and now < sticking_until:
                continue
            sticking_until = None
        new: Literal["stuck", "free"] = "stuck" if stuck else "free"
        if new != state:
            if new == "stuck" and state != "sticking":
                reactions.append({"t": now, "kind": "hard-coded"})
            state = new
            wm.sensory.update(tip=state, since=now)
            ctx.put(TipState(state, now))


async def _unstick(ctx: TaskContext, lift: float) -> Freed:
    wm = ctx.world
    wm.command["unstick"] = "stopping"
    mem = await ctx.call("A6", DrivesCommand(stop=True, memorize="stuck"))
    if not mem.ok:
        raise MotionFailed(f"C1: A6 could not stop/memorize: {mem.error}")
    off = await ctx.call("A2", SetVolts(volts=0.0))
    if not off.ok:
        raise MotionFailed(f"C1: A2 could not turn the voltage off: {off.error}")
    record = expect("C1", await ctx.ask("A6", "position", "stuck"), Memorized)
    p0 = record.pos
    on = await ctx.call("A6", DrivesCommand(enable=True, memorize=None))
    if not on.ok:
        raise MotionFailed(f"C1: A6 could not enable the joint drives again: {on.error}")
    wm.command["unstick"] = "lifting"
    up = await ctx.call("A4", MoveTo(p=(p0[0], p0[1], p0[2] + lift), yaw=record.yaw,
                                     speed=10.0))
    here = await tip_pose(ctx, "C1")
    if not up.ok or here.pos[2] - p0[2] < 0.8 * lift:
        raise TipStillStuck(f"C1: tip still stuck at {p0} after the lift "
                            f"({up.status.value} {up.error})")
    wm.command["unstick"] = "freed"
    wm.sensory.update(tip="free", since=ctx.now)
    return Freed(record, lift)
