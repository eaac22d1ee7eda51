"""loopthread - an asyncio service run on its own event loop in a background thread.

The north-side servers (:mod:`chcos.north.opcua`, :mod:`chcos.north.modbus_facade`) and the live
view (:mod:`chcos.viewer.server`) serve a running system from a thread of their own, so the
kernel never waits on a client. :class:`LoopThread` is that scaffolding, once: a new event loop
in a daemon thread runs the service's ``serve`` coroutine, which sets itself up, calls
:meth:`LoopThread.ready`, waits for :meth:`LoopThread.stopped` and cleans up. :meth:`start`
returns once the service is ready - or raises what its set-up raised, so a port that cannot be
bound is the caller's error at once; :meth:`stop` asks the coroutine to finish and joins the
thread. A failure after the service was ready is logged (it has no caller left to raise to).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Coroutine
from typing import Any

log = logging.getLogger(__name__)

Serve = Callable[["LoopThread"], Coroutine[Any, Any, None]]
"""The service: set up, ``lt.ready()``, ``await lt.stopped()``, clean up."""


class LoopThreadError(RuntimeError):
    """A LoopThread used out of order (started twice)."""


class LoopThread:
    """Runs one ``serve`` coroutine on a new event loop in the daemon thread ``name``."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._stop: asyncio.Event | None = None
        self._stopping = False

    @property
    def stopping(self) -> bool:
        """True once :meth:`stop` was called (until the next :meth:`start`); any thread."""
        return self._stopping

    @property
    def running(self) -> bool:
        """True between a successful :meth:`start` and :meth:`stop`."""
        return self._thread is not None

    def start(self, serve: Serve) -> None:
        """Run ``serve(self)`` in a new thread; return once it called :meth:`ready`. Raises
        whatever ``serve`` raised before that (the thread is joined first), LoopThreadError if
        already started."""
        if self._thread is not None:
            raise LoopThreadError(f"{self.name}: already started")
        self._ready.clear()
        self._error = None
        self._stopping = False
        thread = threading.Thread(target=self._main, args=(serve,), name=self.name, daemon=True)
        self._thread = thread
        thread.start()
        self._ready.wait()
        if self._error is not None:
            thread.join(timeout=10)
            self._thread = None
            raise self._error

    def ready(self) -> None:
        """Called by the service (on its loop) once it serves: :meth:`start` returns."""
        self._ready.set()

    async def stopped(self) -> None:
        """Wait (on the loop) until :meth:`stop` is called."""
        assert self._stop is not None
        await self._stop.wait()

    def call(self, fn: Callable[..., Any], *args: Any) -> bool:
        """Schedule ``fn(*args)`` on the loop from any thread; False when the loop is not
        running (not started, or closed), so nothing was scheduled."""
        loop = self.loop
        if loop is None or loop.is_closed():
            return False
        loop.call_soon_threadsafe(fn, *args)
        return True

    def stop(self, timeout: float = 10.0) -> None:
        """Ask the service to finish and join its thread (at most ``timeout`` s). No error if
        it is not running."""
        thread, stop = self._thread, self._stop
        if thread is None:
            return
        self._stopping = True
        if stop is not None:
            self.call(stop.set)
        thread.join(timeout=timeout)
        self._thread = None

    def _main(self, serve: Serve) -> None:
        loop = asyncio.new_event_loop()
        self.loop = loop
        try:
            loop.run_until_complete(self._run(serve))
        finally:
            self._ready.set()
            loop.run_until_complete(loop.shutdown_default_executor())
            loop.close()

    async def _run(self, serve: Serve) -> None:
        self._stop = asyncio.Event()
        try:
            await serve(self)
            if not self._ready.is_set():
                raise LoopThreadError(f"{self.name}: the service ended before it was ready")
        except BaseException as exc:
            if not self._ready.is_set():
                self._error = exc
            else:
                log.exception("%s failed", self.name)


__all__ = ["LoopThread", "LoopThreadError", "Serve"]
