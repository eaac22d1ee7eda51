"""Kernel: priority order, FCFS ties, virtual time, timers, interrupts, semaphores, suspend,
set_priority."""

from __future__ import annotations

import threading
import types
from collections.abc import Coroutine, Generator
from typing import Any

import pytest

from chcos.errors import HandlerError, KernelError
from chcos.kernel.clock import RealClock, VirtualClock
from chcos.kernel.instrument import Counters, Instrument
from chcos.kernel.scheduler import BLOCK, YIELD, End, Kernel
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
    k.start(t, coro, prio)
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


def test_a_requeued_or_suspended_ready_task_is_queued_once_in_its_new_place() -> None:
    k = Kernel(VirtualClock())
    order: list[str] = []

    async def body(name: str) -> None:
        order.append(name)

    a, b, c = (spawn(k, n, body(n), 5) for n in "abc")
    k.ready(a, 7)   # re-queued higher: first
    k.ready(b, 5)   # re-queued at the same priority: behind c now
    k.suspend(c)    # out of the queue until resumed
    assert k.ready_priorities() == [7, 5] and k.stats()["ready"] == 2
    k.run()
    assert order == ["a", "b"] and (a.steps, b.steps, c.steps) == (1, 1, 0)
    k.resume(c)
    assert k.ready_priorities() == [5]
    k.run()
    assert order == ["a", "b", "c"] and k.stats()["ready"] == 0
    assert k.steps == 3


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
    ended: list[tuple[str, End]] = []
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
    assert ("bad", End.ERROR) in ended and ("good", End.RETURN) in ended


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


# ---- collected errors surface (issue 14) ------------------------------------------------------
def test_check_raises_each_collected_handler_error_once_naming_the_handler() -> None:
    k = Kernel(VirtualClock())

    def bad_timer() -> None:
        raise RuntimeError("boom")

    def bad_irq(x: int) -> None:
        raise ValueError(f"bad value {x}")

    k.check()  # nothing collected: quiet
    k.call_later(0.1, bad_timer)
    k.interrupt(bad_irq, 7)
    k.run()
    with pytest.raises(HandlerError) as first:
        k.check()
    assert "bad_irq failed on the kernel thread: ValueError: bad value 7" in str(first.value)
    assert isinstance(first.value.__cause__, ValueError)
    assert any("1 more handler error" in n for n in first.value.__notes__)
    with pytest.raises(HandlerError, match="timer failed on the kernel thread: RuntimeError: "
                                           "boom") as second:
        k.check()
    assert isinstance(second.value.__cause__, RuntimeError)
    k.check()  # each raised once
    assert len(k.irq_errors) == 2  # the texts stay


class _Broken(Instrument):
    def __init__(self, hook: str) -> None:
        self.hook = hook
        self.calls = 0

    def before_step(self, task: TaskEntry) -> None:
        self.calls += 1
        if self.hook == "before_step":
            raise RuntimeError("instrument bug")

    def event(self, kind: str, detail: str) -> None:
        self.calls += 1
        if self.hook == "event":
            raise RuntimeError("instrument bug")


def test_failing_instrument_is_removed_and_logged_and_the_kernel_runs_on(
        caplog: pytest.LogCaptureFixture) -> None:
    k = Kernel(VirtualClock())
    broken = _Broken("before_step")
    counters = Counters()
    k.add_instrument(broken)
    k.add_instrument(counters)
    order: list[str] = []

    async def body(name: str) -> None:
        order.append(name)
        await checkpoint()
        order.append(name + "'")

    a = spawn(k, "a", body("a"), 5)
    b = spawn(k, "b", body("b"), 4)
    with caplog.at_level("ERROR", logger="chcos.kernel.instrument"):
        k.run()
    assert order == ["a", "a'", "b", "b'"]          # every task ran to its end
    assert a.state is not TaskState.CURRENT and b.state is not TaskState.CURRENT
    assert k.current is None
    assert broken.calls == 1                          # removed after its first failure
    assert broken not in k.instruments and counters in k.instruments
    assert counters.steps == {"a": 2, "b": 2}         # the others still heard every step
    assert [(i, h) for i, h, _ in k.dropped_instruments] == [(broken, "before_step")]
    assert "instrument bug" in caplog.text and "removed" in caplog.text


def test_failing_event_instrument_does_not_break_the_caller() -> None:
    k = Kernel(VirtualClock())
    broken = _Broken("event")
    counters = Counters()
    k.add_instrument(broken)
    k.add_instrument(counters)
    k.event("install", "A1")
    k.event("install", "A2")
    assert counters.events == [("install", "A1"), ("install", "A2")]
    assert broken.calls == 1 and broken not in k.instruments


def test_wake_ends_a_wait_through_the_unwait_its_layer_left() -> None:
    """The kernel knows timers, not ports or links: whoever blocks a task leaves ``unwait``."""
    k = Kernel(VirtualClock())
    undone: list[str] = []
    t: TaskEntry | None = None

    @types.coroutine
    def wait_for_something() -> Generator[Any, Any, Any]:
        me = k.current
        assert me is not None
        me.unwait = lambda task: undone.append(task.name)
        k.block(me, TaskState.WAITING)
        return (yield BLOCK)

    got: list[Any] = []

    async def body() -> None:
        got.append(await wait_for_something())

    t = spawn(k, "w", body(), 3)
    k.run()
    assert t.state is TaskState.WAITING and undone == []
    k.suspend(t)
    k.resume(t)
    assert t.state is TaskState.WAITING  # back to what it waited for
    k.wake(t, 3, "value")
    k.run()
    assert undone == ["w"] and got == ["value"] and t.unwait is None


@pytest.mark.parametrize("then", ["block", "yield", "return", "raise"])
def test_a_task_cancelled_in_its_own_step_ends_preempted_after_it(then: str) -> None:
    """A cancellation of the running task (Lifecycle.cancel with it current) ends its
    activation as soon as the step is over, however the step ended; an interrupt that came
    during the step (here, one waking it) runs after that end and cannot carry it on."""
    k = Kernel(VirtualClock())
    ends: list[tuple[str, End, str]] = []
    k.set_end_handler(lambda t, how, v: ends.append((t.name, how, type(v).__name__)))
    trail: list[str] = []

    async def body() -> None:
        t = k.current
        assert t is not None
        await checkpoint()  # (cancelled in a later step than its first)
        k.interrupt(lambda: k.wake(t, 5, "woken"))  # queued before the cancellation
        k.cancel(t, "by itself")
        try:
            if then == "block":
                k.block(t, TaskState.WAITING)
                await _block()
            elif then == "yield":
                await checkpoint()
            elif then == "raise":
                raise ValueError("after its cancellation")
            trail.append("carried on")
        finally:
            trail.append("finally")

    t = spawn(k, "T", body(), 5)
    other = spawn(k, "U", _count(trail), 1)  # a lower task: runs once T is out of the way
    k.run()
    assert ends[0][:2] == ("T", End.PREEMPTED)
    assert ends[0][2] == {"block": "NoneType", "yield": "NoneType", "return": "NoneType",
                          "raise": "ValueError"}[then]
    assert trail == (["carried on"] if then == "return" else []) + ["finally", "U"]
    assert t.coro is None and not t.cancelling and other.coro is None
    assert t.state is TaskState.SUSPENDED  # (the wake-up found no activation to run)


@types.coroutine
def _block() -> Generator[Any, Any, None]:
    yield BLOCK


async def _count(trail: list[str]) -> None:
    trail.append("U")


# ---- Kernel.set_priority: the one way a priority changes outside Kernel.ready --------------
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
