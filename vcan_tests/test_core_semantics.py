"""The thesis' semantics (issue 16): standing tasks and restart policies, waiting on what
happens (wait_any), ownership as in Appendix 3 (repeated topen, resetpri, release of
subordinates, reset after an emergency), msgstat and the map telling the truth."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from chcos.apps.weld.cell import SAFE_DEVICES, open_cell
from chcos.comm.payloads import OpenAnswer
from chcos.errors import CommandSyntaxError, MessageError, ReadTimeout, SensorFailure
from chcos.kernel.clock import VirtualClock
from chcos.system.cmdline import Install, parse
from chcos.system.embedded import System, sysmap
from chcos.tables.messages import LinkStatus
from chcos.tables.tasks import TaskState
from chcos.user.context import Event, EventKind, TaskContext
from vcan_tests.conftest import MakeSystem, memory_map

M = "vcan_tests.test_core_semantics"


# ---- tasks used by the tests ------------------------------------------------------------------
async def loop(ctx: TaskContext, cmd: Any) -> None:
    """A standing loop: counts activations and readings of its sensor in its world model."""
    wm = ctx.world.sensory
    wm["starts"] = wm.get("starts", 0) + 1
    wm.setdefault("commands", []).append(cmd)
    while True:
        wm["last"] = await ctx.read(0)


async def flaky(ctx: TaskContext, cmd: Any) -> None:
    """Raises on its first activation (any later one runs on)."""
    wm = ctx.world.sensory
    wm["starts"] = wm.get("starts", 0) + 1
    wm.setdefault("commands", []).append(cmd)
    if wm["starts"] == 1:
        raise RuntimeError("first start fails")
    while True:
        await ctx.sleep(1.0)


async def servo(ctx: TaskContext, cmd: Any) -> None:
    """A control loop whose sensor failure ends it abnormally (SensorFailure is not caught)."""
    wm = ctx.world.sensory
    wm["starts"] = wm.get("starts", 0) + 1
    wm.setdefault("commands", []).append(cmd)
    while True:
        ctx.write("M1", float(await ctx.read("S1")))


async def worker(ctx: TaskContext, cmd: Any) -> Any:
    """Takes every newer command of its owner without a new activation; writes M1."""
    wm = ctx.world.sensory
    wm["starts"] = wm.get("starts", 0) + 1
    seen = wm.setdefault("seen", [])
    seen.append(cmd)
    ctx.write("M1", 5.0)
    while True:
        ev = await ctx.wait_any(commands=True)
        seen.append(ev.value)
        if ev.value == "finish":
            return "finished"


async def boss(ctx: TaskContext, cmd: Any) -> Any:
    """Invokes W with each of ``cmd["send"]`` (repeated topens), then waits for it."""
    for c in cmd["send"]:
        await ctx.invoke("W", c)
        await ctx.sleep(0.1)
    if cmd.get("fail"):
        raise RuntimeError("boss fails while owning W")
    if cmd.get("hold"):
        await ctx.sleep(100.0)
    done = await ctx.done("W")
    ctx.world.sensory["done"] = done
    return done.result


async def watcher(ctx: TaskContext, cmd: Any) -> None:
    """Records every wait_any event."""
    events: list[Event | tuple[str, float]] = ctx.world.sensory.setdefault("events", [])
    kw = dict(cmd)
    ports = kw.pop("ports", ())
    while True:
        try:
            events.append(await ctx.wait_any(ports, **kw))
        except ReadTimeout:
            events.append(("timeout", ctx.now))
            return


async def sender(ctx: TaskContext, cmd: Any) -> None:
    """Puts each value of ``cmd`` at 0.1 s intervals."""
    for v in cmd:
        ctx.put(v)
        await ctx.sleep(0.1)


async def quick(ctx: TaskContext, cmd: Any) -> Any:
    await ctx.sleep(0.5)
    return cmd


async def caller(ctx: TaskContext, cmd: Any) -> None:
    """Invokes Q without waiting, then waits for its completion or a command."""
    await ctx.invoke("Q", "job")
    events = ctx.world.sensory.setdefault("events", [])
    while True:
        events.append(await ctx.wait_any(completions=["Q"], commands=True))


def _world(s: System, task: str) -> dict[str, Any]:
    wm = s.tsktab.get(task).world
    assert wm is not None
    return wm.sensory


def _events(s: System) -> list[tuple[str, str]]:
    from chcos.kernel.instrument import Instrument

    got: list[tuple[str, str]] = []

    class Rec(Instrument):
        def event(self, kind: str, detail: str) -> None:
            got.append((kind, detail))

    s.kernel.add_instrument(Rec())
    return got


# ---- 1. standing tasks and restart policies ----------------------------------------------------
@pytest.mark.parametrize(("line", "standing", "restart", "backoff"), [
    ("install -m0i1s A1 S1", True, "never", 1.0),
    ("install -m0i1 -s A1 S1", True, "never", 1.0),
    ("install -m0i1 --standing --restart=on-recovery --backoff=0.25 A1 S1", True,
     "on-recovery", 0.25),
    ("install --machine 0 --inputs 1 --restart always A1 S1", False, "always", 1.0),
    ("install -m0i1 A1 S1", False, "never", 1.0),
])
def test_install_options_for_standing_and_restart(line: str, standing: bool, restart: str,
                                                  backoff: float) -> None:
    req = parse(line)
    assert isinstance(req, Install)
    assert (req.standing, req.restart, req.backoff) == (standing, restart, backoff)


@pytest.mark.parametrize(("line", "message"), [
    ("install -m0i1 --restart=sometimes A1 S1", "expected never, on-recovery, always"),
    ("install -m0i1 --backoff=nan A1 S1", "expected seconds in 0..86400"),
    ("install -m0i1 --backoff=-1 A1 S1", "expected seconds in 0..86400"),
    ("install -m0i1 --backoff=soon A1 S1", "is not a number of seconds"),
])
def test_bad_restart_options_are_refused(line: str, message: str) -> None:
    with pytest.raises(CommandSyntaxError, match=message):
        parse(line)


MEMORY_MAP = """
[[bus]]
name = "mem"
kind = "memory"

[[device]]
name = "S1"
direction = "sensor"
machine = 0
bus = "mem"
address = {}
"""


def test_standing_task_starts_at_install_and_survives_the_map(make_system: MakeSystem,
                                                              tmp_path: Path) -> None:
    devmap = tmp_path / "mem.toml"
    devmap.write_text(MEMORY_MAP)
    s = make_system([devmap])
    s.execute(f"install -m0i1 --standing --restart=on-recovery --backoff=0.5 "
              f"--code={M}:loop L S1")
    s.execute("inject S1 3")
    s.run_for(0.1)
    assert _world(s, "L") == {"starts": 1, "commands": [None], "last": 3}
    doc = sysmap.read(tmp_path / "sysfile.map")
    line = next(ln for ln in sysmap.install_lines(doc) if " L " in ln)
    assert "--standing" in line and "--restart=on-recovery" in line and "--backoff=0.5" in line
    s2 = System.from_map(tmp_path / "sysfile.map", clock=VirtualClock(),
                         map_path=tmp_path / "again.map")
    try:
        t = s2.tsktab.get("L")
        assert (t.standing, t.restart, t.backoff) == (True, "on-recovery", 0.5)
        s2.execute("inject S1 7")
        s2.run_for(0.1)
        assert _world(s2, "L")["last"] == 7  # running without any invoke
    finally:
        s2.shutdown()


def test_restart_always_after_backoff_with_the_last_command_is_an_event(
        make_system: MakeSystem) -> None:
    s = make_system()
    events = _events(s)
    s.execute(f"install -m0 --restart=always --backoff=0.5 --code={M}:flaky F")
    s.invoke("F", {"x": 1})
    s.run_for(0.4)
    t = s.tsktab.get("F")
    assert t.abnormal == 1 and t.coro is None
    s.run_for(0.2)
    assert t.coro is not None and t.restarts == 1
    assert _world(s, "F")["commands"] == [{"x": 1}, {"x": 1}]
    assert any(k == "restart" and "F restarted" in d for k, d in events)


def test_restart_never_is_the_default_the_owner_decides(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:flaky F")
    s.invoke("F", {"x": 1})
    s.run_for(10.0)
    t = s.tsktab.get("F")
    assert t.abnormal == 1 and t.coro is None and t.restarts == 0
    assert t.state is TaskState.SUSPENDED


def test_on_recovery_restarts_a_loop_when_its_device_is_healthy_again(
        make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"], {"M1": 0.0}))
    events = _events(s)
    s.execute(f"install -m0i1o1 --restart=on-recovery --backoff=0.2 --code={M}:servo V S1 M1")
    s.invoke("V", {"gain": 2})
    s.execute("inject S1 4")
    s.run_for(0.1)
    assert s.devtab.get("M1").value == 4.0
    s.call(s.devtab.fail, "S1", "bus off")
    s.run_for(1.0)
    t = s.tsktab.get("V")
    assert t.abnormal == 1 and t.coro is None
    assert s.devtab.get("M1").value == 0.0  # safe value at the abnormal end
    assert t.waiting_devices == frozenset({"S1"})
    s.run_for(5.0)
    assert t.coro is None  # still failed: nothing restarts it
    s.execute("inject S1 6")  # a reading does not end a failure the driver reported
    s.run_for(0.5)
    assert t.coro is None
    s.call(s.devtab.recover, "S1", "bus on")  # the driver's own end event: healthy again
    s.run_for(0.1)
    assert t.coro is None  # back-off
    s.run_for(0.2)
    assert t.coro is not None and t.restarts == 1
    assert _world(s, "V")["commands"] == [{"gain": 2}, {"gain": 2}]
    s.execute("inject S1 5")
    s.run_for(0.1)
    assert s.devtab.get("M1").value == 5.0
    assert [k for k, _ in events if k.startswith("restart")] == ["restart-waiting", "restart"]


def test_on_recovery_does_not_restart_after_a_plain_bug(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --restart=on-recovery --backoff=0.1 --code={M}:flaky F")
    s.invoke("F", {})
    s.run_for(5.0)
    assert s.tsktab.get("F").restarts == 0


def test_weld_map_rebuilt_invoke_job_then_intruder_puts_every_actuator_safe(
        tmp_path: Path) -> None:
    """Issue 16 item 1: a welding run's sysfile.map, rebuilt, keeps its emergency chain."""
    with open_cell("direct", workdir=tmp_path) as cell:
        cell.start_job()
        cell.run(2.0, until_done=False)
        devmaps = cell.system.devmap.files
    mapfile = tmp_path / "sysfile.map"
    doc = json.loads(mapfile.read_text())
    doc["devmaps"] = [str(p) for p in devmaps]
    mapfile.write_text(json.dumps(doc))
    s = System.from_map(mapfile, clock=VirtualClock(), map_path=tmp_path / "rebuilt.map")
    try:
        s.execute("invoke E2")
        s.run_for(3.0)
        assert s.devtab.get("drives_enable").value == 1.0  # the job moves the arm
        s.execute("inject intruder 1")
        s.run_for(0.5)
        assert s.tsktab.get("D3").steps > 0 and s.tsktab.get("E1").steps > 1
        for dev in SAFE_DEVICES:
            assert s.devtab.get(dev).value in (None, 0.0), dev
        assert s.devtab.get("drives_enable").value == 0.0
    finally:
        s.shutdown()


# ---- 2. waiting on what happens ----------------------------------------------------------------
async def top(ctx: TaskContext, cmd: Any) -> None:
    """Invokes C, then again with a newer command (a repeated topen)."""
    await ctx.invoke("C", "first")
    await ctx.sleep(0.1)
    await ctx.invoke("C", "newer")
    await ctx.sleep(100.0)


def test_wait_any_returns_a_completion_and_a_command(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:quick Q")
    s.execute(f"install -m0o1 --code={M}:caller C Q")
    s.execute(f"install -m0o1 --code={M}:top T C")
    s.invoke("T")
    s.run_for(1.0)
    ev = _world(s, "C")["events"]
    assert ev[0] == Event(EventKind.COMMAND, "T", "newer")
    assert ev[1].kind is EventKind.COMPLETION and ev[1].source == "Q"
    assert ev[1].value.result == "job"
    assert s.tsktab.get("C").activations == 1


def test_a_host_invoke_starts_the_command_afresh(make_system: MakeSystem) -> None:
    """The host's invoke is the system manager's, not a topen: it restarts a running task."""
    s = make_system()
    s.execute(f"install -m0 --code={M}:quick Q")
    s.execute(f"install -m0o1 --code={M}:caller C Q")
    s.invoke("C")
    s.run_for(0.1)
    s.invoke("C", "again")
    s.run_for(0.1)
    assert s.tsktab.get("C").activations == 2


def test_wait_any_when_filter_wakes_only_for_news(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:sender P")
    s.execute(f"install -m0i1 --code={M}:watcher W P")
    s.invoke("W", {"ports": ["P"], "when": lambda src, v: v > 10})
    s.run_for(0.01)
    steps = s.tsktab.get("W").steps
    s.invoke("P", [1, 2, 3, 50, 4, 5, 60])
    s.run_for(1.0)
    got = [e.value for e in _world(s, "W")["events"]]
    assert got == [50, 60]
    assert s.tsktab.get("W").steps - steps == 2  # it never ran for 1, 2, 3, 4, 5


def test_wait_any_exception_tap_failure_and_timeout(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"]))
    s.execute(f"install -m0 --code={M}:sender P")
    s.execute(f"install -m0i1 --role=exception --level=3 --code={M}:watcher X S1")
    s.invoke("X", {"ports": ["S1"], "exceptions": True, "timeout": 2.0})
    s.run_for(0.01)
    s.invoke("P", ["low"])
    s.run_for(0.05)
    s.execute("inject S1 1")
    s.run_for(0.05)
    s.call(s.devtab.fail, "S1", "wire cut")
    s.run_for(3.0)
    ev = _world(s, "X")["events"]
    assert ev[0] == Event(EventKind.EXCEPTION, "P", "low")
    assert ev[1] == Event(EventKind.MESSAGE, "S1", 1, 0)
    assert ev[2] == Event(EventKind.FAILURE, "S1", "wire cut", 0)
    assert ev[3][0] == "timeout"


def test_weld_exception_task_and_job_run_on_news_not_on_a_clock(good_gap_job: Any) -> None:
    """D3 ran 134 times a second (the curtain's 50 Hz and more), E2 20 times: now they run
    when a lower task reports something new. Checked on the session's good-gap job (direct
    binding, run to its outcome: conftest.good_gap_job)."""
    run = good_gap_job
    assert run.outcome is not None and run.outcome["outcome"] == "welded"
    d3 = run.extra["steps"]["D3"] / run.extra["secs"]
    e2 = run.extra["steps"]["E2"]
    assert d3 < 10.0, d3  # far below the light curtain's 50 Hz
    assert e2 <= 10, e2  # one step per phase completion


# ---- 3. ownership as in Appendix 3 -------------------------------------------------------------
def _owned(make_system: MakeSystem) -> System:
    s = make_system(memory_map([], {"M1": -1.0}))
    s.execute(f"install -m0o1 --code={M}:worker W M1")
    s.execute(f"install -m0o1 --code={M}:boss B W")
    return s


def test_repeated_topen_from_the_owner_does_not_restart(make_system: MakeSystem) -> None:
    s = _owned(make_system)
    s.invoke("B", {"send": ["a", "b", "finish"]})
    s.run_for(1.0)
    w = s.tsktab.get("W")
    assert w.activations == 1
    assert _world(s, "W")["seen"] == ["a", "b", "finish"]
    assert _world(s, "B")["done"].result == "finished"


def test_owner_that_ends_abnormally_releases_its_subordinate_safe(
        make_system: MakeSystem) -> None:
    s = _owned(make_system)
    s.invoke("B", {"send": ["a"], "fail": True})
    s.run_for(1.0)
    w = s.tsktab.get("W")
    assert w.owner is None and w.coro is None and w.state is TaskState.SUSPENDED
    assert s.devtab.get("M1").value == -1.0  # tclose: suspended with its actuators safe


def test_suspended_owner_releases_and_msgstat_says_suspended(make_system: MakeSystem) -> None:
    s = _owned(make_system)
    s.invoke("B", {"send": ["a"], "hold": True})
    s.run_for(1.0)
    assert s.tsktab.get("W").owner is s.msgtab.find("B", "W")
    s.execute("suspend B")
    s.run_for(0.1)
    assert s.tsktab.get("W").owner is None and s.tsktab.get("W").coro is None
    assert s.sysmgr.host_links["B"].status is LinkStatus.SUSPENDED
    doc = s.sysmgr.map_doc()
    assert next(lk for lk in doc["links"] if lk["src"] == "host" and lk["dst"] == "B")[
        "status"] == "suspended"
    s.execute("resume B")
    assert s.sysmgr.host_links["B"].status is LinkStatus.OK


def test_released_standing_task_goes_back_to_its_loop(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"], {"M1": 0.0}))
    s.execute(f"install -m0i1 --standing --code={M}:loop L S1")
    s.run_for(0.1)
    s.execute("invoke -30 L job=1")
    s.run_for(0.1)
    t = s.tsktab.get("L")
    assert t.prio == 30 and _world(s, "L")["commands"] == [None, {"job": 1}]
    s.execute("close L")
    s.run_for(0.1)
    assert t.owner is None and t.coro is not None and t.prio == t.default_prio
    assert _world(s, "L")["commands"] == [None, {"job": 1}, None]


def test_resetpri_host_and_task(make_system: MakeSystem) -> None:
    s = _owned(make_system)
    s.execute("setpri -40 B W")
    assert "priority 4" in s.execute("resetpri B W")
    assert s.msgtab.find("B", "W").priority == 4
    s.execute("invoke -60 W x=1")
    s.run_for(0.1)
    w = s.tsktab.get("W")
    w.prio = 90  # as if raised while an emergency path owned it
    assert s.execute("resetpri W") == "W: priority 60"
    s.execute("close W")
    s.run_for(0.1)
    assert w.prio == w.default_prio == 4


async def urgent(ctx: TaskContext, cmd: Any) -> None:
    """Invokes W at ``cmd["prio"]`` (at most its own running priority)."""
    try:
        await ctx.invoke("W", "urgent", priority=cmd["prio"])
        ctx.world.sensory["got"] = "owner"
    except MessageError as exc:
        ctx.world.sensory["got"] = str(exc)
    await ctx.sleep(100.0)


def test_a_task_passes_down_at_most_its_own_priority(make_system: MakeSystem) -> None:
    s = make_system(memory_map([], {"M1": -1.0}))
    s.execute(f"install -m0o1 --code={M}:worker W M1")
    s.execute(f"install -m0o1 --code={M}:urgent U W")
    s.execute(f"install -m0o1 --code={M}:urgent V W")
    s.execute("invoke -30 W x=1")  # the host holds W at 30
    s.execute("invoke -40 U prio=40")
    s.execute("invoke -20 V prio=50")
    s.run_for(0.1)
    assert _world(s, "U")["got"] == "owner"  # 40 > 30: pre-empts the host
    assert "runs at priority 20: it cannot invoke W at priority 50" in _world(s, "V")["got"]
    assert s.tsktab.get("W").owner is s.msgtab.find("U", "W")


def test_tasks_owned_from_a_dead_satellite_are_released(make_system: MakeSystem) -> None:
    s = make_system(memory_map([], {"M1": -1.0}), machines=(0, 1), local_machines=[0])
    s.execute(f"install -m0o1 --code={M}:worker W M1")
    s.execute(f"install -m1o1 --code={M}:boss B W")
    link = s.msgtab.find("B", "W")
    assert s.msgmgr.remote_open(link, "remote job", True) == OpenAnswer.owner()
    s.run_for(0.1)
    assert s.tsktab.get("W").owner is link
    s.msgmgr.satellite_lost(1)
    s.run_for(0.1)
    w = s.tsktab.get("W")
    assert w.owner is None and w.coro is None
    assert s.devtab.get("M1").value == -1.0


def test_reset_after_an_emergency_brings_the_cell_back_to_work(tmp_path: Path) -> None:
    with open_cell("direct", workdir=tmp_path) as cell:
        s = cell.system
        cell.start_job()
        cell.run(8.0, until_done=False)
        cell.inject("intruder(for=0.5s)")
        cell.run(30.0)
        assert cell.outcome() is not None and cell.outcome()["outcome"] == "aborted"
        frozen = [t.name for t in s.tsktab if t.frozen]
        assert "D1" in frozen
        assert s.msgtab.find("E2", "D1").status is LinkStatus.SUSPENDED  # msgstat tells
        answer = s.execute("reset")
        assert "D1" in answer
        assert not any(t.frozen for t in s.tsktab)
        a2 = s.tsktab.get("A2")
        assert a2.owner is None and a2.base_prio == a2.default_prio == 4  # not 90 any more
        cell.start_job()
        cell.run(150.0)
        assert cell.outcome() is not None and cell.outcome()["outcome"] == "welded", \
            cell.outcome()


# ---- 4. the map tells the truth ----------------------------------------------------------------
def test_map_runtime_fields_are_current_where_shown(make_system: MakeSystem,
                                                     tmp_path: Path) -> None:
    s = make_system(memory_map(["S1"]))
    s.execute(f"install -m0i1 --standing --code={M}:loop L S1")
    for v in range(5):
        s.execute(f"inject S1 {v}")
        s.run_for(0.1)
    s.execute("map")
    doc = sysmap.read(tmp_path / "sysfile.map")
    task = next(t for t in doc["tasks"] if t["name"] == "L")
    assert task["steps"] >= 5 and task["status"] == "waiting" and task["standing"] is True


def test_suspended_device_shows_suspended_and_drops_readings(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"]))
    s.execute(f"install -m0i1 --standing --code={M}:loop L S1")
    s.execute("suspend S1")
    s.execute("inject S1 9")
    s.run_for(0.1)
    assert s.devtab.get("S1").status.value == "suspended"
    assert "last" not in _world(s, "L")
    doc = s.sysmgr.map_doc()
    assert next(d for d in doc["devices"] if d["name"] == "S1")["status"] == "suspended"
    s.execute("resume S1")
    s.execute("inject S1 8")
    s.run_for(0.1)
    assert _world(s, "L")["last"] == 8


def test_sensor_failure_reaches_a_plain_read(make_system: MakeSystem) -> None:
    """wait_any's failure events leave plain reads as they were."""
    s = make_system(memory_map(["S1"], {"M1": 0.0}))
    s.execute(f"install -m0i1o1 --code={M}:servo V S1 M1")
    s.invoke("V")
    s.run_for(0.1)
    s.call(s.devtab.fail, "S1", "x")
    s.run_for(0.1)
    assert SensorFailure.__name__ in s.tsktab.get("V").last_error
