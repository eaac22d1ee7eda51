"""server - the live page of ``chcos view`` and ``chcos run --view``: aiohttp on its own asyncio
loop in its own thread.

Routes (on 127.0.0.1 unless told otherwise):

``GET /``                  the page (static HTML/JS/CSS from ``chcos/viewer/static``, no build)
``GET /api/snapshot``      one JSON snapshot (see :meth:`Snapshotter.take`); ``?since=N`` adds
                           the events numbered above N, ``?svg=0`` leaves the drawing out
``GET /api/stream``        server-sent events: the first message is the whole state
                           (``{"type": "snapshot", "state": ...}``), every later one a JSON merge
                           patch of it (``{"type": "delta", "patch": ...}``), one per ``period``
                           (default 0.1 s), each with the events the client has not seen yet; the
                           drawing is resent only when it changed, at most once per ``svg_period``
                           unless the structure (statuses, owners, priorities, marks) changed
``GET /api/map.svg|.dot|.txt``  the current map drawn as SVG, graphviz dot or text
``GET /api/session``       who this browser session is logged in as, and its command token
``POST /api/login``        ``{"user": ..., "password": ...}`` (JSON only): a session cookie
                           (HttpOnly, SameSite=Strict) and a per-session command token
``POST /api/logout``       ends the session
``POST /api/command``      ``{"line": "setpri -9 C1 B1"}`` with header ``X-CHCOS-Token``: setpri
                           or invoke, run through :meth:`System.execute` (the CLI's parser and
                           checks); ``{"ok": true, "answer": ...}`` or ``{"ok": false, "error":
                           ...}`` with a 4xx status saying why

Security. Every request's ``Host`` must be this server's own address (``127.0.0.1:PORT``, or
``localhost:PORT`` on loopback) and an ``Origin``, when sent, the same: a page from another site,
also one reached through DNS rebinding, can neither read nor command. Logins and commands
(read-only without ``users``; session cookie and token; setpri and invoke only) are
:mod:`chcos.viewer.commands`. Wrong logins are slowed down per client address and per user
name, each attempt counted before its password is checked
(:class:`chcos.north.auth.LoginThrottle`: after a few, each further attempt waits longer,
answered ``429`` with ``Retry-After`` meanwhile); a JSON body nested too deeply to parse is
answered ``400``.

The cell is never slowed by the page: snapshots are taken on the viewer's thread at the viewer's
rate, only while a page is connected, by reading the tables (torn reads accepted, see
:mod:`chcos.viewer.snapshot`); the kernel only pays for the event hook. A client that stops
reading is dropped once its stream has not drained for ``stall_timeout`` seconds or more than
``max_buffer`` bytes wait for it, and its buffers go with it.
"""

from __future__ import annotations

import asyncio
import json
import logging
import ssl
import threading
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from aiohttp import web

from chcos import resources
from chcos.comm.config import is_loopback
from chcos.serving.auth import LoginThrottle
from chcos.serving.guard import (
    MAX_BODY,
    REQUEST_TIMEOUT,
    ConnectionGate,
    bound_port,
    connection_cap,
    http_limits,
    serve_http,
    throttle_library_logs,
)
from chcos.serving.loopthread import LoopThread
from chcos.system.textview import render_text
from chcos.viewer import ViewerError
from chcos.viewer.commands import PageCommands
from chcos.viewer.graph import Live, render_dot, render_svg
from chcos.viewer.history import History
from chcos.viewer.snapshot import (
    SAME,
    EventLog,
    Snapshotter,
    merge_diff,
    stream_state,
    structure_key,
)

if TYPE_CHECKING:
    from chcos.serving.auth import Users
    from chcos.system.embedded import System

log = logging.getLogger("chcos.viewer")
STATIC = resources.path("chcos.viewer", "static")
#: Events a newly connected page receives from before it connected.
HISTORY = 200
#: Concurrent connections the view takes (less if the descriptor limit is low: see
#: :func:`chcos.north.guard.connection_cap`).
MAX_CONNECTIONS = 128
def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=str, separators=(",", ":"))


class Viewer:
    """The live view of ``system`` served on ``host:port`` (port 0: a free one) from a
    background thread. :meth:`start` raises ViewerError if the server cannot start; ``url`` is
    where the page is. ``events`` is the EventLog to show (default: the one already listening
    on the kernel, so the page also shows what happened before it started, else a new one).
    ``users`` are the accounts that may log in and command (None: read-only)."""

    def __init__(self, system: System, host: str = "127.0.0.1", port: int = 0, *,
                 period: float = 0.1, events: EventLog | None = None,
                 users: Users | None = None, implicit: bool = False,
                 svg_period: float = 1.0, stall_timeout: float = 5.0,
                 max_buffer: int = 1 << 20, ssl_context: ssl.SSLContext | None = None,
                 login_throttle: LoginThrottle | None = None,
                 history: History | None = None, max_connections: int | None = None) -> None:
        if period <= 0:
            raise ViewerError(f"snapshot period {period} s: must be positive")
        if stall_timeout <= 0 or max_buffer <= 0:
            raise ViewerError("stall_timeout and max_buffer must be positive")
        if ssl_context is None and not is_loopback(host):
            raise ViewerError(f"viewer on {host}: an address off loopback needs TLS "
                              "(a certificate and key)")
        self.system = system
        self.host = host
        self.port = port
        self.ssl_context = ssl_context
        self.scheme = "https" if ssl_context is not None else "http"
        self.period = period
        self.svg_period = svg_period
        self.stall_timeout = stall_timeout
        self.max_buffer = max_buffer
        self.users = users
        #: each device's recent values (sparklines on the page, /api/history.csv)
        self.history = history or History()
        self.snapshots = Snapshotter(system, events, implicit)
        self.events = self.snapshots.events
        self.implicit = implicit
        self._service = LoopThread("chcos-viewer")
        self._tick: asyncio.Condition | None = None
        # the newest state and the patch from the one before it (shared by every stream)
        self._state: dict[str, Any] | None = None
        self._patch: Any = SAME
        self._prev: dict[str, Any] | None = None
        self._svg: tuple[Any, float, str] | None = None  # (structure, when, svg)
        self.login_throttle = login_throttle or LoginThrottle()
        #: the cap, deadlines and counts of this server's connections
        self.gate = ConnectionGate("view", max_connections or connection_cap(MAX_CONNECTIONS))
        self.commands = PageCommands(system, users, secure=ssl_context is not None,
                                     throttle=self.login_throttle)
        self._clients = 0
        self._count = threading.Condition()
        self.dropped = 0
        self.sent_bytes = 0
        self._stopping = False
        self._listener: asyncio.AbstractServer

    @property
    def read_only(self) -> bool:
        """True when nobody can log in: the page only shows."""
        return self.commands.read_only

    @property
    def url(self) -> str:
        """The page's address (valid once started)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"{self.scheme}://{host}:{self.port}/"

    @property
    def clients(self) -> int:
        """Pages connected to the stream now."""
        return self._clients

    def wait_clients(self, pred: Callable[[int], bool], timeout: float) -> bool:
        """Wait until ``pred(clients)`` holds (True) or ``timeout`` seconds pass (False)."""
        with self._count:
            return self._count.wait_for(lambda: pred(self._clients), timeout)

    def _set_clients(self, delta: int) -> None:
        with self._count:
            self._clients += delta
            self._count.notify_all()

    # ---- life cycle -------------------------------------------------------------------------
    def start(self) -> Viewer:
        """Start serving on a background thread; returns self. Raises ViewerError if the
        address cannot be bound or the viewer already runs."""
        if self._service.running:
            raise ViewerError("viewer already started")
        try:
            self._service.start(self._serve)
        except Exception as exc:
            raise ViewerError(f"cannot serve on {self.host}:{self.port}: {exc}") from exc
        return self

    def stop(self) -> None:
        """Close every stream, stop the server and join its thread (no error if not started)."""
        self._service.stop(timeout=10)

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def app(self) -> web.Application:
        """The aiohttp application (routes, the Host/Origin guard, login throttling and the
        answer to bodies nested too deeply); also for test clients."""
        app = web.Application(middlewares=[http_limits(self.gate), self._guard, self._limits],
                              client_max_size=MAX_BODY)
        app.router.add_get("/", self._index)
        app.router.add_static("/static/", STATIC)
        app.router.add_get("/api/snapshot", self._snapshot)
        app.router.add_get("/api/stream", self._stream)
        app.router.add_get("/api/map.svg", self._map_svg)
        app.router.add_get("/api/map.dot", self._map_dot)
        app.router.add_get("/api/map.txt", self._map_txt)
        app.router.add_get("/api/history", self._history)
        app.router.add_get("/api/history.csv", self._history_csv)
        app.router.add_get("/api/session", self.commands.session)
        app.router.add_post("/api/login", self.commands.login)
        app.router.add_post("/api/logout", self.commands.logout)
        app.router.add_post("/api/command", self.commands.command)
        return app

    async def _serve(self, service: LoopThread) -> None:
        """The server's life on its loop: bind, serve until stopped, close every stream."""
        runner = await self._start()
        service.ready()
        assert self._tick is not None
        ticker = asyncio.create_task(self._ticker())
        await service.stopped()
        self._stopping = True
        ticker.cancel()
        async with self._tick:
            self._tick.notify_all()
        self._listener.close()
        await runner.cleanup()

    async def _start(self) -> web.AppRunner:
        self._tick = asyncio.Condition()
        throttle_library_logs()
        runner = web.AppRunner(self.app(), access_log=None, shutdown_timeout=1.0,
                               keepalive_timeout=REQUEST_TIMEOUT)
        await runner.setup()
        try:
            self._listener = await serve_http(runner, self.gate, self.host, self.port,
                                              self.ssl_context)
        except BaseException:
            await runner.cleanup()
            raise
        self.port = bound_port(self._listener)
        return runner

    # ---- the state the streams send ---------------------------------------------------------
    def _render(self, snap: dict[str, Any]) -> str:
        marks = {k: (v["kind"], v["detail"]) for k, v in snap["marks"].items()}
        live = Live(snap["rates"], snap["ages"], marks, frozenset(snap["map"]["frozen"]))
        return render_svg(snap["map"], live, self.implicit)

    def _next_state(self) -> dict[str, Any]:
        """A new state; the SVG is redrawn when the structure changed or once per svg_period."""
        snap = self.snapshots.take(None, svg=False)
        state = stream_state(snap)
        key = structure_key(state)
        now = time.monotonic()
        if self._svg is None or self._svg[0] != key or now - self._svg[1] >= self.svg_period:
            self._svg = (key, now, self._render(snap))
        state["svg"] = self._svg[2]
        return state

    async def _ticker(self) -> None:
        """Take one state a period while pages are connected and wake their streams."""
        assert self._tick is not None
        while True:
            await asyncio.sleep(self.period)
            await self._sample_history()
            if self._clients:
                try:
                    new = self._next_state()
                except ViewerError as exc:  # keep serving the last good state
                    new = {**(self._state or {}), "error": str(exc)}
                self._patch = SAME if self._state is None else merge_diff(self._state, new)
                self._prev, self._state = self._state, new
                async with self._tick:
                    self._tick.notify_all()

    async def _sample_history(self) -> None:
        """A history sample when one is due on the system's clock (pages open or not); the
        tables are read on a worker thread, never on the event loop."""
        now = self.system.kernel.clock.now() - self.events.t0
        if not self.history.due(now):
            return
        loop = asyncio.get_running_loop()
        try:
            doc = await loop.run_in_executor(None, self.snapshots.map_doc)
        except ViewerError:  # a torn read: the next tick samples
            return
        self.history.sample(now, doc["devices"])

    # ---- guard: Host and Origin -------------------------------------------------------------
    def _own_hosts(self) -> set[str]:
        port = self.port
        hosts = {f"{self.host}:{port}", f"[{self.host}]:{port}"}
        if is_loopback(self.host):
            hosts.add(f"localhost:{port}")
        return hosts

    @web.middleware
    async def _guard(self, request: web.Request,
                     handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                     ) -> web.StreamResponse:
        own = self._own_hosts()
        host = request.headers.get("Host", "")
        if host not in own:
            return web.json_response(
                {"ok": False, "error": f"Host {host!r} is not this viewer's address "
                                       f"({self.host}:{self.port}); refused (DNS rebinding?)"},
                status=421)
        origin = request.headers.get("Origin")
        if origin is not None and origin not in {f"{self.scheme}://{h}" for h in own}:
            return web.json_response(
                {"ok": False, "error": f"Origin {origin!r} is not this viewer "
                                       f"({self.scheme}://{host}); cross-site requests are "
                                       "refused"},
                status=403)
        return await handler(request)

    @web.middleware
    async def _limits(self, request: web.Request,
                      handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
                      ) -> web.StreamResponse:
        """A body the JSON parser cannot descend (nested too deeply) answered 400, not 500
        (wrong logins are throttled in the login handler: :class:`LoginThrottle`)."""
        try:
            return await handler(request)
        except RecursionError:
            return web.json_response(
                {"ok": False, "error": "request body nested too deeply: expected a flat JSON "
                                       "object"}, status=400)

    # ---- handlers ---------------------------------------------------------------------------
    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _snapshot(self, request: web.Request) -> web.Response:
        since = request.query.get("since")
        try:
            since_n = int(since) if since is not None else None
            snap = self.snapshots.take(since_n, svg=request.query.get("svg", "1") != "0")
        except ValueError:
            return web.json_response({"error": f"since={since!r}: not a whole number"},
                                     status=400)
        except ViewerError as exc:
            return web.json_response({"error": str(exc)}, status=503)
        return web.json_response(snap, dumps=_dumps)

    async def _map_svg(self, request: web.Request) -> web.Response:
        doc = self.snapshots.map_doc()
        return web.Response(text=render_svg(doc), content_type="image/svg+xml")

    async def _map_dot(self, request: web.Request) -> web.Response:
        doc = self.snapshots.map_doc()
        return web.Response(text=render_dot(doc), content_type="text/vnd.graphviz")

    async def _history(self, request: web.Request) -> web.Response:
        return web.json_response(self.history.as_json(), dumps=_dumps)

    async def _history_csv(self, request: web.Request) -> web.Response:
        return web.Response(text=self.history.as_csv(), content_type="text/csv",
                            headers={"Content-Disposition":
                                     'attachment; filename="chcos-history.csv"'})

    async def _map_txt(self, request: web.Request) -> web.Response:
        return web.Response(text=render_text(self.snapshots.map_doc()) + "\n")

    async def _write(self, request: web.Request, resp: web.StreamResponse, data: bytes) -> bool:
        """Send ``data`` to one stream; False (and the connection aborted, its buffers freed)
        if the client has stopped reading."""
        transport = request.transport
        if transport is None or transport.is_closing():
            return False
        if transport.get_write_buffer_size() > self.max_buffer:
            transport.abort()
            self.dropped += 1
            return False
        try:
            await asyncio.wait_for(resp.write(data), self.stall_timeout)
        except TimeoutError:
            transport.abort()
            self.dropped += 1
            return False
        self.sent_bytes += len(data)
        return True

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        assert self._tick is not None
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache"})
        await resp.prepare(request)
        self._set_clients(+1)
        seen = max(0, self.events.last_seq - HISTORY)
        try:
            try:
                state = self._next_state()
            except ViewerError as exc:
                state = {**(self._state or {}), "error": str(exc)}
            self._state = self._state or state
            msg: dict[str, Any] = {"type": "snapshot", "state": state}
            while not self._stopping:
                events = self.events.since(seen)
                if events:
                    seen = events[-1].seq
                msg["events"] = [e.as_dict() for e in events]
                if not await self._write(request, resp, f"data: {_dumps(msg)}\n\n".encode()):
                    break
                sent = state
                async with self._tick:
                    await self._tick.wait()
                state = self._state or sent
                if sent is self._prev and state is self._state:
                    patch = self._patch  # the shared patch fits: this client is up to date
                else:
                    patch = merge_diff(sent, state)
                msg = {"type": "delta", "patch": {} if patch is SAME else patch}
        except (ConnectionResetError, ViewerError):
            pass
        finally:
            self._set_clients(-1)
        return resp

def serve(system: System, host: str = "127.0.0.1", port: int = 0, *, period: float = 0.1,
          events: EventLog | None = None, users: Users | None = None,
          **kwargs: Any) -> Viewer:
    """Serve the live view of ``system`` from a background thread and return the running
    :class:`Viewer` (``.url``, ``.stop()``). Raises ViewerError if it cannot start."""
    return Viewer(system, host, port, period=period, events=events, users=users,
                  **kwargs).start()
