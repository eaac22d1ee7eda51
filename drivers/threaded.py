"""threaded - the reader/writer-thread plumbing shared by stream drivers (raw CAN, serial).

A subclass runs ``_read_loop`` (receive, hand readings to the host, call :meth:`_idle` whenever a
receive finds nothing) and ``_write_loop`` (take commands from ``_outbox`` under ``_cond``, set
``_sending`` while one is on its way). This base queues writes without blocking the caller, starts
and stops the two threads, and implements :meth:`settle` on top of the reader's idle count.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

from chcos.devspec import BusSpec, DeviceSpec
from drivers.base import Driver, DriverHost


class ThreadedDriver(Driver):
    """A driver with one reader and one writer thread (see the module doc)."""

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._cond = threading.Condition()
        self._outbox: deque[tuple[str, Any]] = deque()
        self._sending = False
        self._idle_gen = 0
        self._running = False
        self._threads: list[threading.Thread] = []

    def _read_loop(self) -> None:
        raise NotImplementedError

    def _write_loop(self) -> None:
        raise NotImplementedError

    def _start_threads(self, prefix: str) -> None:
        """Start the reader and the writer, named ``<prefix>-<bus>-rx``/``-tx``."""
        self._running = True
        for target, role in ((self._read_loop, "rx"), (self._write_loop, "tx")):
            t = threading.Thread(target=target, name=f"{prefix}-{self.bus.name}-{role}",
                                 daemon=True)
            self._threads.append(t)
            t.start()

    def _stop_threads(self) -> None:
        """Tell both threads to end and wait for them (a thread never waits for itself)."""
        with self._cond:
            self._running = False
            self._cond.notify_all()
        for t in self._threads:
            if t is not threading.current_thread():
                t.join(timeout=2.0)
        self._threads.clear()

    def _idle(self) -> None:
        """The reader found nothing to receive (wakes :meth:`settle`)."""
        with self._cond:
            self._idle_gen += 1
            self._cond.notify_all()

    def write(self, device: str, value: Any) -> None:
        """Queue ``value`` for actuator ``device``; the writer thread sends it (failures arrive
        later as ``host.fail``). Never blocks."""
        with self._cond:
            self._outbox.append((device, value))
            self._cond.notify_all()

    def settle(self, timeout: float) -> bool:
        """Wait until no command is queued or on its way and the reader has found nothing to
        receive twice after this call, so every frame or line that arrived before it has been
        handed to the host. True at once when stopped; False on timeout."""
        with self._cond:
            if not self._running:
                return True
            gen = self._idle_gen
            return self._cond.wait_for(
                lambda: not self._running or (self._idle_gen > gen + 1 and not self._outbox
                                               and not self._sending), timeout)
