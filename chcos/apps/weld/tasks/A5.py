"""A5 - level 1: advance/retard the electrode (wire) speed (A5.c); electrode speed (A5.s).

Command ``SetWire(speed=mm/s)`` (console: ``invoke A5 speed=...``) sets the wire feed,
``SetWire(step=mm/s)`` advances (positive) or
retards (negative) it; either is completed at once. The loop reads ``wire_speed`` (20 Hz) and
sends a :class:`~chcos.apps.weld.tasks.sensed.WireState` (wire, setpoint) upward; a failed
sensor is reported as a ``SensorFailed``.

When A5 is installed with the electrode supply ``wire_left`` (m of wire on the spool) among its
inputs, each message also carries ``left`` (m) and ``empty`` (below ``empty_m``,
default 0.05 m) and a failed supply sensor is reported as ``SensorFailed("wire_left", ...)`` (and
nothing else is sent until it reports again). Another message is refused (MessageError naming
A5 and the message).
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import (
    await_recovery,
    clear_failure,
    latest,
    report_failure,
)
from chcos.apps.weld.tasks.messages import SetWire, from_host
from chcos.apps.weld.tasks.results import WireSet
from chcos.apps.weld.tasks.sensed import WireState
from chcos.errors import ReadTimeout, SensorFailure
from chcos.user.context import TaskContext

WIRE_MAX = 250.0


async def main(ctx: TaskContext, command: Any) -> None:
    """Set and report the electrode speed."""
    match command:
        case SetWire():
            cmd = command
        case None:
            cmd = SetWire()
        case _:
            cmd = from_host("A5", command, {"set": SetWire}, "set", "a SetWire")
    wm = ctx.world
    speed = float(wm.command.get("speed", 0.0))
    if cmd.speed is not None:
        speed = float(cmd.speed)
    if cmd.step is not None:
        speed += float(cmd.step)
    if cmd.speed is not None or cmd.step is not None:
        speed = max(0.0, min(WIRE_MAX, speed))
        wm.command["speed"] = speed
        ctx.write("wire_set", speed)
    ctx.complete(WireSet(speed))
    supply = "wire_left" in ctx.inputs
    empty_m = float(ctx.params.get("empty_m", 0.05) if cmd.empty_m is None else cmd.empty_m)
    while True:
        try:
            wire = float(await ctx.read("wire_speed"))
        except SensorFailure as exc:
            report_failure(ctx, exc)
            await await_recovery(ctx, exc)
            continue
        clear_failure(ctx, "wire_speed")
        wm.sensory["wire"] = wire
        msg = WireState(wire, float(wm.command.get("speed", 0.0)))
        if supply:
            try:
                left = float(await latest(ctx, "wire_left", timeout=0.3))
            except SensorFailure as exc:
                # the failure stays the newest message (the exception task sees it) until the
                # supply reports again
                report_failure(ctx, exc)
                ctx.world.sensory.pop("last:wire_left", None)
                await ctx.sleep(0.1)
                continue
            except ReadTimeout:
                pass  # no supply reading yet
            else:
                clear_failure(ctx, "wire_left")
                msg = WireState(msg.wire, msg.setpoint, left, left < empty_m)
                wm.sensory.update(left=left, empty=left < empty_m)
        ctx.put(msg)
