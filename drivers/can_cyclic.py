"""can_cyclic - chcos' own cyclic CAN messages: a message with actuators and a cycle time keeps
the last command and sends it every cycle, as a real controller does (a receiving ECU drops a
command that is not repeated at its cycle).

Two senders with one interface (:class:`Cycle`: :meth:`~Cycle.update` with the message's new
payload, :meth:`~Cycle.stop`), chosen by the driver:

- :class:`ClockedCycle`, on the kernel clock (virtual time): a kernel timer per frame, each due
  one period after the previous was due (drift-free), the frame stamped (counter, checksum) and
  sent on the kernel thread;
- :class:`PeriodicCycle`, on real time: python-can's ``send_periodic`` with one frame per counter
  value (the whole counter cycle, checksums computed), so the interface's own periodic sender
  does the sending - the kernel's broadcast manager (``CAN_BCM``) on SocketCAN, python-can's
  drift-free thread elsewhere - and ``modify_data`` when the command changes: the sender keeps
  its place in the cycle, so the counter runs on.

The first command starts the cycle with a frame at once; a later one goes out with the next
frame due; :meth:`~Cycle.stop` (the driver stopping, after the shutdown's safe values) ends it,
as a controller switched off falls silent.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Callable
from typing import Any, Protocol

import can


class Cycle(Protocol):
    """A message sent every cycle (see the module doc)."""

    period: float

    def update(self, data: bytes) -> None:
        """The message's payload from now on (counter and checksum not yet in it)."""

    def stop(self) -> None:
        """End the cycle. Idempotent."""


class ClockedCycle:
    """A cyclic message on the kernel clock: ``at(when, fn)`` and ``now()`` are the driver
    host's; ``send(data)`` stamps and sends one frame of ``data`` on the kernel thread (True if
    it went out); ``paused()`` holds the frames back while it is true (a bus-off controller)."""

    def __init__(self, period: float, send: Callable[[bytes], bool],
                 at: Callable[[float, Callable[[], None]], None], now: Callable[[], float],
                 paused: Callable[[], bool] = lambda: False) -> None:
        self.period = period
        self._send = send
        self._at = at
        self._now = now
        self._paused = paused
        self._data: bytes | None = None
        self._running = True
        #: frames this cycle sent, and those it could not send
        self.sent = 0
        self.failed = 0

    def update(self, data: bytes) -> None:
        first = self._data is None
        self._data = data
        if first and self._running:
            self._fire(round(self._now(), 9))

    def _fire(self, due: float) -> None:
        if not self._running or self._data is None:
            return
        if not self._paused():
            if self._send(self._data):
                self.sent += 1
            else:
                self.failed += 1
        self._at(round(due + self.period, 9), lambda: self._fire(round(due + self.period, 9)))

    def stop(self) -> None:
        self._running = False


class PeriodicCycle:
    """A cyclic message on real time through python-can's ``send_periodic`` on ``bus`` (see the
    module doc); ``frames(data)`` gives one python-can message per counter value, in counter
    order (one without a counter). A send task that fails to start or change raises
    ``can.CanError`` to the caller."""

    def __init__(self, bus: can.BusABC, period: float,
                 frames: Callable[[bytes], list[can.Message]]) -> None:
        self.period = period
        self._bus = bus
        self._frames = frames
        self._task: Any = None

    def update(self, data: bytes) -> None:
        msgs = self._frames(data)
        if self._task is None:
            with warnings.catch_warnings():   # python-can warns of its thread fallback
                warnings.simplefilter("ignore")
                self._task = self._bus.send_periodic(msgs, self.period, store_task=True)
            return
        self._task.modify_data(msgs)

    def stop(self) -> None:
        task, self._task = self._task, None
        if task is not None:
            with contextlib.suppress(can.CanError, OSError):   # the bus is closing
                task.stop()
