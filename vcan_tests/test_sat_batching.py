"""The communications manager's outgoing batches on real time, with a hand-driven clock: how long
a batch waits, and how a saturated kernel (one idle for less than BUSY_IDLE_SHARE of a batch
delay) sends its newest-wins batches less often while messages that must arrive keep the short
delay."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from chcos.comm.batching import (
    BATCH_DELAY,
    BUSY_BATCH_DELAY,
    BUSY_BATCH_DELAY_MAX,
    BUSY_IDLE_SHARE,
    Batches,
)
from chcos.comm.codec import LinkMessage, MessageKind, decode_batch, encode
from chcos.kernel.timers import Timer


class _Clock:
    virtual = False

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


class _Kernel:
    """The scheduler protocol with timers fired by hand (:meth:`fire`)."""

    def __init__(self) -> None:
        self.clock = _Clock()
        self.timers: list[Timer] = []
        self.idle_time = 0.0

    def add_idle_hook(self, hook: Callable[[], None]) -> None:
        raise AssertionError("not used here")

    def call_later(self, delay: float, callback: Callable[[], None]) -> Timer:
        tm = Timer(self.clock.t + delay, callback, None)
        self.timers.append(tm)
        return tm

    def interrupt(self, handler: Callable[..., None], *args: Any) -> None:
        raise AssertionError("not used here")

    def armed(self) -> list[float]:
        """The deadlines of the timers still armed, relative to now."""
        return [round(tm.deadline - self.clock.t, 9) for tm in self.timers if not tm.cancelled]

    def fire(self) -> None:
        """Move the clock to the first armed timer (if it is not past it) and run it."""
        tm = min((tm for tm in self.timers if not tm.cancelled), key=lambda tm: tm.deadline)
        self.timers.remove(tm)
        self.clock.t = max(self.clock.t, tm.deadline)
        tm.callback()

    def work(self, seconds: float) -> None:
        """The kernel runs tasks for ``seconds``."""
        self.clock.t += seconds

    def idle(self, seconds: float) -> None:
        """The kernel waits ``seconds`` for work, as Kernel._idle_wait counts it."""
        self.clock.t += seconds
        self.idle_time += seconds


class _Link:
    def __init__(self) -> None:
        self.sent: list[tuple[float, str, list[Any], MessageKind]] = []
        self.clock: _Clock | None = None

    def publish(self, key: str, payload: bytes, *, priority: int, kind: Any,
                express: bool | None = None) -> None:
        assert self.clock is not None
        self.sent.append((self.clock.t, key, [m.value for m in decode_batch(payload)], kind))


def _msg(lid: int, value: Any, kind: MessageKind = MessageKind.SENSORY) -> bytes:
    return encode(LinkMessage(kind, "A", "B", lid, 10, 1, 0, value))


@pytest.fixture
def batches() -> tuple[Batches, _Kernel, _Link]:
    k, link = _Kernel(), _Link()
    link.clock = k.clock
    return Batches(k, link, lambda text: None), k, link


def test_a_saturated_kernel_sends_newest_wins_batches_at_the_busy_delay(
        batches: tuple[Batches, _Kernel, _Link]) -> None:
    b, k, link = batches
    b.add("m/1", True, True, 1, _msg(1, 1.0), 10)
    assert k.armed() == [BATCH_DELAY]             # not known to be busy: the short delay
    b.add("m/1", True, True, 1, _msg(1, 2.0), 10)
    k.fire()                                      # no idle during the whole delay: busy
    assert link.sent == [(BATCH_DELAY, "m/1", [2.0], MessageKind.SENSORY)]
    assert b.busy
    b.add("m/1", True, True, 1, _msg(1, 3.0), 10)
    assert k.armed() == [BUSY_BATCH_DELAY]
    # a message that must arrive does not wait for the busy delay: the timer is armed short
    b.add("m/1", False, False, 2, _msg(2, "go", MessageKind.COMMAND), 10)
    assert k.armed() == [BATCH_DELAY]
    k.fire()
    assert {(tuple(v), kind) for _t, _k, v, kind in link.sent[1:]} == {
        ((3.0,), MessageKind.SENSORY), (("go",), MessageKind.COMMAND)}
    assert b.busy                                 # still never idle
    # brief waits for a timer due within microseconds (a sensor sampled faster than it is
    # served) leave it saturated: the next newest-wins batch still waits the busy delay
    for _ in range(4):
        b.on_idle()
        k.idle(BATCH_DELAY * BUSY_IDLE_SHARE / 5)
        k.work(BATCH_DELAY / 10)
    b.add("m/1", True, True, 1, _msg(1, 4.0), 10)
    assert b.busy and k.armed() == [BUSY_BATCH_DELAY]
    k.fire()
    assert link.sent[-1][2] == [4.0] and b.busy
    # idle for a while since that batch left (the kernel had nothing to do): not busy, the
    # next newest-wins message waits the short delay again
    b.on_idle()
    k.idle(BATCH_DELAY * BUSY_IDLE_SHARE)
    b.add("m/1", True, True, 1, _msg(1, 5.0), 10)
    assert not b.busy and k.armed() == [BATCH_DELAY]


def test_a_kernel_idle_for_its_share_of_the_delay_is_not_busy(
        batches: tuple[Batches, _Kernel, _Link]) -> None:
    b, k, link = batches
    b.add("m/1", True, True, 1, _msg(1, 1.0), 10)
    b.on_idle()             # real time: newest-wins sensory batches wait for their timer
    k.idle(BATCH_DELAY * BUSY_IDLE_SHARE)
    assert link.sent == []
    k.fire()
    assert not b.busy and len(link.sent) == 1
    b.add("m/1", True, True, 1, _msg(1, 2.0), 10)
    assert k.armed() == [BATCH_DELAY]
    # just under the share idle during a delay: busy
    b.on_idle()
    k.idle(BATCH_DELAY * BUSY_IDLE_SHARE * 0.9)
    k.fire()
    assert b.busy and len(link.sent) == 2
    b.add("m/1", True, True, 1, _msg(1, 3.0), 10)
    assert k.armed() == [BUSY_BATCH_DELAY]


def test_a_kernel_saturated_for_long_sends_ever_less_often_up_to_the_longest_delay(
        batches: tuple[Batches, _Kernel, _Link]) -> None:
    """While the kernel stays saturated the newest-wins delay doubles with each batch, up to
    BUSY_BATCH_DELAY_MAX; one batch delay with idle enough starts again from the short delay."""
    b, k, link = batches
    delays = []
    for i in range(6):
        b.add("m/1", True, True, 1, _msg(1, float(i)), 10)
        delays += k.armed()
        k.fire()                                  # never idle: busy
    assert BUSY_BATCH_DELAY * 4 == BUSY_BATCH_DELAY_MAX
    assert delays == [BATCH_DELAY, BUSY_BATCH_DELAY, BUSY_BATCH_DELAY * 2,
                      BUSY_BATCH_DELAY_MAX, BUSY_BATCH_DELAY_MAX, BUSY_BATCH_DELAY_MAX]
    assert [v for _t, _k, v, _kind in link.sent] == [[float(i)] for i in range(6)]
    # a window idle for more than a quarter of it: not busy, the short delay again, and the
    # next saturated stretch starts from BUSY_BATCH_DELAY
    b.add("m/1", True, True, 1, _msg(1, 6.0), 10)
    b.on_idle()
    k.idle(BUSY_BATCH_DELAY_MAX * BUSY_IDLE_SHARE * 1.1)
    k.fire()
    assert not b.busy
    delays = []
    for i in range(3):
        b.add("m/1", True, True, 1, _msg(1, 7.0 + i), 10)
        delays += k.armed()
        k.fire()
    assert delays == [BATCH_DELAY, BUSY_BATCH_DELAY, BUSY_BATCH_DELAY * 2]


def test_on_virtual_time_going_idle_sends_everything_and_ends_the_saturation(
        batches: tuple[Batches, _Kernel, _Link]) -> None:
    """Virtual time: the idle waits take no time (idle_time stays 0), so going idle itself
    ends a saturation, and everything waiting leaves then."""
    b, k, link = batches
    k.clock.virtual = True
    b.add("m/1", True, True, 1, _msg(1, 1.0), 10)
    k.fire()                                      # never idle: busy
    b.add("m/1", True, True, 1, _msg(1, 2.0), 10)
    assert b.busy and k.armed() == [BUSY_BATCH_DELAY]
    b.on_idle()
    assert not b.busy and k.armed() == [] and [v for _t, _k, v, _kd in link.sent] == [[1.0],
                                                                                      [2.0]]
    b.add("m/1", True, True, 1, _msg(1, 3.0), 10)
    assert k.armed() == [BATCH_DELAY]


def test_the_kernel_counts_its_idle_waits_on_real_time() -> None:
    """Kernel.idle_time, which the batches read: the time its idle waits took on a real-time
    clock (here one driven by hand: each idle wait moves it to the deadline), not the time it
    ran tasks or timers."""
    import threading

    from chcos.kernel.clock import Clock
    from chcos.kernel.scheduler import Kernel

    class HandClock(Clock):
        virtual = False

        def __init__(self) -> None:
            self.t = 0.0

        def now(self) -> float:
            return self.t

        def idle(self, wake: threading.Event, deadline: float | None) -> None:
            assert deadline is not None
            self.t = max(self.t, deadline)

    clock = HandClock()
    k = Kernel(clock)

    def busy() -> None:
        clock.t += 0.003      # a timer callback that runs for 3 ms

    k.call_later(0.010, busy)
    k.call_later(0.020, k.stop)
    k.run()
    assert clock.t == pytest.approx(0.020)
    assert k.idle_time == pytest.approx(0.017)   # 10 ms, then 7 ms after the 3 ms of work
