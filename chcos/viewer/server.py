"""server - the live page of ``chcos view``: aiohttp on its own asyncio loop in its own thread.

Routes (all on 127.0.0.1 unless told otherwise):

``GET /``                  the page (static HTML/JS/CSS from ``chcos/viewer/static``, no build)
``GET /api/snapshot``      one JSON snapshot (see :meth:`Snapshotter.take`); ``?since=N`` adds
                           the events numbered above N, ``?svg=0`` leaves the drawing out
``GET /api/stream``        server-sent events: a snapshot every ``period`` seconds (default 0.1,
                           10 a second), each with the events the client has not seen yet
``GET /api/map.svg|.dot|.txt``  the current map drawn as SVG, graphviz dot or text
``POST /api/command``      ``{"line": "setpri -9 C1 B1"}``: setpri, invoke, suspend or resume,
                           run through :meth:`System.execute` (the CLI's parser and checks);
                           answers ``{"ok": true, "answer": ...}`` or ``{"ok": false, "error":
                           ...}`` with status 400 (refused or failed) or 403 (not allowed here)

The cell is never slowed by the page: snapshots are taken on the viewer's thread at the viewer's
rate, only while a page is connected, by reading the tables (torn reads accepted, see
:mod:`chcos.viewer.snapshot`); the kernel only pays for the event hook.
"""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aiohttp import web

from chcos import cmdline
from chcos.errors import ChcosError
from chcos.sysview import render_text
from chcos.viewer import ViewerError
from chcos.viewer.graph import render_dot, render_svg
from chcos.viewer.snapshot import EventLog, Snapshotter

if TYPE_CHECKING:
    from chcos.system import System

STATIC = Path(__file__).resolve().parent / "static"
#: Events a newly connected page receives from before it connected.
HISTORY = 200


def _dumps(obj: Any) -> str:
    return json.dumps(obj, default=str, separators=(",", ":"))


def allowed(req: cmdline.Request) -> bool:
    """True for the host commands the page may issue: setpri, invoke, suspend, resume."""
    if isinstance(req, cmdline.SetPri | cmdline.Invoke):
        return True
    return isinstance(req, cmdline.TaskOp) and req.op in ("suspend", "resume")


class Viewer:
    """The live view of ``system`` served on ``host:port`` (port 0: a free one) from a
    background thread. :meth:`start` raises ViewerError if the server cannot start; ``url`` is
    where the page is. ``events`` is the EventLog to show (default: the one already listening
    on the kernel, so the page also shows what happened before it started, else a new one)."""

    def __init__(self, system: System, host: str = "127.0.0.1", port: int = 0, *,
                 period: float = 0.1, events: EventLog | None = None,
                 allow_commands: bool = True, implicit: bool = False) -> None:
        if period <= 0:
            raise ViewerError(f"snapshot period {period} s: must be positive")
        self.system = system
        self.host = host
        self.port = port
        self.period = period
        self.allow_commands = allow_commands
        self.snapshots = Snapshotter(system, events, implicit)
        self.events = self.snapshots.events
        self._thread: threading.Thread | None = None
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop_evt: asyncio.Event | None = None
        self._tick: asyncio.Condition | None = None
        self._latest: dict[str, Any] | None = None
        self._clients = 0
        self._stopping = False

    @property
    def url(self) -> str:
        """The page's address (valid once started)."""
        return f"http://{self.host}:{self.port}/"

    @property
    def clients(self) -> int:
        """Pages connected to the stream now."""
        return self._clients

    # ---- life cycle -------------------------------------------------------------------------
    def start(self) -> Viewer:
        """Start serving on a background thread; returns self. Raises ViewerError if the
        address cannot be bound or the viewer already runs."""
        if self._thread is not None:
            raise ViewerError("viewer already started")
        self._thread = threading.Thread(target=self._main, name="chcos-viewer", daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join(timeout=10)
            self._thread = None
            raise ViewerError(f"cannot serve on {self.host}:{self.port}: "
                              f"{self._error}") from self._error
        return self

    def stop(self) -> None:
        """Close every stream, stop the server and join its thread (no error if not started)."""
        loop, evt = self._loop, self._stop_evt
        if self._thread is None or loop is None or evt is None:
            return
        if not loop.is_closed():
            loop.call_soon_threadsafe(evt.set)
        self._thread.join(timeout=10)
        self._thread = None

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _main(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        runner: web.AppRunner | None = None
        try:
            try:
                runner = loop.run_until_complete(self._start())
            except BaseException as exc:  # reported to start()
                self._error = exc
                return
            finally:
                self._ready.set()
            assert self._stop_evt is not None
            loop.run_until_complete(self._serve_until_stopped(runner))
        finally:
            loop.run_until_complete(loop.shutdown_default_executor())
            loop.close()

    async def _start(self) -> web.AppRunner:
        self._stop_evt = asyncio.Event()
        self._tick = asyncio.Condition()
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_static("/static/", STATIC)
        app.router.add_get("/api/snapshot", self._snapshot)
        app.router.add_get("/api/stream", self._stream)
        app.router.add_get("/api/map.svg", self._map_svg)
        app.router.add_get("/api/map.dot", self._map_dot)
        app.router.add_get("/api/map.txt", self._map_txt)
        app.router.add_post("/api/command", self._command)
        runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
        await runner.setup()
        try:
            site = web.TCPSite(runner, self.host, self.port)
            await site.start()
        except BaseException:
            await runner.cleanup()
            raise
        self.port = int(runner.addresses[0][1])
        return runner

    async def _serve_until_stopped(self, runner: web.AppRunner) -> None:
        assert self._stop_evt is not None and self._tick is not None
        ticker = asyncio.create_task(self._ticker())
        await self._stop_evt.wait()
        self._stopping = True
        ticker.cancel()
        async with self._tick:
            self._tick.notify_all()
        await runner.cleanup()

    async def _ticker(self) -> None:
        """Take one snapshot a period while pages are connected and wake their streams."""
        assert self._tick is not None
        while True:
            await asyncio.sleep(self.period)
            if self._clients:
                try:
                    self._latest = self.snapshots.take(None)
                except ViewerError as exc:  # keep serving the last good snapshot
                    self._latest = {**(self._latest or {}), "error": str(exc)}
                async with self._tick:
                    self._tick.notify_all()

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

    async def _map_txt(self, request: web.Request) -> web.Response:
        return web.Response(text=render_text(self.snapshots.map_doc()) + "\n")

    async def _stream(self, request: web.Request) -> web.StreamResponse:
        assert self._tick is not None
        resp = web.StreamResponse(headers={"Content-Type": "text/event-stream",
                                           "Cache-Control": "no-cache"})
        await resp.prepare(request)
        self._clients += 1
        seen = max(0, self.events.last_seq - HISTORY)
        try:
            snap = self.snapshots.take(None)
            self._latest = snap
            while not self._stopping:
                events = self.events.since(seen)
                if events:
                    seen = events[-1].seq
                payload = {**snap, "events": [e.as_dict() for e in events]}
                await resp.write(f"data: {_dumps(payload)}\n\n".encode())
                async with self._tick:
                    await self._tick.wait()
                snap = self._latest or snap
        except (ConnectionResetError, ViewerError):
            pass
        finally:
            self._clients -= 1
        return resp

    async def _command(self, request: web.Request) -> web.Response:
        if not self.allow_commands:
            return web.json_response({"ok": False, "error": "this viewer is read-only"},
                                     status=403)
        try:
            body = await request.json()
            line = body["line"]
            if not isinstance(line, str):
                raise TypeError("line must be a string")
        except (ValueError, KeyError, TypeError) as exc:
            return web.json_response(
                {"ok": False, "error": f'expected JSON {{"line": "setpri -9 C1 B1"}}: {exc}'},
                status=400)
        try:
            req = cmdline.parse(line)
        except ChcosError as exc:
            return web.json_response({"ok": False, "error": str(exc)}, status=400)
        if req is None or not allowed(req):
            return web.json_response(
                {"ok": False, "error": f"{line.split()[0] if line.split() else 'empty line'}: "
                                       "only setpri, invoke, suspend and resume may be issued "
                                       "from the viewer"}, status=403)
        loop = asyncio.get_running_loop()
        try:
            answer = await loop.run_in_executor(None, self.system.execute, req)
        except ChcosError as exc:
            return web.json_response({"ok": False, "error": str(exc)}, status=400)
        except TimeoutError:
            return web.json_response({"ok": False, "error": f"{line}: the kernel did not "
                                      "answer in time"}, status=504)
        return web.json_response({"ok": True, "answer": answer})


def serve(system: System, host: str = "127.0.0.1", port: int = 0, *, period: float = 0.1,
          events: EventLog | None = None, allow_commands: bool = True) -> Viewer:
    """Serve the live view of ``system`` from a background thread and return the running
    :class:`Viewer` (``.url``, ``.stop()``). Raises ViewerError if it cannot start."""
    return Viewer(system, host, port, period=period, events=events,
                  allow_commands=allow_commands).start()
