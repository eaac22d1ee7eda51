"""guard - the limits every north-side server keeps against its clients: a cap on concurrent
connections well below the process's descriptor limit, read timeouts, refused and timed-out
connections counted and logged once per period, and the libraries' log of untrusted input
rate-limited the same way.

:class:`ConnectionGate` wraps an asyncio protocol factory (the live view's and the metrics'
aiohttp server, the Modbus facade's pymodbus server): a connection beyond the cap is closed as
soon as it is accepted; a connection that has not delivered a complete request within
``request_timeout`` seconds of connecting (or of its last answer: keep-alive) is closed - the
server marks a request complete with :meth:`ConnectionGate.hold` and answered with
:meth:`ConnectionGate.release`; a ``stream`` gate (Modbus) instead closes a connection that
sent nothing for ``idle_timeout`` seconds. The OPC UA server uses asyncua's own cap and
activation timeout, set from the same figures (:mod:`chcos.north.opcua`).

:func:`connection_cap` keeps every server's cap below its share of the descriptor limit
(``RLIMIT_NOFILE``) after :data:`RESERVED_FDS` descriptors are set aside for the drivers, the
link and the log files, so a flood of one server can neither starve the cell's own sockets and
files nor the other servers.

:func:`throttle_library_logs` sends what asyncua, pymodbus, aiohttp and asyncio log at warning
and above through the link's rate-limited log (:class:`chcos.comm.secret.Throttle`): one line
per cause per period with the count since the last, never a traceback.

Every figure is listed in ``docs/security.md``.
"""

from __future__ import annotations

import asyncio
import logging
import re
import resource
import threading
import time
from collections.abc import Callable
from typing import Any

from aiohttp import web

from chcos.comm.secret import Throttle

log = logging.getLogger("chcos.north")

#: Descriptors kept for the drivers, the link and the log files whatever the servers hold.
RESERVED_FDS = 256
#: The north-side servers sharing what is left (view, metrics, OPC UA, Modbus facade).
SERVERS = 4
#: Seconds a client has to send a complete request (HTTP headers) after connecting or after
#: its last answer, and to finish sending a request body.
REQUEST_TIMEOUT = 10.0
#: Seconds a TLS client has to complete its handshake.
HANDSHAKE_TIMEOUT = 10.0
#: Seconds a Modbus client may stay silent before its connection is closed.
IDLE_TIMEOUT = 60.0
#: Seconds between two log lines of one cause.
LOG_PERIOD = 10.0
#: Library loggers whose records are rate-limited (they log what untrusted clients sent).
LIBRARIES = ("asyncua", "pymodbus", "aiohttp", "asyncio")
#: Distinct causes kept per library before the rest are counted as one.
MAX_CAUSES = 100


def connection_cap(default: int) -> int:
    """``default``, or less: this server's share of the descriptor limit after
    RESERVED_FDS (at least 4)."""
    soft, _hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY:
        return default
    return max(4, min(default, (soft - RESERVED_FDS) // SERVERS))


class _Gated(asyncio.Protocol):
    """One connection through a gate: the server's own protocol, and its deadline."""

    def __init__(self, gate: ConnectionGate, inner: asyncio.BaseProtocol | None) -> None:
        self.gate = gate
        self.inner: Any = inner
        self.transport: asyncio.BaseTransport | None = None
        self.accepted = time.monotonic()
        self._timer: asyncio.TimerHandle | None = None
        self.peer = "?"

    # -- the deadline ---------------------------------------------------------------------
    def arm(self, seconds: float, why: str) -> None:
        self.disarm()
        self._timer = asyncio.get_running_loop().call_later(seconds, self._expire, why)

    def disarm(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _expire(self, why: str) -> None:
        self._timer = None
        if self.transport is not None and not self.transport.is_closing():
            self.gate.throttle.note(f"{self.gate.name}: connection closed: {why}",
                                    f"from {self.peer}")
            self.transport.abort()  # type: ignore[attr-defined]

    # -- asyncio.Protocol -----------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport
        peer = transport.get_extra_info("peername")
        self.peer = str(peer[0]) if isinstance(peer, tuple) and peer else str(peer)
        if self.inner is None:  # over the cap
            transport.abort()  # type: ignore[attr-defined]
            return
        self.gate._made(self)
        if self.gate.stream:
            self.arm(self.gate.idle_timeout, f"silent for {self.gate.idle_timeout:g} s")
        else:
            self.arm(self.gate.request_timeout,
                     f"no complete request within {self.gate.request_timeout:g} s")
        self.inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        if self.gate.stream and self._timer is not None:
            self.arm(self.gate.idle_timeout, f"silent for {self.gate.idle_timeout:g} s")
        self.inner.data_received(data)

    def eof_received(self) -> bool | None:
        eof = getattr(self.inner, "eof_received", None)
        if eof is None:
            return None
        result: bool | None = eof()
        return result

    def connection_lost(self, exc: Exception | None) -> None:
        self.disarm()
        self.gate._lost(self)
        if self.inner is not None and self.transport is not None:
            self.inner.connection_lost(exc)

    def pause_writing(self) -> None:
        if self.inner is not None:
            self.inner.pause_writing()

    def resume_writing(self) -> None:
        if self.inner is not None:
            self.inner.resume_writing()


class ConnectionGate:
    """Bounds the connections of server ``name`` (see the module doc): at most ``cap`` at
    once; ``stream`` (Modbus) closes a connection silent for ``idle_timeout`` s, otherwise
    (HTTP) one without a complete request ``request_timeout`` s after connecting or after its
    last answer. ``refused`` counts the connections closed at the cap; ``throttle`` holds the
    counts by cause (refused, timed out) and logs each cause once per LOG_PERIOD. ``open`` and
    ``peak``: connections now and at most."""

    def __init__(self, name: str, cap: int, *, stream: bool = False,
                 request_timeout: float = REQUEST_TIMEOUT, idle_timeout: float = IDLE_TIMEOUT,
                 handshake_timeout: float = HANDSHAKE_TIMEOUT) -> None:
        self.name = name
        self.cap = cap
        self.stream = stream
        self.request_timeout = request_timeout
        self.idle_timeout = idle_timeout
        self.handshake_timeout = handshake_timeout
        self.throttle = Throttle(log, LOG_PERIOD)
        self.refused = 0
        self.peak = 0
        self._lock = threading.Lock()
        self._open: set[_Gated] = set()        # connection made (handshake done)
        self._accepted: set[_Gated] = set()    # accepted, TLS handshake under way
        self._by_transport: dict[int, _Gated] = {}

    @property
    def open(self) -> int:
        """Connections held now (TLS handshakes under way included)."""
        with self._lock:
            return len(self._open) + len(self._accepted)

    def factory(self, inner: Callable[[], Any]) -> Callable[[], asyncio.Protocol]:
        """The protocol factory to give ``loop.create_server`` in place of ``inner``."""
        def make() -> asyncio.Protocol:
            now = time.monotonic()
            with self._lock:
                # a TLS handshake that failed never reaches connection_made (nor lost):
                # asyncio gave up on it after handshake_timeout
                self._accepted = {g for g in self._accepted
                                  if now - g.accepted < self.handshake_timeout + 5.0}
                full = len(self._open) + len(self._accepted) >= self.cap
                if full:
                    self.refused += 1
                else:
                    g = _Gated(self, None)
                    self._accepted.add(g)
                    self.peak = max(self.peak, len(self._open) + len(self._accepted))
            if full:
                self.throttle.note(f"{self.name}: connection refused at the cap of {self.cap} "
                                   "concurrent connections", "a client connected while full")
                return _Gated(self, None)
            g.inner = inner()
            return g
        return make

    def _made(self, g: _Gated) -> None:
        with self._lock:
            self._accepted.discard(g)
            self._open.add(g)
            if g.transport is not None:
                self._by_transport[id(g.transport)] = g

    def _lost(self, g: _Gated) -> None:
        with self._lock:
            self._accepted.discard(g)
            self._open.discard(g)
            if g.transport is not None:
                self._by_transport.pop(id(g.transport), None)

    def hold(self, transport: Any) -> None:
        """A complete request arrived on ``transport``: no deadline while it is served."""
        g = self._by_transport.get(id(transport))
        if g is not None:
            g.disarm()

    def release(self, transport: Any) -> None:
        """The request on ``transport`` was answered: the next must come within
        request_timeout (keep-alive)."""
        g = self._by_transport.get(id(transport))
        if g is not None and g.transport is not None and not g.transport.is_closing():
            g.arm(self.request_timeout, f"idle for {self.request_timeout:g} s after an answer")


#: Largest HTTP request body the view and the metrics read (logins and commands are small).
MAX_BODY = 64 * 1024

Handler = Callable[[web.Request], Any]


def http_limits(gate: ConnectionGate) -> Any:
    """The aiohttp middleware of a gated server: no deadline while a request is served, the
    body read within the gate's request_timeout (else 408, counted and logged once per
    period), the next request within request_timeout of the answer."""
    @web.middleware
    async def limits(request: web.Request, handler: Handler) -> web.StreamResponse:
        transport = request.transport
        gate.hold(transport)
        try:
            if request.body_exists:
                try:
                    await asyncio.wait_for(request.read(), gate.request_timeout)
                except TimeoutError:
                    gate.throttle.note(f"{gate.name}: request body not sent within "
                                       f"{gate.request_timeout:g} s", f"from {request.remote}")
                    return web.json_response({"ok": False, "error": "request body not sent in "
                                              f"{gate.request_timeout:g} s"}, status=408,
                                             headers={"Connection": "close"})
            response: web.StreamResponse = await handler(request)
            return response
        finally:
            gate.release(transport)
    return limits


async def serve_http(runner: web.AppRunner, gate: ConnectionGate, host: str, port: int,
                     ssl_context: Any = None) -> asyncio.AbstractServer:
    """Listen on ``host:port`` for the set-up ``runner``'s application through ``gate``
    (TLS handshakes bounded by its handshake_timeout). Raises OSError if it cannot bind."""
    loop = asyncio.get_running_loop()
    server = runner.server
    assert server is not None  # runner.setup() was awaited
    return await loop.create_server(
        gate.factory(server), host, port, ssl=ssl_context, reuse_address=True,
        ssl_handshake_timeout=gate.handshake_timeout if ssl_context is not None else None)


def bound_port(server: asyncio.AbstractServer) -> int:
    """The port ``server`` listens on."""
    return int(server.sockets[0].getsockname()[1])  # type: ignore[attr-defined]


class _LibraryLog(logging.Handler):
    """A library's records at warning and above, through a Throttle by cause: the logger and
    the message with its numbers blanked, at most MAX_CAUSES causes per library."""

    def __init__(self, throttle: Throttle) -> None:
        super().__init__(logging.WARNING)
        self.throttle = throttle
        self._causes: set[str] = set()

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
        except Exception:  # a record whose arguments do not fit its message
            text = str(record.msg)
        first = text.split("\n", 1)[0]
        cause = f"{record.name}: {re.sub(r'[0-9]+', 'N', first)[:60]}"
        lib = record.name.split(".", 1)[0]
        if cause not in self._causes:
            if sum(c.startswith(lib) for c in self._causes) >= MAX_CAUSES:
                cause = f"{lib}: other messages"
            self._causes.add(cause)
        if record.exc_info and record.exc_info[1] is not None:
            exc = record.exc_info[1]
            first += f" ({type(exc).__name__}: {str(exc)[:120]})"
        self.throttle.note(cause, first)


_installed: dict[str, _LibraryLog] = {}
_install_lock = threading.Lock()


def throttle_library_logs() -> Throttle:
    """Rate-limit the LIBRARIES' log in this process (once; see the module doc): their records
    no longer propagate as they are, each cause is logged once per LOG_PERIOD with a count.
    Returns the Throttle (its ``counts`` by cause)."""
    with _install_lock:
        if not _installed:
            throttle = Throttle(log, LOG_PERIOD)
            for name in LIBRARIES:
                logger = logging.getLogger(name)
                handler = _LibraryLog(throttle)
                logger.addHandler(handler)
                logger.propagate = False
                _installed[name] = handler
        return next(iter(_installed.values())).throttle


__all__ = ["HANDSHAKE_TIMEOUT", "IDLE_TIMEOUT", "MAX_BODY", "REQUEST_TIMEOUT", "RESERVED_FDS",
           "ConnectionGate", "bound_port", "connection_cap", "http_limits", "serve_http",
           "throttle_library_logs"]
