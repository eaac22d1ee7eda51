"""Kernel: priority order, FCFS ties, virtual time, timers, interrupts, semaphores, suspend."""

from __future__ import annotations

import threading
import types
from collections.abc import Coroutine, Generator
from typing import Any

import pytest

from chcos.errors import KernelError
from chcos.kernel.clock import RealClock, VirtualClock
from chcos.kernel.instrument import Counters, Instrument
from chcos.kernel.scheduler import BLOCK, YIELD, Kernel
from chcos.kernel.sem import Semaphore
from chcos.tables.tasks import TaskEntry, TaskState


@types.coroutine
def checkpoint() -> Generator[Any, Any, None]:
    yield YIELD


@types.coroutine
def sleep(k: Kernel, dt: float) -> Generator[Any, Any, None]:
    t = k.current
    assert t is not None
    t.timer = k.call_later(dt, lambda: k.wake(t, t.prio))
    k.block(t, TaskState.ASLEEP)
    yield BLOCK


def spawn(k: Kernel, name: str, coro: Coroutine[Any, Any, Any], prio: int) -> TaskEntry:
    t = TaskEntry(tid=0, name=name, machine=0, level=1, func=lambda *a: None)  # type: ignore
    t.coro = coro
    k.ready(t, prio)
    return t


def test_highest_priority_runs_first_and_ties_are_fifo() -> None:
    k = Kernel(VirtualClock())
    order: list[str] = []

    async def body(name: str) -> None:
        order.append(name)

    spawn(k, "low", body("low"), 1)
    spawn(k, "mid-a", body("mid-a"), 5)
    spawn(k, "high", body("high"), 9)
    spawn(k, "mid-b", body("mid-b"), 5)
    k.run()
    assert order == ["high", "mid-a", "mid-b", "low"]


def test_yield_lets_higher_and_equal_priority_run_but_not_lower() -> None:
    k = Kernel(VirtualClock())
    order: list[str] = []

    async def looping(name: str, n: int) -> None:
        for i in range(n):
            order.append(f"{name}{i}")
            await checkpoint()

    spawn(k, "a", looping("a", 3), 5)
    spawn(k, "b", looping("b", 3), 5)
    spawn(k, "z", looping("z", 2), 1)
    k.run()
    assert order == ["a0", "b0", "a1", "b1", "a2", "b2", "z0", "z1"]


def test_virtual_sleep_is_exact_and_ordered() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    woke: list[tuple[str, float]] = []

    async def sleeper(name: str, dt: float) -> None:
        await sleep(k, dt)
        woke.append((name, clock.now()))

    spawn(k, "late", sleeper("late", 2.5), 1)
    spawn(k, "early", sleeper("early", 0.75), 1)
    spawn(k, "mid", sleeper("mid", 1.25), 1)
    k.run()
    assert woke == [("early", 0.75), ("mid", 1.25), ("late", 2.5)]
    assert clock.now() == 2.5


def test_run_until_stops_at_that_time_and_periodic_timer_is_drift_free() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    ticks: list[float] = []
    k.every(0.1, lambda: ticks.append(clock.now()))
    k.run(until=1.0)
    assert clock.now() == 1.0
    assert len(ticks) == 10
    assert ticks[-1] == pytest.approx(1.0)
    k.run(until=2.0)
    assert len(ticks) == 20


def test_failing_timer_callback_is_recorded_and_kernel_goes_on() -> None:
    k = Kernel(VirtualClock())
    done: list[int] = []

    def bad() -> None:
        raise RuntimeError("boom")

    k.call_later(0.1, bad)
    k.call_later(0.2, lambda: done.append(1))
    k.run()
    assert done == [1]
    assert any("boom" in e for e in k.irq_errors)


def test_interrupt_from_another_thread_wakes_an_idle_real_clock_kernel() -> None:
    k = Kernel(RealClock())
    got = threading.Event()
    seen: list[str] = []

    def handler(what: str) -> None:
        seen.append(what)
        got.set()
        k.stop()

    runner = threading.Thread(target=k.run)
    runner.start()
    k.interrupt(handler, "sensor")
    assert got.wait(5)
    runner.join(5)
    assert not runner.is_alive()
    assert seen == ["sensor"]


def test_kernel_refuses_to_run_twice() -> None:
    k = Kernel(VirtualClock())
    errors: list[Exception] = []

    async def reenter() -> None:
        try:
            k.run()
        except KernelError as exc:
            errors.append(exc)

    spawn(k, "t", reenter(), 1)
    k.run()
    assert errors and "already running" in str(errors[0])


def test_semaphore_serves_waiters_in_order() -> None:
    k = Kernel(VirtualClock())
    sem = Semaphore(k, 0)
    got: list[str] = []

    async def waiter(name: str) -> None:
        await sem.wait()
        got.append(name)

    async def signaller() -> None:
        await sleep(k, 1.0)
        for _ in range(3):
            sem.signal()

    for n in ("w1", "w2", "w3"):
        spawn(k, n, waiter(n), 5)
    spawn(k, "s", signaller(), 1)
    k.run()
    assert got == ["w1", "w2", "w3"]
    assert sem.count == 0 and sem.waiting == 0


def test_suspend_keeps_wakeups_until_resume() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    woke: list[float] = []

    async def sleeper() -> None:
        await sleep(k, 1.0)
        woke.append(clock.now())

    t = spawn(k, "t", sleeper(), 5)
    k.run(until=0.5)
    k.suspend(t)
    k.run(until=3.0)
    assert woke == [] and t.state is TaskState.SUSPENDED
    k.resume(t)
    k.run()
    assert woke == [3.0]


def test_instruments_see_steps_and_only_when_installed() -> None:
    k = Kernel(VirtualClock())
    c = Counters()
    k.add_instrument(c)

    async def body() -> None:
        await checkpoint()

    spawn(k, "x", body(), 3)
    k.run()
    assert c.steps["x"] == 2


def test_foreign_await_is_an_error_of_that_task_only() -> None:
    k = Kernel(VirtualClock())
    ended: list[tuple[str, str]] = []
    k.set_end_handler(lambda t, how, v: ended.append((t.name, how)))

    @types.coroutine
    def alien() -> Generator[Any, Any, None]:
        yield "not a chcos trap"

    async def bad() -> None:
        await alien()

    async def good() -> None:
        await checkpoint()

    spawn(k, "bad", bad(), 5)
    spawn(k, "good", good(), 5)
    k.run()
    assert ("bad", "error") in ended and ("good", "return") in ended


class PriorityChecker(Instrument):
    """Asserts the stepping task has the highest priority among ready ones."""

    def __init__(self, k: Kernel) -> None:
        self.k = k
        self.violations = 0

    def before_step(self, task: TaskEntry) -> None:
        ready = self.k.ready_priorities()
        if ready and ready[0] > task.prio:
            self.violations += 1


def test_priority_checker_instrument_on_mixed_load() -> None:
    k = Kernel(VirtualClock())
    chk = PriorityChecker(k)
    k.add_instrument(chk)

    async def worker(n: int, dt: float) -> None:
        for _ in range(n):
            await sleep(k, dt)
            await checkpoint()

    for i in range(6):
        spawn(k, f"w{i}", worker(5, 0.1 * (i + 1)), i * 10)
    k.run()
    assert chk.violations == 0
