"""threaded - the reader/writer-thread plumbing shared by stream drivers (raw CAN, serial).

A subclass writes ``_read_loop`` (receive, hand readings to the host, call :meth:`_idle` whenever
a receive finds nothing) and ``_send`` (put one command on the wire); it may override
``_can_send`` to hold commands back (a serial port not open yet). This base queues writes without
blocking the caller, runs the writer thread, starts and stops both threads, counts bus errors, and
implements :meth:`settle` on top of the reader's idle count.
"""

from __future__ import annotations

import threading
from collections import Counter, deque
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
        self.error_counts: Counter[str] = Counter()

    def _read_loop(self) -> None:
        raise NotImplementedError

    def _send(self, device: str, value: Any) -> None:
        """Put one command on the wire (writer thread); report failures to the host."""
        raise NotImplementedError

    def _can_send(self) -> bool:
        """Whether a taken command may go now (checked under ``_cond``); default always."""
        return True

    def _write_loop(self) -> None:
        while True:
            with self._cond:
                self._cond.wait_for(lambda: bool(self._outbox) or not self._running)
                if not self._running:
                    return
                device, value = self._outbox.popleft()
                self._sending = True
                self._cond.wait_for(lambda: self._can_send() or not self._running)
                if not self._running:
                    self._sending = False
                    return
            try:
                self._send(device, value)
            finally:
                with self._cond:
                    self._sending = False
                    self._cond.notify_all()

    def _error(self, kind: str, detail: str) -> None:
        """Count and report a bus-level error (malformed frame, garbage line...)."""
        self.error_counts[kind] += 1
        self.host.error(self.bus.name, kind, detail)

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
