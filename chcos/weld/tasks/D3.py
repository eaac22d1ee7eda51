"""D3 - level 4: the sensory exception task (role ``exception``).

Hears every sensory message of every lower task (``ctx.read_exception``) and reads the light
curtain ``intruder`` itself (priority 99). It recognises the dangerous patterns and sends
``{"alarm": kind, "detail", "t"}`` upward to the assassin E1 (and the job E2):

* ``intruder`` - the light curtain is broken (or its sensor failed);
* ``sensor failure`` - a lower task reports a failed sensor (at most once per device);
* ``unexpected heat`` - the arc temperature is above ``hot`` (default 200 degC) when no heat is
  expected. Context decides: D3 asks B1's world model (along the exception link) whether heat is
  expected - it is while D2 welds and for a while after, not while D1 only inspects;
* ``overheat`` - above ``overheat`` (default 2600 degC) whatever the context.

Anything else worth knowing (a gas failure, which the weld loop handles itself) is kept as a
notice in the world model. The intruder is waited on; the tap is drained each time it reports,
so the reaction to the light curtain never waits for the tap.
"""

from __future__ import annotations

from typing import Any

from chcos.errors import MessageError, ReadTimeout, SensorFailure
from chcos.usrmgr import TaskContext
from chcos.worldmodel import WorldModel


def classify(src: str, msg: Any, hot: float, overheat: float) -> tuple[str, str] | None:
    """The alarm a message from task ``src`` raises without context, or ("heat?", detail) when
    only context can tell (a hot arc); None when it is harmless."""
    if not isinstance(msg, dict):
        return None
    if "fail" in msg:
        return "sensor failure", f"{msg['fail']} (reported by {src}): {msg.get('reason', '')}"
    if "temp" in msg:
        temp = float(msg["temp"])
        if temp > overheat:
            return "overheat", f"arc temperature {temp:.0f} degC above {overheat:.0f} degC"
        if temp > hot:
            return "heat?", f"arc temperature {temp:.0f} degC"
    return None


class ExceptionModel(WorldModel):
    """D3's world model: the alarms raised, notices kept, devices known failed."""

    def answer(self, topic: str, *args: Any) -> Any:
        """``alarms``: the alarms so far; anything else as the base model."""
        if topic == "alarms":
            return list(self.sensory.get("alarms", []))
        return super().answer(topic, *args)


def _alarm(ctx: TaskContext, kind: str, detail: str) -> None:
    record = {"alarm": kind, "detail": detail, "t": ctx.now}
    ctx.world.sensory.setdefault("alarms", []).append(record)
    ctx.put(record)


async def _heat_expected(ctx: TaskContext) -> bool:
    try:
        return bool(await ctx.ask("B1", "heat_expected", ctx.now))
    except MessageError:
        return False


async def main(ctx: TaskContext, command: Any) -> None:
    """Watch the intruder and every lower sensory message for dangerous patterns."""
    ctx.complete("watching")
    wm = ctx.world
    hot = float(ctx.params.get("hot", 200.0))
    overheat = float(ctx.params.get("overheat", 2600.0))
    failed: set[str] = wm.sensory.setdefault("failed", set())
    intruder = False
    while True:
        try:
            present = bool(await ctx.read("intruder"))
        except SensorFailure as exc:
            present = False
            if "intruder" not in failed:
                failed.add("intruder")
                _alarm(ctx, "intruder", f"light curtain sensor failed: {exc.reason}")
            await ctx.sleep(0.02)
        if present and not intruder:
            _alarm(ctx, "intruder", "light curtain broken")
        intruder = present
        while True:  # drain the tap: every lower sensory message since the last look
            try:
                src, msg = await ctx.read_exception(timeout=0.0)
            except ReadTimeout:
                break
            found = classify(src, msg, hot, overheat)
            if found is None:
                if isinstance(msg, dict) and msg.get("weld") == "fail":
                    wm.sensory.setdefault("notices", []).append(
                        {"from": src, "notice": msg.get("reason"), "t": ctx.now})
                continue
            kind, detail = found
            if kind == "sensor failure":
                device = str(msg["fail"])
                if device not in failed:
                    failed.add(device)
                    _alarm(ctx, kind, detail)
            elif kind == "heat?":
                if not await _heat_expected(ctx) and not wm.sensory.get("heat_alarm"):
                    wm.sensory["heat_alarm"] = True
                    _alarm(ctx, "unexpected heat", f"{detail} while no weld is on")
            elif not wm.sensory.get(kind):
                wm.sensory[kind] = True
                _alarm(ctx, kind, detail)


main.world_model = ExceptionModel  # type: ignore[attr-defined]
