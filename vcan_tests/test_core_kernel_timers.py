"""Kernel: periodic timers' catch-up policy (missed periods skipped and counted), stop(), and
instruments installed during a step, all on the virtual clock."""

from __future__ import annotations

import random
import types
from collections.abc import Coroutine, Generator
from typing import Any

import pytest

from chcos.kernel.clock import VirtualClock
from chcos.kernel.instrument import Instrument
from chcos.kernel.scheduler import BLOCK, YIELD, Kernel
from chcos.tables.tasks import TaskEntry


@types.coroutine
def checkpoint() -> Generator[Any, Any, None]:
    yield YIELD


def spawn(k: Kernel, name: str, coro: Coroutine[Any, Any, Any], prio: int) -> TaskEntry:
    t = TaskEntry(tid=0, name=name, machine=0, level=1, func=lambda *a: None)  # type: ignore
    k.start(t, coro, prio)
    return t


def test_periodic_timer_on_time_skips_nothing() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    tm = k.every(0.001, lambda: None)
    k.run(until=0.5)
    assert tm.count == 500 and tm.skipped == 0
    assert k.skipped_periods == 0 and k.stats()["skipped_periods"] == 0


def test_stalled_callback_makes_a_periodic_timer_skip_to_the_next_boundary() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    ticks: list[float] = []
    tm = k.every(0.001, lambda: ticks.append(clock.now()))
    k.call_at(0.0025, lambda: clock.advance(0.0057))  # a callback that takes 5.7 ms
    k.run(until=0.012)
    # 3 ms was due at 8.2 ms: it fires once, late; 4..8 ms are skipped; 9 ms is on time again
    assert ticks == pytest.approx([0.001, 0.002, 0.0082, 0.009, 0.010, 0.011, 0.012])
    assert tm.skipped == 5
    assert k.skipped_periods == 5
    assert k.stats()["skipped_periods"] == 5
    assert tm.deadline == pytest.approx(0.013)  # still on the drift-free grid


def test_20khz_poll_after_a_long_step_fires_once_and_lets_tasks_run() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    polls: list[float] = []
    tm = k.every(0.00005, lambda: polls.append(clock.now()))
    order: list[str] = []

    @types.coroutine
    def sleep(dt: float) -> Generator[Any, Any, None]:
        t = k.current
        assert t is not None
        t.timer = k.call_at(clock.now() + dt, lambda: k.wake(t, 1))
        yield BLOCK

    async def stalls() -> None:
        await sleep(0.00102)
        clock.advance(0.05)  # a step that takes 50 ms (a stalled machine)
        order.append("stalled")
        await checkpoint()
        order.append(f"after stall, {len(polls)} polls")

    spawn(k, "slow", stalls(), 1)
    k.run(until=0.0511)
    # 20 polls before the stall, then ONE for the 999 periods that passed during it, then the
    # boundaries at 51.05 and 51.10 ms; the task's next step came right after the late poll
    assert len(polls) == 23
    assert polls[20] == pytest.approx(0.05102)
    assert polls[21:] == pytest.approx([0.05105, 0.0511])
    assert tm.skipped == 999 == k.skipped_periods
    assert order == ["stalled", "after stall, 21 polls"]


def test_skipped_periods_add_up_over_timers_and_cancelled_timers_stop() -> None:
    clock = VirtualClock()
    k = Kernel(clock)
    a = k.every(0.01, lambda: None)
    b = k.every(0.004, lambda: None)
    k.call_at(0.005, lambda: clock.advance(0.02))  # now 25 ms
    k.run(until=0.03)
    # a: due 10 ms, fired at 25 ms, skipped 20 ms, next 30 ms; b: due 8 ms, fired at 25 ms,
    # skipped 12, 16, 20, 24 ms, next 28 ms
    assert (a.skipped, b.skipped) == (1, 4)
    assert k.skipped_periods == 5
    b.cancel()
    k.run(until=0.05)
    assert k.stats()["timers"] == 1  # only a is pending


def test_stats_counts_steps_ready_tasks_and_errors() -> None:
    k = Kernel(VirtualClock())

    async def body() -> None:
        await checkpoint()

    spawn(k, "x", body(), 3)
    spawn(k, "y", body(), 2)
    assert k.stats()["ready"] == 2

    def bad() -> None:
        raise RuntimeError("boom")

    k.call_later(0.1, bad)
    k.run()
    st = k.stats()
    assert st["steps"] == 4 and st["ready"] == 0 and st["handler_errors"] == 1


def test_stop_from_a_task_returns_after_that_step_and_run_resumes_later() -> None:
    k = Kernel(VirtualClock())
    log: list[str] = []

    async def stopper() -> None:
        log.append("stopper")
        k.stop()
        await checkpoint()
        log.append("stopper again")

    async def other() -> None:
        log.append("other")

    spawn(k, "s", stopper(), 5)
    spawn(k, "o", other(), 1)
    k.run()
    assert log == ["stopper"]
    k.run()
    assert log == ["stopper", "stopper again", "other"]


def test_stop_before_run_does_not_stop_the_next_run() -> None:
    k = Kernel(VirtualClock())
    log: list[str] = []

    async def body() -> None:
        log.append("ran")

    k.stop()
    spawn(k, "x", body(), 1)
    k.run()
    assert log == ["ran"]


class _After(Instrument):
    def __init__(self) -> None:
        self.seen: list[str] = []

    def after_step(self, task: TaskEntry) -> None:
        self.seen.append(task.name)


class _Before(Instrument):
    def before_step(self, task: TaskEntry) -> None:
        pass


@pytest.mark.parametrize("with_before", [False, True])
def test_an_instrument_added_by_a_step_hears_whole_steps_from_the_next_one_on(
        with_before: bool) -> None:
    k = Kernel(VirtualClock())
    if with_before:  # the step runs on the kernel's slow path
        k.add_instrument(_Before())
    inst = _After()

    async def installer() -> None:
        k.add_instrument(inst)
        await checkpoint()

    async def other() -> None:
        await checkpoint()

    spawn(k, "i", installer(), 5)
    spawn(k, "o", other(), 1)
    k.run()
    # not the installing step (it did not hear it begin); the installer's last step, then
    # o's two steps: each heard once, whether or not another instrument watched steps already
    assert inst.seen == ["i", "o", "o"]


def test_the_system_map_and_its_text_view_show_the_kernel_stats() -> None:
    from pathlib import Path

    from chcos.devices.spec import DeviceMap
    from chcos.system.embedded import System
    from chcos.system.textview import render_text

    clock = VirtualClock()
    s = System(DeviceMap(), clock=clock, machines=[0], base_dir=Path("."))
    s.kernel.every(0.001, lambda: None)
    s.kernel.call_at(0.0025, lambda: clock.advance(0.0057))
    s.kernel.run(until=0.012)
    doc = s.sysmgr.map_doc()
    assert doc["kernel"]["skipped_periods"] == 5
    assert "5 timer periods skipped (late)" in render_text(doc)


def test_a_late_periodic_timer_moves_to_the_first_boundary_after_now() -> None:
    """Timers.fire on many late firings (seeded): the next deadline is the first
    period boundary after the firing time (or the one after it, when the firing time is
    within a nanosecond of a boundary), never one before; every boundary in between is
    counted as skipped, and the timer fires once per firing."""
    rng = random.Random(21)
    for _ in range(2000):
        _one_late_firing(rng)


def _one_late_firing(rng: random.Random) -> None:
    k = Kernel(VirtualClock())
    period = rng.choice([1e-5, 1e-3, 0.1, 1 / 3, 0.7, 2.5]) * rng.uniform(0.5, 2.0)
    fired: list[int] = []
    tm = k.call_at(rng.uniform(0.0, 5.0), lambda: fired.append(1), period)
    base = tm.base
    now = base + period * rng.uniform(0.0, 50.0)
    if rng.random() < 0.2:  # right on a boundary, or within a hair of one
        now = base + period * rng.randrange(1, 50) + rng.choice([0.0, 1e-12, -1e-12])
    k.timers.fire(now)
    assert fired == [1]
    c = tm.count

    def at(n: int) -> float:
        return round((base + n * period) * 1e9) / 1e9

    assert tm.deadline == at(c) > now
    assert c == 1 or at(c - 1) <= now + 1e-9  # not a boundary too far
    assert tm.skipped == k.skipped_periods == c - 1
