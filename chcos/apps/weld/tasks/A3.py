"""A3 - level 1: turn the shielding gas on/off (A3.c); bottle full/empty and flow on/off (A3.s).

Command ``SetGas(gas="on" | "off")`` (console: ``invoke A3 gas=on``) switches ``gas_valve`` and is
completed at once. The loop reads the bottle pressure ``gas_bottle`` (20 Hz) and the flow
``gas_flow`` and sends a :class:`~chcos.apps.weld.tasks.sensed.GasState` (bottle, empty, flow,
flow_ok, valve) upward: the bottle is empty below ``empty_bar`` (install parameter, default 5
bar), the flow is good from ``min_flow`` (default 8 L/min). A failed sensor is reported as a
``SensorFailed``. Another message is refused
(MessageError naming A3 and the message).
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import (
    await_recovery,
    clear_failure,
    latest,
    report_failure,
)
from chcos.apps.weld.tasks.messages import SetGas, from_host, record
from chcos.apps.weld.tasks.results import GasSet
from chcos.apps.weld.tasks.sensed import GasState
from chcos.errors import SensorFailure
from chcos.user.context import TaskContext


async def main(ctx: TaskContext, command: Any) -> None:
    """Switch and watch the gas."""
    match command:
        case SetGas():
            cmd = command
        case None:
            cmd = SetGas()
        case _:
            cmd = from_host("A3", command, {"set": SetGas}, "set", "a SetGas")
    wm = ctx.world
    if cmd.gas is not None:
        on = cmd.on
        wm.command["valve"] = on
        ctx.write("gas_valve", 1.0 if on else 0.0)
    ctx.complete(GasSet(bool(wm.command.get("valve", False))))
    empty_bar = float(ctx.params.get("empty_bar", 5.0))
    min_flow = float(ctx.params.get("min_flow", 8.0))
    while True:
        try:
            bottle = float(await ctx.read("gas_bottle"))
            flow = float(await latest(ctx, "gas_flow"))
        except SensorFailure as exc:
            report_failure(ctx, exc)
            await await_recovery(ctx, exc)
            continue
        clear_failure(ctx, "gas_bottle")
        clear_failure(ctx, "gas_flow")
        msg = GasState(bottle=bottle, empty=bottle < empty_bar, flow=flow,
                       flow_ok=flow >= min_flow, valve=bool(wm.command.get("valve", False)))
        wm.sensory.update(record(msg))
        ctx.put(msg)
