"""Message delivery to a reader that is suspended, that waits with a read timeout, or that an
instrument watches: it gets the same messages, and the links count the same, as a plain reader
(virtual clock)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chcos.devices.spec import DeviceMap
from chcos.errors import MessageError, ReadTimeout
from chcos.kernel.clock import VirtualClock
from chcos.kernel.instrument import Counters, Instrument, Latency
from chcos.system.embedded import System
from chcos.tables.messages import Link
from chcos.tables.tasks import TaskEntry, TaskState
from chcos.user.context import TaskContext

M = "vcan_tests.test_core_delivery_paths"


async def idle(ctx: TaskContext, cmd: Any) -> None:
    """The source task: never runs; the test delivers on its link."""


async def reader(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        try:
            cmd["log"].append(await ctx.read(0, timeout=cmd.get("timeout")))
        except ReadTimeout:
            cmd["log"].append(("timeout", ctx.now))
            return


def _system(tmp_path: Path, cmd: dict[str, Any]) -> tuple[System, TaskEntry, Link]:
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    s.execute(f"install -m0 --code={M}:idle P")
    s.execute(f"install -m0i1 --code={M}:reader C P")
    s.invoke("C", cmd, priority=20)
    s.run(until=0.0)
    c = s.tsktab.get("C")
    assert c.state is TaskState.WAITING
    return s, c, c.in_ports[0].link


def test_suspended_reader_keeps_the_newest_message_until_resumed(tmp_path: Path) -> None:
    log: list[Any] = []
    s, c, link = _system(tmp_path, {"log": log})
    s.kernel.suspend(c)
    s.msgmgr.deliver(link, 1)
    s.msgmgr.deliver(link, 2)
    s.run()
    assert log == []
    assert c.state is TaskState.SUSPENDED
    assert (link.sent, link.overwritten, link.delivered) == (2, 1, 0)
    s.kernel.resume(c)
    s.run()
    assert log == [2]
    assert c.state.value == "waiting"  # (mypy narrowed c.state to SUSPENDED above)
    assert link.delivered == 1


def test_reader_suspended_and_resumed_in_its_wait_is_woken_by_the_next_message(
        tmp_path: Path) -> None:
    """A reader suspended and resumed before any message came still waits in its read; the
    next message readies it, and it reads that message."""
    log: list[Any] = []
    s, c, link = _system(tmp_path, {"log": log})
    s.run()
    s.kernel.suspend(c)
    assert c.state is TaskState.SUSPENDED
    s.kernel.resume(c)
    assert c.state.value == "waiting"  # (mypy narrowed c.state to SUSPENDED above)
    s.msgmgr.deliver(link, 7)
    assert c.state.value == "ready" and s.kernel.ready_tasks() == [c]
    s.run()
    assert log == [7] and c.state.value == "waiting"
    assert (link.sent, link.overwritten, link.delivered) == (1, 0, 1)


def test_message_before_the_read_timeout_cancels_that_timeout(tmp_path: Path) -> None:
    log: list[Any] = []
    s, c, link = _system(tmp_path, {"log": log, "timeout": 1.0})
    s.run(until=0.5)
    s.msgmgr.deliver(link, "x")
    s.run(until=3.0)
    # the second read began at 0.5 and timed out at 1.5; the first read's timer (due at 1.0)
    # was cancelled by the message
    assert log == ["x", ("timeout", 1.5)]
    assert c.timer is None


class _Scheduled(Instrument):
    def __init__(self) -> None:
        self.names: list[str] = []

    def task_scheduled(self, task: TaskEntry) -> None:
        self.names.append(task.name)


def test_instruments_hear_the_messages_and_the_wake_up(tmp_path: Path) -> None:
    log: list[Any] = []
    s, _c, link = _system(tmp_path, {"log": log})
    counters, sched = Counters(), _Scheduled()
    s.kernel.add_instrument(counters)
    s.kernel.add_instrument(sched)
    s.msgmgr.deliver(link, 1)
    s.msgmgr.deliver(link, 2)  # overwrites 1 before C runs
    s.run()
    assert log == [2]
    assert counters.sent[link.name] == 2
    assert counters.overwritten[link.name] == 1
    assert counters.delivered[link.name] == 1
    assert sched.names == ["C"]
    s.kernel.remove_instrument(counters)
    s.kernel.remove_instrument(sched)
    s.msgmgr.deliver(link, 3)  # the hot path again
    s.run()
    assert log == [2, 3] and (link.sent, link.overwritten, link.delivered) == (3, 1, 2)


class _Blocked(Instrument):
    def __init__(self) -> None:
        self.seen: list[tuple[str, str]] = []

    def task_blocked(self, task: TaskEntry) -> None:
        self.seen.append((task.name, task.state.value))


async def sleeper(ctx: TaskContext, cmd: Any) -> None:
    await ctx.sleep(1.0)
    await ctx.read(0)


async def boss(ctx: TaskContext, cmd: Any) -> None:
    await ctx.invoke(0, "go")
    await ctx.done(0)


def test_an_instrument_hears_every_block_once_with_the_state_it_waits_in(
        tmp_path: Path) -> None:
    """The kernel tells ``task_blocked`` when a step ends in a wait: a sleep, a read, an
    invoke's completion (the reads no longer tell it themselves)."""
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    s.execute(f"install -m0 --code={M}:idle P")
    s.execute(f"install -m0i1 --code={M}:sleeper C P")
    s.execute(f"install -m0o1 --code={M}:boss B C")
    blocked = _Blocked()
    s.kernel.add_instrument(blocked)
    s.invoke("B", None, priority=20)
    s.run(until=0.5)
    # B invoked C (owning it at once) and waits for its completion; C sleeps
    assert blocked.seen == [("B", "waiting"), ("C", "asleep")]
    s.run(until=2.0)
    assert blocked.seen[2:] == [("C", "waiting")]  # C's read
    s.msgmgr.deliver(s.tsktab.get("C").in_ports[0].link, 1)
    s.run(until=3.0)
    assert len(blocked.seen) == 3  # C returned, B's done() returned: nobody waits again
    s.kernel.remove_instrument(blocked)
    s.invoke("B", None, priority=20)   # a second round: C sleeps, reads, returns again
    s.run(until=5.0)
    s.msgmgr.deliver(s.tsktab.get("C").in_ports[0].link, 2)
    s.run(until=6.0)
    assert len(blocked.seen) == 3  # a removed instrument hears of no more blocks
    assert s.tsktab.get("C").completions == 2


def test_an_instrument_hears_links_installed_after_it_and_queued_links(tmp_path: Path) -> None:
    """An instrument hears of the messages on links installed after it, newest-wins and
    queued; once removed it hears of nothing more, and the links count the same."""
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    counters = Counters()
    s.kernel.add_instrument(counters)
    s.execute(f"install -m0 --code={M}:idle P")
    s.execute(f"install -m0 --code={M}:idle Q")
    s.execute(f"install -m0i2 --queue=Q=4 --code={M}:reader2 C P Q")
    c = s.tsktab.get("C")
    newest, queued = c.in_ports[0].link, c.in_ports[1].link
    log: list[Any] = []
    s.invoke("C", {"log": log}, priority=20)
    s.run(until=0.0)
    for v in (1, 2):
        s.msgmgr.deliver(newest, v)
        s.msgmgr.deliver(queued, -v)
    s.run()
    assert log == [2, -1, -2]
    assert counters.sent[newest.name] == 2 and counters.overwritten[newest.name] == 1
    assert counters.delivered[newest.name] == 1 and counters.delivered[queued.name] == 2
    s.kernel.remove_instrument(counters)
    s.msgmgr.deliver(queued, -3)
    s.msgmgr.deliver(newest, 3)
    s.run()
    assert log == [2, -1, -2, 3, -3]
    assert (newest.sent, newest.delivered, queued.sent, queued.delivered) == (3, 2, 3, 3)
    assert counters.sent[newest.name] == 2 and counters.delivered[queued.name] == 2


async def reader2(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        cmd["log"].append(await ctx.read(0))
        while ctx.pending(1):
            cmd["log"].append(await ctx.read("Q"))


async def port_reader(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    for port in cmd["ports"]:
        try:
            cmd["log"].append(await ctx.read(port))
        except MessageError as exc:
            cmd["log"].append(str(exc))


def test_read_finds_a_port_by_index_or_name_and_names_a_bad_one(tmp_path: Path) -> None:
    """A port is an index or a source name, nothing else: a bad index, an unknown name, or a
    bool, float or list is a MessageError naming it."""
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    s.execute(f"install -m0 --code={M}:idle P")
    s.execute(f"install -m0 --code={M}:idle Q")
    s.execute(f"install -m0i2 --code={M}:port_reader C P Q")
    c = s.tsktab.get("C")
    p, q = c.in_ports[0].link, c.in_ports[1].link
    log: list[Any] = []
    ports: list[Any] = [1, "Q", "P", 0, -1, 2, "X", [0], True, 1.0, 1]
    s.invoke("C", {"log": log, "ports": ports}, priority=20)
    for _ in ports:  # a message on both before each read
        s.msgmgr.deliver(p, "p")
        s.msgmgr.deliver(q, "q")
        s.run()
    assert log[:4] == ["q", "q", "p", "p"]
    assert log[4] == "task C has no input port -1 (it has 2: P, Q)"
    assert log[5] == "task C has no input port 2 (it has 2: P, Q)"
    assert log[6] == "task C has no input from 'X' (inputs: P, Q)"
    assert log[7] == "task C: an input port is an index or a source name, not [0]"
    assert log[8] == "task C: an input port is an index or a source name, not True"
    assert log[9] == "task C: an input port is an index or a source name, not 1.0"
    assert log[10] == "q"


async def slow_reader(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    while True:
        cmd["log"].append(await ctx.read(cmd.get("port", 0)))
        await ctx.sleep(cmd["slow"])


def test_latency_is_measured_for_the_messages_sent_while_an_instrument_listens(
        tmp_path: Path) -> None:
    """A latency instrument hears of each message sent while it listens, with the time from
    its sending to its reading; a message sent before it was added is delivered all the same
    (and counted by the link) but not measured, newest-wins and queued links alike."""
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    s.execute(f"install -m0 --code={M}:idle P")
    s.execute(f"install -m0 --code={M}:idle Q")
    s.execute(f"install -m0i1 --code={M}:slow_reader C P")
    s.execute(f"install -m0i1 --queue=Q=4 --code={M}:slow_reader F Q")
    c_log: list[Any] = []
    f_log: list[Any] = []
    s.invoke("C", {"log": c_log, "slow": 1.0}, priority=20)
    s.invoke("F", {"log": f_log, "slow": 1.0}, priority=20)
    s.run(until=0.0)
    newest, queued = s.msgtab.find("P", "C"), s.msgtab.find("Q", "F")
    s.msgmgr.deliver(newest, 1)   # before the instrument: read at once, not measured
    s.msgmgr.deliver(queued, -1)  # idem
    s.msgmgr.deliver(queued, -2)  # waits in the queue, not measured
    latency, counters = Latency(), Counters()
    s.kernel.add_instrument(latency)
    s.kernel.add_instrument(counters)
    s.msgmgr.deliver(queued, -3)  # measured: sent at 0, read at 2 (after -2 at 1)
    s.run(until=0.5)
    s.msgmgr.deliver(newest, 2)   # measured: sent at 0.5, read at 1
    s.run(until=2.5)
    assert (c_log, f_log) == ([1, 2], [-1, -2, -3])
    assert sorted(latency.samples) == [0.5, 2.0]
    assert counters.delivered == {newest.name: 1, queued.name: 1}
    assert (newest.sent, newest.delivered, queued.sent, queued.delivered) == (2, 2, 3, 3)
    s.msgmgr.deliver(newest, 3)   # measured, but the instrument goes before it is read
    s.kernel.remove_instrument(latency)
    s.run(until=3.5)
    assert c_log == [1, 2, 3] and sorted(latency.samples) == [0.5, 2.0]


def test_a_message_to_a_reader_already_woken_leaves_it_in_its_place(tmp_path: Path) -> None:
    """Two readers of one priority woken in turn run in that order, however many messages
    reach the first before it runs (a woken reader is readied once); each reads the newest."""
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=tmp_path)
    s.execute(f"install -m0 --code={M}:idle P")
    s.execute(f"install -m0i1 --code={M}:reader A P")
    s.execute(f"install -m0i1 --code={M}:reader B P")
    log: list[Any] = []
    for name in ("A", "B"):
        s.invoke(name, {"log": log}, priority=20)
    s.run(until=0.0)
    to_a, to_b = s.msgtab.find("P", "A"), s.msgtab.find("P", "B")
    scheduled = _Scheduled()
    s.kernel.add_instrument(scheduled)
    s.msgmgr.deliver(to_a, "a1")
    s.msgmgr.deliver(to_b, "b1")
    s.msgmgr.deliver(to_a, "a2")  # A is ready already: it stays ahead of B
    assert [t.name for t in s.kernel.ready_tasks()] == ["A", "B"]
    s.run()
    assert log == ["a2", "b1"]
    assert scheduled.names == ["A", "B"]
    assert (to_a.sent, to_a.overwritten, to_a.delivered) == (2, 1, 1)
