"""D1 - level 4: inspect gap (D1.c); target sighted, predicted next centre, gap width (D1.s).

Finds the start of the gap (C2), then moves along it at ``speed`` (default 20 mm/s) keeping the
distance and the alignment on the gap centre: each linear image (A7) with the tip pose (A4)
becomes a gap point, the next centre is predicted 5 mm ahead, and every ``steer`` s B4 is told
to move 5 mm towards the gap. The gap width is compared with ``too_narrow``/``too_wide``
(default 1.2 / 3.0 mm); ``confirm`` (default 3) successive images out of tolerance fail the
inspection at once. At the end marker the tip is stopped and the inspection is OK.

The world model predicts the width (the middle of the tolerance, ``chcos.user.worldmodel``
prediction) and compares each measured width with it: the error vector's surprise is "width not
OK". D1.s puts a ``GapInspected`` (target, next_centre, width, width_ok, travelled, t) upward
every ``steer`` s and at the end: target sighted, the predicted next centre, the width check.

Completes with an ``Inspection`` (``OK`` or ``fail``, reason, at_mm, width, start, ...; a
failed inspection is a normal completion: the inspection itself worked). Raises WeldAborted if
the start cannot be found or a lower task fails, MessageError naming D1 and the message for a
report from A7 that is not an image or a sensor failure.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from chcos.apps.weld.tasks.common import (
    Tracker,
    WeldAborted,
    setting,
    tip_pose,
)
from chcos.apps.weld.tasks.messages import (
    FindStart,
    HoldMotion,
    Inspect,
    Step,
    expect,
    from_host,
    refused,
)
from chcos.apps.weld.tasks.results import Inspection, StartFound
from chcos.apps.weld.tasks.sensed import GapImage, GapInspected, SensorFailed
from chcos.tables.messages import LinkStatus
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task


class GapModel(WorldModel):
    """D1's world model: the gap seen so far (points, widths) and the predicted next centre."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``inspecting``: True while an inspection runs; ``next_centre``: the prediction."""
        if topic == "inspecting":
            return self.command.get("phase") in ("search", "track")
        return super().answer(topic, *args)


@task(world_model=GapModel)
async def main(ctx: TaskContext, command: Any) -> Inspection:
    """Inspect the gap from its start marker to its end marker."""
    match command:
        case Inspect():
            cmd = command
        case None:
            cmd = Inspect()
        case _:
            cmd = from_host("D1", command, {"inspect": Inspect}, "inspect", "an Inspect")
    wm = ctx.world
    speed = float(setting(ctx, cmd.speed, "speed", 20.0))
    too_narrow = float(setting(ctx, cmd.too_narrow, "too_narrow", 1.2))
    too_wide = float(setting(ctx, cmd.too_wide, "too_wide", 3.0))
    confirm = int(setting(ctx, cmd.confirm, "confirm", 3))
    steer_s = float(setting(ctx, cmd.steer, "steer", 0.1))
    search = FindStart(start=cmd.start, heading=cmd.heading, z=cmd.z)
    wm.command.update(phase="search", width_min=None, width_max=None)
    found = await ctx.call("C2", search)
    if not found.ok:
        wm.command["phase"] = "aborted"
        raise WeldAborted(f"D1: cannot find the start of the gap: {found.error}")
    at = expect("D1", found.result, StartFound)
    start = at.at
    heading = float(at.yaw)
    tracker = Tracker(heading, float(start[2]))
    wm.command.update(phase="track", start=start)
    wm.predict("width", (too_narrow + too_wide) / 2.0, (too_wide - too_narrow) / 2.0, ctx.now)
    width_ok = True
    here = await tip_pose(ctx, "D1")
    tracker.moved(here.pos)
    bad: dict[str, int] = {"too wide": 0, "too narrow": 0}
    widths: list[float] = []
    last_steer = -math.inf
    end_at: float | None = None
    # the verdict: (OK or fail, the reason, the width that failed, where)
    outcome: tuple[Literal["OK", "fail"], str, float | None, float] | None = None
    while outcome is None:
        if ctx.status("B4") is LinkStatus.ABNORMAL:
            failed = await ctx.done("B4")
            wm.command["phase"] = "aborted"
            raise WeldAborted(f"D1: inspection stopped, B4 failed: {failed.error}")
        image = await ctx.read("A7", timeout=1.0)
        here = await tip_pose(ctx, "D1")
        travelled = tracker.moved(here.pos)
        match image:
            case GapImage() as msg:
                pass
            case SensorFailed():
                continue
            case other:
                raise refused("D1", other, "a GapImage or SensorFailed from A7")
        tracker.ranged(msg.range)
        if msg.centre is not None and msg.pattern in ("gap", "start", "end"):
            tracker.sighting(here.pos, float(here.yaw), float(msg.centre))
        if msg.pattern == "gap" and msg.width is not None:
            w = float(msg.width)
            widths.append(w)
            ev = wm.compare("width", w, ctx.now)
            width_ok = ev is None or not ev.surprise
            bad["too wide"] = bad["too wide"] + 1 if w > too_wide else 0
            bad["too narrow"] = bad["too narrow"] + 1 if w < too_narrow else 0
            for reason, n in bad.items():
                if n >= confirm:
                    outcome = ("fail", reason, w, travelled)
        if msg.end and end_at is None:
            end_at = travelled
        if end_at is not None and travelled - end_at >= 6.0:
            outcome = ("OK", "", None, travelled)
        wm.sensory.update(travelled=travelled, next_centre=tracker.predict(), width=msg.width)
        if outcome is None and ctx.now - last_steer >= steer_s:
            last_steer = ctx.now
            nxt = tracker.predict()
            ctx.put(GapInspected(target=msg.centre is not None,
                                 next_centre=list(nxt) if nxt is not None else None,
                                 width=msg.width, width_ok=width_ok, travelled=travelled,
                                 t=ctx.now))
            d, yaw = tracker.steer(here.pos)
            await ctx.invoke("B4", Step(d=d, yaw=yaw, speed=speed))
    await ctx.call("B4", HoldMotion())
    verdict, reason, width, at_mm = outcome
    result = Inspection(inspection=verdict, reason=reason, at_mm=at_mm, width=width,
                        start=start, heading=heading, length_mm=tracker.travelled,
                        width_min=min(widths, default=None), width_max=max(widths, default=None))
    wm.command.update(phase="done", outcome=result)
    ctx.put(GapInspected(target=True, next_centre=None, width=result.width, width_ok=result.ok,
                         travelled=tracker.travelled, t=ctx.now, inspection=result.inspection))
    return result
