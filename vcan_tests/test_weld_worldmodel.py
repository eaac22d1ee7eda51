"""The world-model facility (chcos.user.worldmodel, .knowledge, .plans): context along links,
prediction and the error vector, recognizers, learned responses persisted across runs, and plans."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.weld.tasks.common import WeldTaskError
from chcos.errors import ConfigError, MessageError
from chcos.user.context import TaskContext
from chcos.user.knowledge import Experience, LearnedPattern, Recognizer, Store
from chcos.user.plans import Plan, Plans, PlansExhausted
from chcos.user.worldmodel import WorldModel, context
from vcan_tests.conftest import MakeSystem

M = "vcan_tests.test_weld_worldmodel"


# ---- tasks ----------------------------------------------------------------------------------
async def worker(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Asks its commander what it is doing, and for its prediction of ``temp``."""
    seen = await context(ctx)
    cmd["log"].append(("doing", seen))
    if seen is not None:
        cmd["log"].append(("predict", await context(ctx, "predict", "temp")))


async def boss(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Says what it does and predicts, then commands the worker and waits for it."""
    ctx.world.command.update(phase="welding", band=[1450, 1600])
    ctx.world.predict("temp", 1525.0, tolerance=75.0, t=ctx.now)
    await ctx.call("W", {"log": cmd["log"]})


def test_context_is_what_the_commander_is_doing(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:worker W")
    s.execute(f"install -m0o1 --code={M}:boss B W")
    log: list[Any] = []
    s.invoke("B", {"log": log})
    s.run_for(1.0)
    assert log == [("doing", {"phase": "welding", "band": [1450, 1600]}), ("predict", 1525.0)]
    # invoked from the host, nobody commands W: no context
    log.clear()
    s.invoke("W", {"log": log})
    s.run_for(1.0)
    assert log == [("doing", None)]


def test_prediction_error_vector_and_surprise() -> None:
    wm = WorldModel()
    assert wm.compare("temp", 1500.0) is None  # nothing predicted
    wm.predict("temp", 1525.0, tolerance=75.0, t=1.0)
    ev = wm.compare("temp", 1500.0, t=1.1)
    assert ev is not None and ev.error == {"": -25.0} and not ev.surprise
    ev = wm.compare("temp", 1700.0, t=1.2)
    assert ev is not None and ev.norm == pytest.approx(175.0) and ev.surprise
    assert wm.surprises == {"temp": 1} and wm.errors["temp"] is ev
    wm.predict("centre", {"x": 3.0, "y": 4.0}, tolerance=1.0)
    ev = wm.compare("centre", {"x": 0.0, "y": 0.0})
    assert ev is not None and ev.norm == pytest.approx(5.0) and ev.error == {"x": -3.0, "y": -4.0}
    assert wm.answer("predict", "centre") == {"x": 3.0, "y": 4.0}
    with pytest.raises(MessageError, match="nothing about 'speed'"):
        wm.answer("predict", "speed")
    with pytest.raises(ConfigError, match="components"):
        wm.compare("centre", {"x": 1.0})
    with pytest.raises(ConfigError, match="not a number"):
        wm.predict("bad", "hot")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="tolerance"):
        wm.predict("temp", 1.0, tolerance=-1.0)


def test_recognizer_maps_a_window_to_named_patterns() -> None:
    r = Recognizer(span=0.5)

    def stalled(w: Any) -> bool:  # position unchanged over the last 0.3 s
        t = w[-1][0]
        recent = [s for s in w if s[0] >= t - 0.3 - 1e-9]
        return (t - w[0][0] >= 0.3 - 1e-9
                and all(abs(s[1]["pos"] - w[-1][1]["pos"]) < 0.1 for s in recent))

    r.add("stalled", stalled)
    r.add("hot", lambda w: w[-1][1]["temp"] > 1600)
    with pytest.raises(ConfigError, match="already defined"):
        r.add("hot", lambda w: False)
    hits = [r.push(0.1 * i, {"pos": 0.5 * i, "temp": 1500.0}) for i in range(5)]
    assert all(h == [] for h in hits)
    out = []
    for i in range(5, 12):
        out.append(r.push(0.1 * i, {"pos": 2.5, "temp": 1500.0 + 30 * (i - 5)}))
    assert "stalled" in out[3] and "stalled" not in out[2]
    assert "hot" in out[-1] and r.seen["stalled"] == pytest.approx(0.8)
    r.clear()
    assert r.seen == {} and not r.window


def test_experience_is_persisted_proposes_what_worked_and_resets(tmp_path: Path) -> None:
    store = Store.beside(tmp_path, "C2")
    assert store.path == tmp_path / "learned" / "C2.json"
    exp = Experience(store)
    assert exp.propose("find start", ["spiral", "raster"]) == ["spiral", "raster"]
    exp.record("find start", "spiral", False)
    exp.record("find start", "raster", True)
    again = Experience(Store.beside(tmp_path, "C2"))  # the next run
    assert again.propose("find start", ["spiral", "raster"]) == ["raster", "spiral"]
    assert again.rate("find start", "spiral") == 0.0
    assert json.loads(store.path.read_text())["responses"]["find start"]["raster"] == [1, 1]
    again.reset()
    assert not store.path.exists()
    assert Experience(store).propose("find start", ["spiral", "raster"]) == ["spiral", "raster"]
    store.path.parent.mkdir(exist_ok=True)
    store.path.write_text("{not json")
    with pytest.raises(ConfigError, match=r"C2\.json"):
        Experience(store)


def _ramp(pattern: LearnedPattern, t0: float, n: int, slope: float) -> list[bool]:
    return [pattern.push(t0 + 0.05 * i, {"temp": 1500 + slope * 0.05 * i, "v": 5.0})
            for i in range(n)]


def _normal_then_ramp(pattern: LearnedPattern, t0: float, slope: float) -> list[bool]:
    """3 s of normal windows (flat, a little noise), then 2 s of a ramp of ``slope``."""
    flat = [pattern.push(t0 + 0.05 * i, {"temp": 1500 + 0.5 * (-1) ** i, "v": 5.0})
            for i in range(60)]
    return flat + [pattern.push(t0 + 3.0 + 0.05 * i,
                                {"temp": 1500 + slope * 0.05 * i + 0.5 * (-1) ** i, "v": 5.0})
                   for i in range(40)]


def test_learned_pattern_fires_on_the_precursor_it_learned(tmp_path: Path) -> None:
    store = Store.beside(tmp_path, "tip")
    lp = LearnedPattern(["temp", "v"], store, lead=0.5)
    assert not any(_normal_then_ramp(lp, 0.0, 200.0))  # nothing learned yet
    assert lp.learn(5.0) is not None
    lp2 = LearnedPattern(["temp", "v"], Store.beside(tmp_path, "tip"), lead=0.5)  # next run
    fired = _normal_then_ramp(lp2, 10.0, 200.0)
    assert not any(fired[:60])  # normal windows never fire
    assert any(fired) and fired.index(True) <= 60 + 11  # once a full lead window is seen
    lp3 = LearnedPattern(["temp", "v"], Store.beside(tmp_path, "tip"), lead=0.5)
    assert not any(_normal_then_ramp(lp3, 20.0, 20.0))  # a different slope is not the precursor
    lp3.reset()
    assert not LearnedPattern(["temp", "v"], store, lead=0.5).examples
    with pytest.raises(ConfigError, match="feature"):
        lp3.push(0.0, {"temp": 1.0})


def test_plans_fall_through_to_the_next_permissible_one(tmp_path: Path) -> None:
    calls: list[str] = []

    def plan(name: str, ok: bool) -> Plan:
        async def run(x: int) -> str:
            calls.append(name)
            if not ok:
                raise WeldTaskError(f"{name} found nothing")
            return f"{name}:{x}"
        return Plan(name, run)

    wm = WorldModel()
    forbidden = Plan("teach", plan("teach", True).run, lambda m: m.command.get("taught", False))
    plans = Plans("find start", [plan("spiral", False), forbidden, plan("raster", True)],
                  Experience(Store.beside(tmp_path, "C2")))
    assert asyncio.run(plans.attempt(wm, 7)) == ("raster", "raster:7")
    assert calls == ["spiral", "raster"]  # "teach" was not permissible
    assert [(p["plan"], p["ok"]) for p in wm.command["plans"]] == [("spiral", False),
                                                                   ("raster", True)]
    # next run: experience puts the plan that worked first
    calls.clear()
    plans2 = Plans("find start", [plan("spiral", False), plan("raster", True)],
                   Experience(Store.beside(tmp_path, "C2")))
    assert asyncio.run(plans2.attempt(WorldModel(), 1))[0] == "raster" and calls == ["raster"]
    bad = Plans("find start", [plan("spiral", False), plan("raster", False)])
    with pytest.raises(PlansExhausted, match="spiral: spiral found nothing; raster: raster"):
        asyncio.run(bad.attempt(WorldModel(), 1))


def test_an_outcome_without_a_precursor_teaches_nothing_and_raises_no_alarm_later(
        tmp_path: Path) -> None:
    """The learner needs a reference point: an outcome after normal windows only (a freeze
    without a precursor) learns no example and writes nothing; a later run of normal windows
    raises no alarm, even with an example that looks normal left by an older version."""
    store = Store.beside(tmp_path, "tip")
    lp = LearnedPattern(["temp", "v"], store, lead=0.5)
    flat = [lp.push(0.05 * i, {"temp": 1500 + 0.5 * (-1) ** i, "v": 5.0}) for i in range(100)]
    assert not any(flat)
    assert lp.learn(5.0) is None
    assert not lp.examples and store.path is not None and not store.path.exists()
    # an example of a normal window's rates, as the unfixed recognizer stored one
    store.save({"examples": [{"temp": 0.0, "v": 0.0}], "features": ["temp", "v"]})
    later = LearnedPattern(["temp", "v"], Store.beside(tmp_path, "tip"), lead=0.5)
    assert len(later.examples) == 1
    alarms = [later.push(10.0 + 0.05 * i, {"temp": 1500 + 0.5 * (-1) ** i, "v": 5.0})
              for i in range(400)]
    assert not any(alarms) and later.false_alarms == 0


def test_false_alarms_count_against_a_learned_pattern_until_it_is_forgotten(
        tmp_path: Path) -> None:
    """An example that fires again within ``recur`` s of its previous alarm, with no outcome
    in between, scores a false alarm (kept in the store); after two more false alarms than
    predicted outcomes it is forgotten and fires no more."""
    store = Store.beside(tmp_path, "tip")
    lp = LearnedPattern(["temp", "v"], store, lead=0.5, recur=2.0)
    _normal_then_ramp(lp, 0.0, 200.0)
    assert lp.learn(5.0) is not None
    run = LearnedPattern(["temp", "v"], Store.beside(tmp_path, "tip"), lead=0.5, recur=2.0)
    fired = _normal_then_ramp(run, 10.0, 200.0)   # the ramp goes on: it fires again and again
    fired += [run.push(15.0 + 0.05 * i, {"temp": 1700 + 200.0 * 0.05 * i, "v": 5.0})
              for i in range(40)]
    assert fired.count(True) >= 1
    assert run.false_alarms == 2 and run.forgotten == 1 and not run.examples
    assert not LearnedPattern(["temp", "v"], Store.beside(tmp_path, "tip")).examples
    # an alarm followed by its outcome counts for the example instead
    lp = LearnedPattern(["temp", "v"], Store.beside(tmp_path, "tip2"), lead=0.5)
    _normal_then_ramp(lp, 0.0, 200.0)
    lp.learn(5.0)
    t = 10.0
    while not lp.push(t, {"temp": 1500 + 200.0 * (t - 10.0), "v": 5.0}):
        t += 0.05
        assert t < 12.0
    lp.learn(t + 0.1)
    assert lp.scores[0] == [1, 0] and lp.false_alarms == 0
