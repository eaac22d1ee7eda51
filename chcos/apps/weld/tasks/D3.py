"""D3 - level 4: the sensory exception task (role ``exception``).

Hears every sensory message of every lower task (``ctx.read_exception``) and reads the light
curtain ``intruder`` itself (priority 99). It recognises the dangerous patterns and sends an
:class:`chcos.apps.weld.tasks.messages.Alarm` (kind, detail, t) upward to the assassin E1 (and
the job E2):

* ``intruder`` - the light curtain is broken (or its sensor failed);
* ``sensor failure`` - a lower task reports a failed sensor (at most once per device);
* ``unexpected heat`` - the arc temperature is above ``hot`` (default 200 degC) when no heat is
  expected. Context decides: D3 asks B1's world model (along the exception link) whether heat is
  expected - it is while D2 welds and for a while after, not while D1 only inspects;
* ``overheat`` - above ``overheat`` (default 2600 degC) whatever the context.

Anything else worth knowing (a gas failure, which the weld loop handles itself) is kept as a
notice in the world model. D3 judges the kinds of :mod:`chcos.apps.weld.tasks.sensed` that can
mean danger (``SensorFailed``, A1's ``ArcTemp``, B1's ``WeldState``); every other report of a
lower task is harmless to it. D3 waits on the light curtain and the tap at once
(``ctx.wait_any(["intruder"], exceptions=True, when=news)``); the ``news`` filter runs at
delivery and wakes D3 only for a change of the curtain, a failure not yet reported, a weld failure
or an arc hotter than the context allows (after B1 said heat is expected, not again for
``HEAT_RECHECK_S``), so D3 runs when a lower task reports something new, not at the curtain's
50 Hz.
"""

from __future__ import annotations

import math
from typing import Any

from chcos.apps.weld.tasks.messages import Alarm
from chcos.apps.weld.tasks.sensed import ArcTemp, SensorFailed, WeldState
from chcos.errors import MessageError, SensorFailure
from chcos.user.context import TaskContext
from chcos.user.worldmodel import WorldModel, task

HEAT_RECHECK_S = 0.5
"""After B1 said heat is expected, D3 does not ask again (nor wake for heat) for this long."""


def classify(src: str, msg: object, hot: float, overheat: float) -> tuple[str, str] | None:
    """The alarm a message from task ``src`` raises without context, or ("heat?", detail) when
    only context can tell (a hot arc); None when it is harmless."""
    match msg:
        case SensorFailed(device=device, reason=reason):
            return "sensor failure", f"{device} (reported by {src}): {reason}"
        case ArcTemp(temp=temp) if temp > overheat:
            return "overheat", f"arc temperature {temp:.0f} degC above {overheat:.0f} degC"
        case ArcTemp(temp=temp) if temp > hot:
            return "heat?", f"arc temperature {temp:.0f} degC"
        case _:
            return None


class ExceptionModel(WorldModel):
    """D3's world model: the alarms raised, notices kept, devices known failed."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``alarms``: the alarms so far; anything else as the base model."""
        if topic == "alarms":
            return list(self.sensory.get("alarms", []))
        return super().answer(topic, *args)


def _alarm(ctx: TaskContext, kind: str, detail: str) -> None:
    alarm = Alarm(kind, detail, ctx.now)
    ctx.world.sensory.setdefault("alarms", []).append(alarm.record())
    ctx.put(alarm)


async def _heat_expected(ctx: TaskContext) -> bool:
    try:
        return bool(await ctx.ask("B1", "heat_expected", ctx.now))
    except MessageError:
        return False


@task(world_model=ExceptionModel)
async def main(ctx: TaskContext, command: Any) -> None:
    """Watch the intruder and every lower sensory message for dangerous patterns; run only when
    one of them has something new to say."""
    ctx.complete("watching")
    wm = ctx.world
    hot = float(ctx.params.get("hot", 200.0))
    overheat = float(ctx.params.get("overheat", 2600.0))
    failed: set[str] = wm.sensory.setdefault("failed", set())
    seen = {"intruder": False, "heat_ok_until": -math.inf}

    def news(src: str, msg: Any) -> bool:
        """Worth waking D3 for (runs when the message is delivered, in the sender's step): a
        change of the light curtain, a failure not reported yet, a weld failure, an arc hotter
        than the context allows."""
        if src == "intruder":
            return bool(msg) != seen["intruder"]
        match msg:
            case SensorFailed(device=device):
                return device not in failed
            case WeldState(weld="fail"):
                return True
            case ArcTemp(temp=temp) if temp > overheat:
                return not wm.sensory.get("overheat")
            case ArcTemp(temp=temp) if temp > hot:
                return not wm.sensory.get("heat_alarm") and ctx.now >= seen["heat_ok_until"]
            case _:
                return False

    try:  # a light curtain that is already dead when D3 starts
        ctx.poll("intruder")
    except SensorFailure as exc:
        failed.add("intruder")
        _alarm(ctx, "intruder", f"light curtain sensor failed: {exc.reason}")
    while True:
        ev = await ctx.wait_any(["intruder"], exceptions=True, when=news)
        if ev.kind == "failure":
            if "intruder" not in failed:
                failed.add("intruder")
                _alarm(ctx, "intruder", f"light curtain sensor failed: {ev.value}")
            continue
        if ev.kind == "message":
            failed.discard("intruder")
            present = bool(ev.value)
            if present and not seen["intruder"]:
                _alarm(ctx, "intruder", "light curtain broken")
            seen["intruder"] = present
            continue
        src, msg = ev.source, ev.value
        found = classify(src, msg, hot, overheat)
        if found is None:
            match msg:
                case WeldState(weld="fail", reason=reason):
                    wm.sensory.setdefault("notices", []).append(
                        {"from": src, "notice": reason, "t": ctx.now})
            continue
        kind, detail = found
        match msg:
            case SensorFailed(device=device):
                if device not in failed:
                    failed.add(device)
                    _alarm(ctx, kind, detail)
            case ArcTemp() if kind == "heat?":
                if await _heat_expected(ctx):
                    seen["heat_ok_until"] = ctx.now + HEAT_RECHECK_S
                elif not wm.sensory.get("heat_alarm"):
                    wm.sensory["heat_alarm"] = True
                    _alarm(ctx, "unexpected heat", f"{detail} while no weld is on")
            case _:  # overheat, whatever the context
                if not wm.sensory.get(kind):
                    wm.sensory[kind] = True
                    _alarm(ctx, kind, detail)
