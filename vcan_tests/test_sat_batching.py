"""The communications manager's outgoing batches on real time, with a hand-driven clock: how long
a batch waits, and how a saturated kernel (one that never goes idle) sends its newest-wins
batches less often while messages that must arrive keep the short delay."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from chcos.comm.batching import BATCH_DELAY, BUSY_BATCH_DELAY, Batches
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
        """Move the clock to the first armed timer and run it."""
        tm = min((tm for tm in self.timers if not tm.cancelled), key=lambda tm: tm.deadline)
        self.timers.remove(tm)
        self.clock.t = tm.deadline
        tm.callback()


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
    b.on_idle()                                   # the kernel had nothing to do: not busy
    assert not b.busy
    b.add("m/1", True, True, 1, _msg(1, 4.0), 10)
    assert k.armed() == [BATCH_DELAY]


def test_a_kernel_that_went_idle_during_the_delay_is_not_busy(
        batches: tuple[Batches, _Kernel, _Link]) -> None:
    b, k, link = batches
    b.add("m/1", True, True, 1, _msg(1, 1.0), 10)
    b.on_idle()             # real time: newest-wins sensory batches wait for their timer
    assert link.sent == []
    k.fire()
    assert not b.busy and len(link.sent) == 1
    b.add("m/1", True, True, 1, _msg(1, 2.0), 10)
    assert k.armed() == [BATCH_DELAY]
