"""A1 - level 1: temperature of the arc (A1.s), compared with the band from its commander.

Reads ``arc_temp`` (50 Hz), filters out spikes (median of three), compares the temperature with
the band ``{"band": [low, high]}`` its commander gave (the thesis' "threshold from the C module")
and sends an :class:`~chcos.apps.weld.tasks.sensed.ArcTemp` (temp, cmp, band) upward, ``cmp``
being ``"below"``, ``"within"``, ``"above"`` or None without a band. A sensor failure is sent up
as a :class:`~chcos.apps.weld.tasks.sensed.SensorFailed` and the loop goes on waiting for the
sensor. A command is taken at once (completed with a ``BandSet``) and the loop runs on unowned.
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import (
    SpikeFilter,
    await_recovery,
    clear_failure,
    report_failure,
)
from chcos.apps.weld.tasks.messages import SetBand, from_host
from chcos.apps.weld.tasks.results import BandSet
from chcos.apps.weld.tasks.sensed import ArcTemp, Compared
from chcos.errors import SensorFailure
from chcos.user.context import TaskContext


def compare(temp: float, band: Any) -> Compared | None:
    """Where ``temp`` lies against ``band`` ([low, high] degC): below, within, above, or None."""
    if not isinstance(band, list | tuple) or len(band) != 2:
        return None
    lo, hi = float(band[0]), float(band[1])
    return "below" if temp < lo else "above" if temp > hi else "within"


async def main(ctx: TaskContext, command: Any) -> None:
    """Filter, compare and report the arc temperature forever."""
    match command:
        case SetBand():
            cmd = command
        case None:
            cmd = SetBand()
        case _:
            cmd = from_host("A1", command, {"set": SetBand}, "set", "a SetBand")
    wm = ctx.world
    if cmd.band is not None:
        wm.command["band"] = cmd.band
    ctx.complete(BandSet(wm.command.get("band")))
    filt: SpikeFilter = wm.sensory.setdefault("filter", SpikeFilter())
    while True:
        try:
            raw = await ctx.read("arc_temp")
        except SensorFailure as exc:
            report_failure(ctx, exc)
            await await_recovery(ctx, exc)
            continue
        clear_failure(ctx, "arc_temp")
        temp = filt.push(float(raw))
        cmp = compare(temp, wm.command.get("band"))
        wm.sensory["temp"] = temp
        ctx.put(ArcTemp(temp, cmp, wm.command.get("band")))
