"""B1 - level 2: turn the weld on/off (B1.c).

Commands: :data:`chcos.apps.weld.tasks.messages.WeldCommand` (console: ``op=on volts=... wire=...``,
``op=off``). ``WeldOn(volts=V, wire=mm/s)``: gas on (A3) and wait up to ``gas_wait`` s for the flow,
then the wire feed (A5) and the voltage to its start-up value (A2); report ``WeldState("on")`` and
stay active, watching the gas (A3.s) while the weld is on. ``WeldOff()``: voltage off, wire off, gas
off, report ``WeldState("off")``, complete. If the gas fails (bottle empty or no flow for
``gas_grace`` s) while on, the weld is turned off, ``WeldState("fail", reason)`` is reported and
the activation raises GasFailure (its owner sees an abnormal completion). Installed with A5 among
its inputs, B1 also watches the electrode supply (A5.s): when the spool is empty the weld is turned
off the same way, reported as ``wire fail`` and WireFailure is raised. The world model answers
``welding`` (is the weld on), the context D3 asks for. A message that is not a WeldCommand is
refused with a MessageError naming B1 and the message, and so is a report from A3 or A5 that is
not theirs (the weld is turned off first).
"""

from __future__ import annotations

from typing import Any

from chcos.apps.weld.tasks.common import GasFailure, WeldTaskError, WireFailure
from chcos.apps.weld.tasks.messages import (
    SetGas,
    SetVolts,
    SetWire,
    WeldCommand,
    WeldOff,
    WeldOn,
    from_host,
    refused,
)
from chcos.apps.weld.tasks.sensed import GasState, SensorFailed, WeldState, WireState
from chcos.errors import MessageError
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task

COOLING_S = 15.0
"""How long after the weld is off a hot arc region is still expected (s)."""

WELD_COMMANDS: dict[str, type[WeldCommand]] = {"on": WeldOn, "off": WeldOff}
"""B1's commands by the ``op`` a console command names."""


def weld_command(command: object) -> WeldCommand:
    """B1's command as a :data:`WeldCommand` (no command: :class:`WeldOff`, a console dict
    converted by :func:`from_host`). Raises MessageError naming B1 and the message for anything
    else."""
    match command:
        case WeldOn() | WeldOff():
            return command
        case None:
            return WeldOff()
        case _:
            return from_host("B1", command, WELD_COMMANDS, "off", "a WeldOn or WeldOff")


class WeldModel(WorldModel):
    """B1's world model: the weld state (off, starting, on, fail) and who asked for it."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``welding``: True while the weld is starting or on. ``heat_expected <now>``: welding,
        or turned off less than ``COOLING_S`` ago (the pool is still cooling)."""
        welding = self.command.get("weld") in ("starting", "on")
        if topic == "welding":
            return welding
        if topic == "heat_expected":
            off_at = self.command.get("off_at")
            now = float(args[0]) if args else 0.0
            return welding or (off_at is not None and now - float(off_at) < COOLING_S)
        return super().answer(topic, *args)


async def _off(ctx: TaskContext) -> None:
    if ctx.world.command.get("weld") in ("starting", "on", "fail"):
        ctx.world.command["off_at"] = ctx.now
    steps: tuple[tuple[str, object], ...] = (
        ("A2", SetVolts(volts=0.0)), ("A5", SetWire(speed=0.0)), ("A3", SetGas(gas="off")))
    for port, cmd in steps:
        done = await ctx.call(port, cmd)
        if not done.ok:
            raise WeldTaskError(f"B1: turning the weld off, {port} answered "
                                f"{done.status.value}: {done.error}")


async def _turn_off(ctx: TaskContext) -> str:
    await _off(ctx)
    ctx.world.command["weld"] = "off"
    ctx.put(WeldState("off"))
    return "off"


@task(world_model=WeldModel)
async def main(ctx: TaskContext, command: Any) -> str:
    """Turn the weld on (and watch the gas) or off. While on, a newer command from the owner
    (a repeated topen, no new activation) is taken up at once: ``on`` runs the start-up again
    (gas, wire, voltage: after C1 freed a stuck tip the voltage is off), anything else turns the
    weld off and completes."""
    cmd = weld_command(command)
    while isinstance(cmd, WeldOn):
        cmd = await _on(ctx, cmd)
    return await _turn_off(ctx)


def _setting(ctx: TaskContext, value: float | None, key: str, default: float) -> float:
    """A WeldOn field, else B1's install parameter ``key``, else ``default``."""
    return float(ctx.params.get(key, default) if value is None else value)


async def _on(ctx: TaskContext, cmd: WeldOn) -> WeldCommand:
    """Start the weld and watch the gas until the owner's next command, which is returned."""
    wm = ctx.world
    volts = _setting(ctx, cmd.volts, "volts", 24.0)
    wire = _setting(ctx, cmd.wire, "wire", 80.0)
    gas_wait = _setting(ctx, cmd.gas_wait, "gas_wait", 1.0)
    grace = _setting(ctx, cmd.gas_grace, "gas_grace", 0.15)
    wm.command.update(weld="starting", volts=volts, wire=wire)
    await ctx.call("A3", SetGas(gas="on"))
    t0 = ctx.now
    while True:
        ev = await ctx.wait_any(["A3"], commands=True, timeout=gas_wait)
        if ev.kind == "command":
            return await _next(ctx, ev.value)
        match ev.value:
            case GasState(flow_ok=True):
                break
            case GasState() | SensorFailed():
                pass
            case other:
                await _turn_off(ctx)
                raise refused("B1", other, "a GasState or SensorFailed from A3")
        if ctx.now - t0 > gas_wait:
            await _fail(ctx, f"no gas flow {gas_wait} s after the valve opened "
                             f"(bottle {_bar(ev.value)})")
    await ctx.call("A5", SetWire(speed=wire))
    await ctx.call("A2", SetVolts(volts=volts))
    wm.command["weld"] = "on"
    ctx.put(WeldState("on"))
    bad_since: float | None = None
    watch = ["A3", "A5"] if "A5" in ctx.inputs else ["A3"]
    while True:
        ev = await ctx.wait_any(watch, commands=True)
        if ev.kind == "command":
            return await _next(ctx, ev.value)
        match ev.value:
            case WireState(empty=True, left=left):
                await _fail(ctx, f"electrode supply empty ({left or 0.0:.2f} m of wire "
                                 f"left)", "wire")
            case WireState() | SensorFailed():
                continue
            case GasState(empty=empty, flow_ok=flow_ok, flow=flow) as gas:
                if empty or not flow_ok:
                    bad_since = ctx.now if bad_since is None else bad_since
                    if ctx.now - bad_since >= grace:
                        what = "bottle empty" if empty else "no flow"
                        await _fail(ctx, f"{what} (bottle {_bar(gas)}, flow {flow:.1f} L/min)")
                else:
                    bad_since = None
            case other:
                await _turn_off(ctx)
                raise refused("B1", other, "a GasState from A3, a WireState from A5 or a "
                                           "SensorFailed")


async def _next(ctx: TaskContext, command: object) -> WeldCommand:
    """The owner's newer command while the weld is starting or on; a message that is not a
    WeldCommand turns the weld off before it is refused (MessageError naming B1)."""
    try:
        return weld_command(command)
    except MessageError:
        await _turn_off(ctx)
        raise


async def _fail(ctx: TaskContext, why: str, what: str = "gas") -> None:
    await _off(ctx)
    ctx.world.command["weld"] = "fail"
    reason = f"{what} fail: {why}"
    ctx.world.command["reason"] = reason
    ctx.put(WeldState("fail", reason))
    error = WireFailure if what == "wire" else GasFailure
    raise error(f"B1: {reason}; weld turned off")


def _bar(gas: object) -> str:
    match gas:
        case GasState(bottle=bottle):
            return f"{bottle:.1f} bar"
        case _:
            return "unknown"
