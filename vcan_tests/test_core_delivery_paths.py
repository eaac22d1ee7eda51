"""Message delivery off its inlined hot path: a reader that is suspended, that waits with a
read timeout, or that an instrument watches gets the same messages and counts as on the hot
path (virtual clock)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from chcos.devices.spec import DeviceMap
from chcos.errors import ReadTimeout
from chcos.kernel.clock import VirtualClock
from chcos.kernel.instrument import Counters, Instrument
from chcos.kernel.lifecycle import FrozenUnwait
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


def test_reader_suspended_and_resumed_in_its_wait_is_woken_on_the_hot_path(
        tmp_path: Path) -> None:
    """suspend() swaps a waiting reader's unwait for a FrozenUnwait (so a delivery's hot path,
    which tells a plain read by its unwait, leaves it alone); resume() gives the read its own
    back, so the next message readies it on the hot path again."""
    log: list[Any] = []
    s, c, link = _system(tmp_path, {"log": log})
    s.run()
    port = link.port
    assert c.unwait is port.unwait  # a plain read of the port
    s.kernel.suspend(c)
    assert isinstance(c.unwait, FrozenUnwait) and c.unwait is not port.unwait
    s.kernel.resume(c)
    assert c.unwait is port.unwait and c.state.value == "waiting"
    s.msgmgr.deliver(link, 7)
    assert c.state is TaskState.READY and c.unwait is None and port.waiter is None
    s.run()
    assert log == [7]


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
