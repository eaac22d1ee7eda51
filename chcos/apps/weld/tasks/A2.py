"""A2 - level 1: adjust and maintain the arc voltage (A2.c); voltage of the arc (A2.s).

Command ``SetVolts(volts=V)`` (console: ``invoke A2 volts=V``) sets the power source (``volts_set``)
and is completed at once; the loop then maintains it: while the arc burns (read-back within 3 V of
the request) a read-back more than 0.5 V off trims the set-point by up to 2 V. Reads ``arc_volts``
(20 Hz) and ``arc_amps``, filters spikes, and sends an ``ArcVolts`` (volts, amps, setpoint;
:mod:`chcos.apps.weld.tasks.sensed`) upward. A failed sensor is reported as a ``SensorFailed``.
Another message is refused (MessageError naming A2 and the message).
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import (
    SpikeFilter,
    await_recovery,
    clear_failure,
    latest,
    report_failure,
)
from chcos.apps.weld.tasks.messages import SetVolts, from_host
from chcos.apps.weld.tasks.results import VoltsSet
from chcos.apps.weld.tasks.sensed import ArcVolts
from chcos.errors import SensorFailure
from chcos.user.context import TaskContext

TRIM_MAX = 2.0


async def main(ctx: TaskContext, command: Any) -> None:
    """Set, maintain and report the arc voltage."""
    match command:
        case SetVolts():
            cmd = command
        case None:
            cmd = SetVolts()
        case _:
            cmd = from_host("A2", command, {"set": SetVolts}, "set", "a SetVolts")
    wm = ctx.world
    if cmd.volts is not None:
        volts = float(cmd.volts)
        wm.command["volts"] = volts
        wm.command["trim"] = 0.0
        ctx.write("volts_set", volts)
    ctx.complete(VoltsSet(float(wm.command.get("volts", 0.0))))
    vf: SpikeFilter = wm.sensory.setdefault("vfilter", SpikeFilter())
    af: SpikeFilter = wm.sensory.setdefault("afilter", SpikeFilter())
    while True:
        try:
            volts = vf.push(float(await ctx.read("arc_volts")))
            amps = af.push(float(await latest(ctx, "arc_amps")))
        except SensorFailure as exc:
            report_failure(ctx, exc)
            await await_recovery(ctx, exc)
            continue
        clear_failure(ctx, "arc_volts")
        clear_failure(ctx, "arc_amps")
        want = float(wm.command.get("volts", 0.0))
        trim = float(wm.command.get("trim", 0.0))
        err = want - volts
        if want > 0.0 and 0.5 < abs(err) < 3.0:
            trim = max(-TRIM_MAX, min(TRIM_MAX, trim + 0.25 * err))
            wm.command["trim"] = trim
            ctx.write("volts_set", max(0.0, min(40.0, want + trim)))
        wm.sensory.update(volts=volts, amps=amps)
        ctx.put(ArcVolts(volts, amps, want))
