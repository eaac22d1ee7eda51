"""A7 - level 1: the linear sensor (A7.s).

Reads the linear image ``linear`` (50 Hz: 64 pixels, '1' dark) with ``range`` and the marker
detector flags ``start_marker``/``end_marker``; determines the binary image's pattern (gap,
start-marker bars, end-marker bars, nothing), the gap's centre and width and the distance to the
surface, and sends a :class:`~chcos.apps.weld.tasks.sensed.GapImage` (range, pattern, centre,
width, marker, start, end, t) upward. ``start``/``end`` are the detector flag or the recognised
bar pattern. A failed sensor is reported as a ``SensorFailed``, and so is an image that is not
64 '0'/'1' pixels. Sensory only: any command just (re)starts the loop.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import (
    PIXELS,
    analyse,
    await_recovery,
    clear_failure,
    latest,
    report_failure,
)
from chcos.apps.weld.tasks.messages import record
from chcos.apps.weld.tasks.sensed import GapImage
from chcos.errors import SensorFailure
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> None:
    """Analyse and report every linear image."""
    ctx.complete("running")
    wm = ctx.world
    while True:
        try:
            raw = await ctx.read("linear")
            if not (isinstance(raw, str) and len(raw) == PIXELS and set(raw) <= {"0", "1"}):
                raise SensorFailure("linear", f"malformed image {raw!r}: expected a string of "
                                              f"{PIXELS} '0'/'1' pixels")
            pixels = raw
            rng = float(await latest(ctx, "range"))
            start = int(await latest(ctx, "start_marker"))
            end = int(await latest(ctx, "end_marker"))
        except SensorFailure as exc:
            report_failure(ctx, exc)
            await await_recovery(ctx, exc)
            continue
        clear_failure(ctx, "linear")
        hint = float(wm.sensory.get("hint", 0.0))
        img = analyse(pixels, hint)
        if img.centre is not None:
            wm.sensory["hint"] = img.centre
        msg = GapImage(range=rng, pattern=img.pattern, centre=img.centre, width=img.width,
                       marker=img.marker_centre, start=bool(start) or img.pattern == "start",
                       end=bool(end) or img.pattern == "end", t=ctx.now)
        wm.sensory.update(record(msg))
        ctx.put(msg)
