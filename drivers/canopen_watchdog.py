"""canopen_watchdog - heartbeat supervision of the ``canopen`` driver's nodes on a thread of its
own, so that a blocking SDO transfer on the I/O thread never delays the detection of a lost
node: a node whose last heartbeat is older than its ``heartbeat_timeout`` is declared lost
within that timeout plus the watchdog's slack (at most :data:`MAX_WAIT`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

#: the longest the watchdog sleeps when no deadline is nearer (s)
MAX_WAIT = 0.5


class HeartbeatWatchdog:
    """Runs ``check()`` (which returns the seconds to its next deadline) on its own thread,
    at every deadline and whenever :meth:`poke` says a supervised state changed."""

    def __init__(self, check: Callable[[], float], name: str) -> None:
        self._check = check
        self._name = name
        self._cond = threading.Condition()
        self._running = False
        self._poked = False
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the thread (once)."""
        self._running = True
        self._thread = threading.Thread(target=self._loop, name=self._name, daemon=True)
        self._thread.start()

    def poke(self) -> None:
        """Check again now (a heartbeat came back, a node was added to supervision)."""
        with self._cond:
            self._poked = True
            self._cond.notify_all()

    def stop(self) -> None:
        """End the thread and wait for it."""
        with self._cond:
            self._running = False
            self._cond.notify_all()
        t, self._thread = self._thread, None
        if t is not None and t is not threading.current_thread():
            t.join(timeout=2.0)

    def _loop(self) -> None:
        wait = 0.0
        while True:
            with self._cond:
                self._cond.wait_for(lambda: not self._running or self._poked,
                                    max(0.0, min(wait, MAX_WAIT)))
                if not self._running:
                    return
                self._poked = False
            started = time.monotonic()
            wait = self._check() - (time.monotonic() - started)
