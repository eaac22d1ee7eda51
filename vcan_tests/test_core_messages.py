"""Message manager: newest wins, queued links, reads, ownership, pre-emption, completion."""

from __future__ import annotations

from typing import Any

import pytest

from chcos.devices.entry import DeviceStatus
from chcos.devices.spec import DeviceMap, DeviceSpec
from chcos.errors import (
    Busy,
    ChcosError,
    DeviceError,
    HandlerError,
    MessageError,
    QueueOverflow,
    ReadTimeout,
    SensorFailure,
)
from chcos.tables.messages import PRIORITIES, TOP_PRIORITY, LinkStatus
from chcos.tables.tasks import TaskState
from chcos.user.context import TaskContext
from vcan_tests.conftest import MakeSystem, memory_map

M = "vcan_tests.test_core_messages"


# ---- tasks used by the tests (module level so install can find them by reference) ----------
async def reader(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        cmd["log"].append(await ctx.read(0))
        if cmd.get("slow"):
            await ctx.sleep(cmd["slow"])


async def reader_any(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        port, value = await ctx.read_any()
        cmd["log"].append((ctx.inputs[port], value))


async def reader_timeout(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    try:
        await ctx.read(0, timeout=0.25)
    except ReadTimeout as exc:
        cmd["log"].append(("timeout", ctx.now, str(exc)))


async def reader_sensor(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        try:
            cmd["log"].append(await ctx.read(0))
        except SensorFailure as exc:
            cmd["log"].append(("failure", exc.device))
            return


async def producer(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    for v in cmd["values"]:
        ctx.put(v)
        if cmd.get("gap"):
            await ctx.sleep(cmd["gap"])
    await ctx.checkpoint()


async def queued_producer(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    for v in cmd["values"]:
        try:
            ctx.put(v)
        except QueueOverflow as exc:
            cmd["log"].append(("overflow", v, str(exc)))


async def worker(ctx: TaskContext, cmd: Any) -> Any:
    """A lower task: logs who commands it, works a while, completes with a result."""
    log = cmd["log"]
    log.append(("start", cmd["who"], ctx.priority))
    await ctx.sleep(cmd.get("work", 1.0))
    if cmd.get("fail"):
        raise ValueError(f"worker broke for {cmd['who']}")
    log.append(("done", cmd["who"]))
    return f"result for {cmd['who']}"


async def boss(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """Invokes W (after an optional delay) and records how it ended."""
    await ctx.sleep(cmd.get("delay", 0.0))
    try:
        await ctx.invoke("W", {"who": ctx.name, "log": cmd["log"], "work": cmd.get("work", 1.0),
                               "fail": cmd.get("fail", False)}, wait=cmd.get("wait", True))
    except Busy as exc:
        cmd["log"].append(("busy", ctx.name, str(exc)))
        return
    done = await ctx.done("W")
    cmd["log"].append(("report", ctx.name, done.status, done.result, done.error))


async def writer(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    ctx.write("M1", 10.0)
    await ctx.sleep(0.5)
    raise RuntimeError("controller fault")


async def bystander(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    for _ in range(10):
        await ctx.sleep(0.1)
        cmd["log"].append(ctx.now)


def install(s: Any, line: str) -> None:
    s.execute(line)


# ---- sensory messages ----------------------------------------------------------------------
def test_newest_message_overwrites_unread_one(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:producer P")
    s.execute(f"install -m0i1 --code={M}:reader R P")
    log: list[Any] = []
    s.invoke("R", {"log": log, "slow": 1.0})
    s.run_for(0.01)
    s.invoke("P", {"values": [1, 2, 3, 4], "gap": 0.4})
    s.run_for(3.0)
    # R reads 1 at once; while it sleeps 1 s, 2 and 3 arrive and 3 overwrites 2; then 4
    assert log == [1, 3, 4]
    link = s.msgtab.find("P", "R")
    assert (link.sent, link.overwritten, link.delivered) == (4, 1, 3)


def test_unread_messages_dropped_by_a_wipe_are_counted_not_delivered(
        make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:producer P")
    s.execute(f"install -m0i1 --code={M}:reader R P")
    s.execute(f"install -m0 --code={M}:producer Q")
    s.execute(f"install -m0i1 --queue=Q=4 --code={M}:reader F Q")
    log: list[Any] = []
    flog: list[Any] = []
    s.invoke("R", {"log": log, "slow": 1.0})
    s.invoke("F", {"log": flog, "slow": 1.0})
    s.run_for(0.01)
    s.invoke("P", {"values": [1, 2, 3], "gap": 0.4})  # R takes 1; 3 overwrites 2 (R sleeps)
    s.invoke("Q", {"values": [7, 8, 9], "gap": 0.4})  # F takes 7; 8 and 9 wait in the queue
    s.run_for(0.9)
    for name in ("R", "F"):
        s.msgmgr.wipe(s.tsktab.get(name), "reloaded")
    s.run_for(2.0)
    assert (log, flog) == ([1], [7])
    p, q = s.msgtab.find("P", "R"), s.msgtab.find("Q", "F")
    assert (p.sent, p.overwritten, p.delivered, p.discarded) == (3, 1, 1, 1)
    assert (q.sent, q.overwritten, q.delivered, q.discarded) == (3, 0, 1, 2)
    assert not p.port.fresh and not q.port.fresh  # type: ignore[union-attr]


def test_queued_link_keeps_fifo_and_refuses_overflow(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:queued_producer P")
    s.execute(f"install -m0i1 --queue=P=3 --code={M}:reader R P")
    log: list[Any] = []
    plog: list[Any] = []
    s.invoke("P", {"values": [1, 2, 3, 4, 5], "log": plog}, priority=50)
    s.run_for(0.1)
    s.invoke("R", {"log": log})
    s.run_for(1.0)
    assert log == [1, 2, 3]
    assert [p[1] for p in plog] == [4, 5]
    assert "queued link P/R is full" in plog[0][2]
    assert s.msgtab.find("P", "R").refused == 2


def test_read_any_prefers_higher_priority_link(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1", "S2"]))
    s.execute(f"install -m0i2 --code={M}:reader_any R S1 S2")
    s.execute("setpri -30 S2 R")
    log: list[Any] = []
    s.devtab.inject("S1", 1.0)
    s.devtab.inject("S2", 2.0)
    s.run_for(0.1)
    s.invoke("R", {"log": log})
    s.run_for(0.1)
    assert log == [("S2", 2.0), ("S1", 1.0)]


def test_read_any_follows_a_setpri_made_while_it_runs(make_system: MakeSystem) -> None:
    """read_any keeps its ports in priority order between calls; a live setpri of any link
    reorders them for the next call (and for an equal priority the lower port comes first)."""
    s = make_system(memory_map(["S1", "S2", "S3"]))
    s.execute(f"install -m0i3 --code={M}:reader_any R S1 S2 S3")
    log: list[Any] = []
    s.invoke("R", {"log": log})
    s.run_for(0.1)

    def burst() -> list[Any]:
        del log[:]
        for i, name in enumerate(("S1", "S2", "S3")):
            s.devtab.inject(name, float(i + 1))
        s.run_for(0.1)
        return [src for src, _v in log]

    assert burst() == ["S1", "S2", "S3"]  # all alike: the lowest port first
    s.execute("setpri -30 S3 R")
    assert burst() == ["S3", "S1", "S2"]
    s.execute("setpri -40 S2 R")
    assert burst() == ["S2", "S3", "S1"]
    s.execute("resetpri S2 R")
    s.execute("resetpri S3 R")
    assert burst() == ["S1", "S2", "S3"]


def test_read_timeout_on_virtual_time(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"]))
    s.execute(f"install -m0i1 --code={M}:reader_timeout R S1")
    log: list[Any] = []
    s.invoke("R", {"log": log})
    s.run_for(1.0)
    assert log[0][0] == "timeout" and log[0][1] == pytest.approx(0.25)
    assert "S1/R" in log[0][2]


def test_stale_sensor_is_a_sensor_failure_for_its_reader(make_system: MakeSystem) -> None:
    s = make_system(memory_map(["S1"], stale_after=0.5))
    s.execute(f"install -m0i1 --code={M}:reader_sensor R S1")
    log: list[Any] = []
    s.invoke("R", {"log": log})
    s.devtab.inject("S1", 5.0)
    s.run_for(2.0)
    assert log == [5.0, ("failure", "S1")]
    assert s.devtab.get("S1").status.value == "stale"


# ---- command messages: ownership, pre-emption, queues, completion ---------------------------
def _boss_system(make_system: MakeSystem) -> Any:
    s = make_system()
    s.execute(f"install -m0 --code={M}:worker W")
    s.execute(f"install -m0o1 --code={M}:boss LOW W")
    s.execute(f"install -m0o1 --code={M}:boss HIGH W")
    s.execute("setpri -2 LOW W")
    s.execute("setpri -20 HIGH W")
    return s


def test_free_target_runs_at_link_priority_and_reports_completion(
        make_system: MakeSystem) -> None:
    s = _boss_system(make_system)
    log: list[Any] = []
    s.invoke("LOW", {"log": log})
    s.run_for(5.0)
    assert log[0] == ("start", "LOW", 2)
    assert log[-1] == ("report", "LOW", LinkStatus.NORMAL, "result for LOW", "")
    assert s.tsktab.get("W").state is TaskState.SUSPENDED
    assert s.tsktab.get("W").owner is None


def test_higher_priority_preempts_lower_owner_who_is_told(make_system: MakeSystem) -> None:
    s = _boss_system(make_system)
    log: list[Any] = []
    s.invoke("LOW", {"log": log, "work": 2.0})
    s.invoke("HIGH", {"log": log, "delay": 0.5, "work": 1.0})
    s.run_for(5.0)
    assert ("start", "LOW", 2) in log and ("start", "HIGH", 20) in log
    low_report = next(e for e in log if e[0] == "report" and e[1] == "LOW")
    assert low_report[2] is LinkStatus.PREEMPTED and "HIGH" in low_report[4]
    assert ("done", "LOW") not in log  # the pre-empted activation never finished
    assert ("report", "HIGH", LinkStatus.NORMAL, "result for HIGH", "") in log
    assert s.msgtab.find("LOW", "W").status is LinkStatus.PREEMPTED


def test_lower_priority_caller_waits_then_gets_the_task(make_system: MakeSystem) -> None:
    s = _boss_system(make_system)
    log: list[Any] = []
    s.invoke("HIGH", {"log": log, "work": 1.0})
    s.invoke("LOW", {"log": log, "delay": 0.2, "work": 1.0})
    s.run_for(5.0)
    starts = [e for e in log if e[0] == "start"]
    assert starts == [("start", "HIGH", 20), ("start", "LOW", 2)]
    assert [e[1] for e in log if e[0] == "report"] == ["HIGH", "LOW"]


def test_no_wait_invoke_gets_busy_at_once(make_system: MakeSystem) -> None:
    s = _boss_system(make_system)
    log: list[Any] = []
    s.invoke("HIGH", {"log": log, "work": 1.0})
    s.invoke("LOW", {"log": log, "delay": 0.2, "wait": False})
    s.run_for(5.0)
    busy = [e for e in log if e[0] == "busy"]
    assert busy and "held by HIGH at priority 20" in busy[0][2]


def test_abnormal_completion_is_contained_and_reported(make_system: MakeSystem) -> None:
    s = _boss_system(make_system)
    log: list[Any] = []
    s.invoke("LOW", {"log": log, "fail": True, "work": 0.5})
    s.run_for(5.0)
    report = next(e for e in log if e[0] == "report")
    assert report[2] is LinkStatus.ABNORMAL
    assert "ValueError: worker broke for LOW" in report[4]
    w = s.tsktab.get("W")
    assert w.abnormal == 1 and w.state is TaskState.SUSPENDED
    # the task is suspended, not dead: it can be invoked again
    s.invoke("HIGH", {"log": log, "work": 0.5})
    s.run_for(5.0)
    assert ("report", "HIGH", LinkStatus.NORMAL, "result for HIGH", "") in log


def test_fault_drives_owned_actuators_safe_and_others_keep_running(
        make_system: MakeSystem) -> None:
    s = make_system(memory_map([], {"M1": -1.0}))
    s.execute(f"install -m0o1 --code={M}:writer C M1")
    s.execute(f"install -m0 --code={M}:bystander B")
    log: list[Any] = []
    s.invoke("C", {})
    s.invoke("B", {"log": log})
    s.run_for(3.0)
    assert s.devtab.get("M1").value == -1.0  # safe value after the fault
    assert len(log) == 10  # the bystander ran to the end
    assert "controller fault" in s.tsktab.get("C").last_error


def test_host_invoke_close_and_msgstat(make_system: MakeSystem) -> None:
    s = _boss_system(make_system)
    log: list[Any] = []
    s.invoke("W", {"who": "host", "log": log, "work": 10.0}, priority=30)
    s.run_for(1.0)
    assert s.tsktab.get("W").owner is s.sysmgr.host_links["W"]
    s.execute("close W")
    s.run_for(1.0)
    assert s.tsktab.get("W").owner is None
    assert s.tsktab.get("W").state is TaskState.SUSPENDED
    assert ("done", "host") not in log


# ---- collected errors surface, one priority range, typed device status (issue 14) -------------
def test_a_reading_refused_by_a_full_queued_link_surfaces_in_system_check(
        make_system: MakeSystem) -> None:
    """The reading interrupt that hit a full queued link is not only collected: check() raises
    it, naming the handler and chaining the QueueOverflow; the kernel ran on meanwhile."""
    s = make_system(memory_map(["S1"]))
    s.execute(f"install -m0i1 --queue=S1=1 --code={M}:reader R S1")
    s.check()
    s.devtab.inject("S1", 1.0)
    s.devtab.inject("S1", 2.0)   # nobody read the first: the queue of one is full
    s.run_for(0.1)
    with pytest.raises(HandlerError) as err:
        s.check()
    assert "Devtab._readings failed on the kernel thread: QueueOverflow: queued link S1/R is " \
           "full" in str(err.value)
    assert isinstance(err.value.__cause__, QueueOverflow)
    s.check()   # raised once
    log: list[Any] = []
    s.invoke("R", {"log": log})
    s.run_for(0.1)
    assert log == [1.0]


@pytest.mark.parametrize("line", ["setpri -100 host R", "invoke -p 100 R", "invoke -p -1 R"])
def test_one_priority_range_everywhere(make_system: MakeSystem, line: str) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:producer R")
    with pytest.raises(ChcosError, match=r"0\.\.99"):
        s.execute(line)
    assert range(0, 100) == PRIORITIES and TOP_PRIORITY == 99


async def _raise_to(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    try:
        await ctx.invoke(0, {"values": []}, priority=cmd["prio"])
    except MessageError as exc:
        cmd["log"].append(str(exc))


def test_a_task_cannot_invoke_outside_the_priority_range(make_system: MakeSystem) -> None:
    s = make_system()
    s.execute(f"install -m0 --code={M}:producer P")
    s.execute(f"install -m0o1 --code={M}:_raise_to C P")
    log: list[Any] = []
    s.invoke("C", {"prio": 100, "log": log}, priority=99)
    s.run_for(0.1)
    assert log and "cannot invoke P at priority 100" in log[0]


def test_device_status_is_typed_and_keeps_its_wire_text(make_system: MakeSystem) -> None:
    """Devtab hands the link a DeviceStatus (not a string); the text on maps and the link is
    the enum's value, as before."""
    told: list[tuple[str, DeviceStatus, str]] = []

    class Link:
        def actuator(self, device: str, machine: int, value: Any, source: str) -> None:
            raise AssertionError("no remote actuator here")

        def device_status(self, device: str, status: DeviceStatus, reason: str) -> None:
            told.append((device, status, reason))

    s = make_system(memory_map(["S1"], ["M1"]))
    s.devtab.remote = Link()
    s.devtab.fail("S1", "wire cut")
    s.devtab.suspend("M1")
    s.run_for(0.1)
    assert told == [("M1", DeviceStatus.SUSPENDED, "suspended by the host"),
                    ("S1", DeviceStatus.FAILED, "wire cut")]
    assert [st.value for _, st, _ in told] == ["suspended", "failed"]
    assert {st.value for st in DeviceStatus} == {"OK", "failed", "suspended", "stale"}


def test_one_process_system_refuses_a_link_to_another_machine() -> None:
    """NoComm: a one-process system has nobody else to tell and refuses remote traffic."""
    from chcos.messages.protocols import NoComm

    nc = NoComm()
    assert nc.is_up(1) is False
    nc.estop("test")
    nc.device_status("S1", DeviceStatus.FAILED, "x")
    with pytest.raises(MessageError, match="actuator command to M1 for machine 2: this system "
                                           "has no link"):
        nc.actuator("M1", 2, 1.0, "A1")


def test_devtab_knows_devices_not_links() -> None:
    """Devtab alone (no message manager): readings and sensor failures go to its one listener,
    which answers whether an unread message was overwritten; an actuator of a machine this
    process does not drive is refused without a link."""
    from chcos.devices.devtab import Devtab
    from chcos.kernel.clock import VirtualClock
    from chcos.kernel.scheduler import Kernel

    heard: list[tuple[str, str, Any]] = []

    class Listener:
        def reading(self, device: str, value: Any) -> bool:
            heard.append(("reading", device, value))
            return len(heard) > 1          # the second reading overwrote an unread one

        def sensor_failed(self, device: str, failure: SensorFailure) -> None:
            heard.append(("failed", device, failure.reason))

    k = Kernel(VirtualClock())
    dt = Devtab(k, local=[0])
    dm = memory_map(["S1"], ["M1"])
    far = DeviceMap(dm.buses, (*dm.devices, DeviceSpec("M9", "actuator", 1, "mem",
                                                       safe_value=0.0)))
    dt.load(far)
    dt.inject("S1", 1.0)
    k.run()
    assert dt.get("S1").value == 1.0 and heard == []   # nobody listens: the buffer still works
    dt.listen(Listener())
    dt.inject("S1", 2.0)
    dt.inject("S1", 3.0)
    dt.fail("S1", "wire cut")
    k.run()
    assert heard == [("reading", "S1", 2.0), ("reading", "S1", 3.0),
                     ("failed", "S1", "wire cut")]
    assert dt.get("S1").overwrites == 1
    assert not dt.healthy("S1") and dt.healthy("M1")
    with pytest.raises(DeviceError, match="M9 is on machine 1, which this process does not "
                                          "drive, and no link leads there"):
        dt.write("M9", 1.0)


def test_a_reading_kept_by_a_queued_link_is_no_overwrite(make_system: MakeSystem) -> None:
    """Devtab's ``overwrites`` counts readings that replaced an unread one on a newest-wins
    link; a queued link keeps each behind the unread ones, so nothing is counted there."""
    s = make_system(memory_map(["S1", "S2"]))
    s.execute(f"install -m0i1 --queue=S1=8 --code={M}:reader Q S1")
    s.execute(f"install -m0i1 --code={M}:reader N S2")
    for v in (1.0, 2.0, 3.0):
        s.devtab.inject("S1", v)
        s.devtab.inject("S2", v)
    s.run_for(0.1)
    assert s.devtab.get("S1").overwrites == 0 and s.devtab.get("S2").overwrites == 2
    log: list[Any] = []
    s.invoke("Q", {"log": log})
    s.run_for(0.1)
    assert log == [1.0, 2.0, 3.0]
