"""Kernel.set_priority: the one way a task's priority changes outside Kernel.ready, for a ready,
a waiting and a suspended task; and the ownership rules (setpri, release, resetpri) through it."""

from __future__ import annotations

import types
from collections.abc import Coroutine, Generator
from typing import Any

from chcos.kernel.clock import VirtualClock
from chcos.kernel.scheduler import BLOCK, Kernel
from chcos.tables.tasks import TaskEntry, TaskState


@types.coroutine
def sleep(k: Kernel, dt: float) -> Generator[Any, Any, None]:
    t = k.current
    assert t is not None
    t.timer = k.call_later(dt, lambda: k.wake(t, t.prio))
    k.block(t, TaskState.ASLEEP)
    yield BLOCK


def spawn(k: Kernel, name: str, coro: Coroutine[Any, Any, Any], prio: int) -> TaskEntry:
    t = TaskEntry(tid=0, name=name, machine=0, level=1, func=lambda *a: None)  # type: ignore
    k.start(t, coro, prio)
    return t


def test_a_ready_task_is_requeued_at_its_new_priority() -> None:
    k = Kernel(VirtualClock())
    order: list[str] = []

    async def body(name: str) -> None:
        order.append(name)

    a, b = spawn(k, "a", body("a"), 5), spawn(k, "b", body("b"), 6)
    k.set_priority(a, 9)
    assert a.prio == 9 and k.ready_priorities() == [9, 6] and k.stats()["ready"] == 2
    k.run()
    assert order == ["a", "b"] and b.state is TaskState.SUSPENDED


def test_a_waiting_task_keeps_the_priority_for_its_wake_up() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    order: list[str] = []

    async def sleeper(name: str) -> None:
        await sleep(k, 1.0)
        order.append(name)

    a = spawn(k, "a", sleeper("a"), 3)
    spawn(k, "b", sleeper("b"), 5)
    k.run(until=0.5)
    assert a.state is TaskState.ASLEEP
    k.set_priority(a, 8)   # not queued: nothing to re-queue, the wake-up uses t.prio
    assert a.prio == 8 and k.ready_priorities() == []
    k.run()
    assert order == ["a", "b"] and clock.now() == 1.0


def test_a_suspended_task_resumes_at_the_new_priority() -> None:
    k = Kernel(VirtualClock())
    order: list[str] = []

    async def body(name: str) -> None:
        order.append(name)

    a = spawn(k, "a", body("a"), 2)
    spawn(k, "b", body("b"), 5)
    k.suspend(a)           # its ready entry kept as a wake-up at 2
    k.set_priority(a, 9)
    assert a.state is TaskState.SUSPENDED and k.ready_priorities() == [5]
    k.resume(a)
    assert k.ready_priorities() == [9, 5]
    k.run()
    assert order == ["a", "b"]
