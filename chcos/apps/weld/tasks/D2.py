"""D2 - level 4: weld gap (D2.c); temperature <=> threshold (D2.s).

Sets the temperature band on A1, finds the start of the gap (C2), starts C1 watching the tip,
turns the weld on (B1), waits for the arc to heat the pool into the band (``strike`` s at most),
then moves along the gap (tracking as D1: gap points from A7 and A4, the next centre predicted
5 mm ahead, B4 told every ``steer`` s to move 5 mm towards the gap). The temperature is kept in
its band by the travel speed and the electrode speed: above the band's middle (by more than
``deadband``) the tip speeds up and the electrode is advanced (A5), below it both slow down.
When C1 reports the tip about to stick (its learned recognizer), D2 cuts the wire feed to
``RETRACT_SHARE`` for ``RETRACT_S`` s, so the arc burns the wire back. When C1 reports the tip
stuck, D2 calls C1 to free it, moves back down to where it stuck and
turns the weld on again. When the end marker comes under the sensor the tip goes on until it has
passed the gap end, then the weld is turned off and the tip held.

The comparison is the world model's: D2 predicts the temperature (the band's middle, tolerance
``deadband``) and the error vector of each A1 sample gives above/equal/below. D2.s puts a
``WeldTemp`` (temp, cmp, error, travelled, phase, t) upward at most every ``steer`` s, and a
``WeldTip`` (sticking or stuck) / ``WeldDone`` when those happen.

Completes with a ``Welded`` (welded_mm, in_band, unstuck, speed_range). Raises WeldAborted
(after turning the weld off and holding the tip) when B1 reports a gas failure, the start cannot
be found, the tip cannot be freed or a lower task ends abnormally; ArcFailure if the arc does not
strike; MessageError naming D2 and the message (after the same shutdown) for a report that is not
one of the kinds it reads.
"""

from __future__ import annotations

import math
from typing import Any, Literal, NoReturn

from chcos.apps.weld.tasks.common import (
    LOOK_AHEAD,
    ArcFailure,
    Tracker,
    WeldAborted,
    dist,
    setting,
    tip_pose,
    unit,
)
from chcos.apps.weld.tasks.messages import (
    FindStart,
    HoldMotion,
    IdleTip,
    SetBand,
    SetWire,
    Step,
    Unstick,
    WatchTip,
    Weld,
    WeldOff,
    WeldOn,
    expect,
    from_host,
    refused,
)
from chcos.apps.weld.tasks.results import Freed, StartFound, Welded
from chcos.apps.weld.tasks.sensed import (
    ArcTemp,
    GapImage,
    SensorFailed,
    TipState,
    WeldDone,
    WeldState,
    WeldTemp,
    WeldTip,
)
from chcos.errors import ReadTimeout
from chcos.tables.messages import LinkStatus
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task

RETRACT_S = 0.8
"""How long the wire feed is cut when C1 reports the tip about to stick (s)."""
RETRACT_SHARE = 0.2
"""The share of its speed the wire is fed at meanwhile."""

END_RUN_MM = 6.0 + LOOK_AHEAD + 0.5
"""How far the tip goes on after the end marker is first seen: the marker reaches 6 mm before
the gap end and the sensor is 5 mm ahead of the tip."""


class WeldGapModel(WorldModel):
    """D2's world model: phase, distance welded, speed and the temperature comparison."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``welding``: True while the arc should burn (phases strike, weld)."""
        if topic == "welding":
            return self.command.get("phase") in ("strike", "weld")
        return super().answer(topic, *args)


async def _check(ctx: TaskContext, port: str) -> None:
    """Raise WeldAborted if the task on ``port`` ended abnormally."""
    if ctx.status(port) is LinkStatus.ABNORMAL:
        failed = await ctx.done(port)
        await _shutdown(ctx)
        raise WeldAborted(f"D2: weld stopped, {port} failed: {failed.error}")


async def _shutdown(ctx: TaskContext) -> None:
    ctx.world.command["phase"] = "stopping"
    await ctx.call("B1", WeldOff())
    await ctx.call("B4", HoldMotion())
    await ctx.call("C1", IdleTip())
    ctx.world.command["phase"] = "stopped"


async def _refuse(ctx: TaskContext, src: str, msg: object) -> NoReturn:
    """Shut the weld down and refuse a report from ``src`` that D2 does not read."""
    await _shutdown(ctx)
    raise refused("D2", msg, f"one of the reports D2 reads (from {src})")


async def _weld_on(ctx: TaskContext, volts: float, wire: float, band: list[float],
                   strike: float) -> None:
    """Turn the weld on (B1) and wait until the temperature reaches the band."""
    wm = ctx.world
    wm.command["phase"] = "strike"
    await ctx.invoke("B1", WeldOn(volts=volts, wire=wire))
    t0 = ctx.now
    on = False
    while True:
        await _check(ctx, "B1")
        try:
            src, msg = await ctx.read_any(["B1", "A1"], timeout=0.2)
        except ReadTimeout:
            src, msg = "", None
        match msg:
            case WeldState(weld="on"):
                on = True
            case WeldState(weld="fail", reason=reason):
                await _shutdown(ctx)
                raise WeldAborted(f"D2: weld stopped: {reason}")
            case ArcTemp(temp=temp) if on and temp >= band[0]:
                return
            case WeldState() | ArcTemp() | SensorFailed() | None:
                pass
            case other:
                await _refuse(ctx, src, other)
        if ctx.now - t0 > strike:
            await _shutdown(ctx)
            raise ArcFailure(f"D2: the arc did not bring the pool to {band[0]} degC within "
                             f"{strike} s (weld {'on' if on else 'not on'})")


@task(world_model=WeldGapModel)
async def main(ctx: TaskContext, command: Any) -> Welded:
    """Weld the gap from its start marker to its end marker."""
    match command:
        case Weld():
            cmd = command
        case None:
            cmd = Weld()
        case _:
            cmd = from_host("D2", command, {"weld": Weld}, "weld", "a Weld")
    wm = ctx.world
    speed0 = float(setting(ctx, cmd.speed, "speed", 5.0))
    band = [float(v) for v in setting(ctx, cmd.band, "band", [1450.0, 1600.0])]
    volts = float(setting(ctx, cmd.volts, "volts", 24.0))
    wire0 = float(setting(ctx, cmd.wire, "wire", 80.0))
    steer_s = float(setting(ctx, cmd.steer, "steer", 0.1))
    deadband = float(setting(ctx, cmd.deadband, "deadband", 20.0))
    strike = float(setting(ctx, cmd.strike, "strike", 3.0))
    centre = (band[0] + band[1]) / 2.0
    wm.command.update(phase="search", band=band, speed=speed0, travelled=0.0, unstuck=0)
    await ctx.call("A1", SetBand(band=band))
    search = FindStart(start=cmd.start, heading=cmd.heading, z=cmd.z)
    found = await ctx.call("C2", search)
    if not found.ok:
        wm.command["phase"] = "aborted"
        raise WeldAborted(f"D2: cannot find the start of the gap: {found.error}")
    at = expect("D2", found.result, StartFound)
    start = at.at
    tracker = Tracker(float(at.yaw), float(start[2]))
    wm.predict("temp", centre, deadband, ctx.now)
    last_put = -math.inf
    await ctx.call("C1", WatchTip())
    await _weld_on(ctx, volts, wire0, band, strike)
    wm.command["phase"] = "weld"
    here = await tip_pose(ctx, "D2")
    tracker.moved(here.pos)
    speed = speed0
    speeds = [speed, speed]
    last_steer = last_regulate = -math.inf
    end_at: float | None = None
    samples = in_band = unstuck = 0
    retract_until: float | None = None
    while True:
        for lower in ("B1", "B4", "A5"):
            await _check(ctx, lower)
        src, msg = await ctx.read_any(["A7", "A1", "C1", "B1"], timeout=1.0)
        here = await tip_pose(ctx, "D2")
        travelled = tracker.moved(here.pos)
        match msg:
            case SensorFailed():
                continue
            case WeldState(weld="fail", reason=reason):
                await _shutdown(ctx)
                raise WeldAborted(f"D2: weld stopped: {reason}")
            case TipState(tip="sticking"):
                # C1 recognized the pattern that precedes a stuck tip: cut the wire feed for a
                # moment so the arc burns the wire back, then feed again
                retract_until = ctx.now + RETRACT_S
                ctx.put(WeldTip("sticking", travelled, "weld", ctx.now))
                wm.command["retracts"] = wm.command.get("retracts", 0) + 1
                await ctx.call("A5", SetWire(speed=RETRACT_SHARE * wire0 * speed / speed0))
                continue
            case WeldState() | TipState() | ArcTemp() | GapImage():
                pass
            case other:
                await _refuse(ctx, src, other)
        if retract_until is not None and ctx.now >= retract_until:
            retract_until = None
            await ctx.call("A5", SetWire(speed=wire0 * speed / speed0))
        match msg:
            case TipState(tip="stuck"):
                ctx.put(WeldTip("stuck", travelled, "unstick", ctx.now))
                unstuck += 1
                wm.command.update(phase="unstick", unstuck=unstuck)
                await _unstick(ctx, volts, wire0 * speed / speed0, band, strike)
                wm.command["phase"] = "weld"
                last_steer = -math.inf
                continue
            case ArcTemp(temp=temp):
                samples += 1
                in_band += band[0] <= temp <= band[1]
                ev = wm.compare("temp", temp, ctx.now)
                err = ev.error[""] if ev is not None else temp - centre
                cmp: Literal["equal", "above", "below"] = \
                    "equal" if ev is not None and not ev.surprise else \
                    "above" if err > 0 else "below"
                wm.sensory.update(temp=temp, cmp=cmp)
                if ctx.now - last_put >= steer_s:
                    last_put = ctx.now
                    ctx.put(WeldTemp(temp, cmp, err, travelled, "weld", ctx.now))
                if cmp != "equal" and ctx.now - last_regulate >= 0.2 and retract_until is None:
                    last_regulate = ctx.now
                    speed = max(0.5 * speed0, min(2.0 * speed0,
                                                  speed + (0.1 if cmp == "above" else -0.1)))
                    speeds = [min(speeds[0], speed), max(speeds[1], speed)]
                    await ctx.call("A5", SetWire(speed=wire0 * speed / speed0))
            case GapImage() as image:
                tracker.ranged(image.range)
                if image.centre is not None and image.pattern in ("gap", "start", "end"):
                    tracker.sighting(here.pos, float(here.yaw), float(image.centre))
                if image.end and end_at is None:
                    end_at = travelled
                    wm.command["end_seen_at"] = travelled
        wm.command.update(travelled=travelled, speed=speed)
        if end_at is not None and travelled - end_at >= END_RUN_MM:
            break
        if ctx.now - last_steer >= steer_s:
            last_steer = ctx.now
            d, yaw = tracker.steer(here.pos)
            await ctx.invoke("B4", Step(d=d, yaw=yaw, speed=speed))
    await _shutdown(ctx)
    result = Welded(welded_mm=tracker.travelled, in_band=in_band / max(1, samples),
                    unstuck=unstuck, speed_range=speeds)
    wm.command.update(phase="done", result=result)
    ctx.put(WeldDone(tracker.travelled, ctx.now))
    return result


async def _unstick(ctx: TaskContext, volts: float, wire: float, band: list[float],
                   strike: float) -> None:
    """Free the tip (C1), go back down to where it stuck and restart the weld."""
    freed = await ctx.call("C1", Unstick())
    if not freed.ok:
        await _shutdown(ctx)
        raise WeldAborted(f"D2: weld stopped, the tip could not be freed: {freed.error}")
    mem = expect("D2", freed.result, Freed).memorized
    here = await tip_pose(ctx, "D2")
    back = [m - h for m, h in zip(mem.pos, here.pos, strict=True)]
    down = await ctx.call("B4", Step(d=unit(back), dist=dist(mem.pos, here.pos),
                                     speed=10.0, yaw=mem.yaw))
    if not down.ok:
        await _shutdown(ctx)
        raise WeldAborted(f"D2: cannot return to the weld after freeing the tip: {down.error}")
    await ctx.call("C1", WatchTip())
    await _weld_on(ctx, volts, wire, band, strike)
