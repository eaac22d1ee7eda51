"""commands - the live page's logins and commands (``/api/session``, ``/login``, ``/logout``,
``/command`` of :mod:`chcos.viewer.server`).

The viewer is read-only unless it is given ``users`` (an operator credential,
:class:`chcos.north.auth.Users`); commands then need a logged-in session (an HttpOnly,
SameSite=Strict cookie) *and* its per-session token in the ``X-CHCOS-Token`` header, as JSON: a
cross-site form or ``text/plain`` POST is refused (CSRF). The page offers setpri and invoke
only (:data:`PAGE_COMMANDS`), and only to a role that may issue them (operator, supervisor); a
command runs through :meth:`System.execute` (the CLI's parser and checks) and a refusal answers
a 4xx status saying why, never 500.
"""

from __future__ import annotations

import asyncio
import hmac
import logging
import math
import secrets
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from aiohttp import web

from chcos.errors import Busy, ChcosError
from chcos.system import cmdline

if TYPE_CHECKING:
    from chcos.serving.auth import LoginThrottle, User, Users
    from chcos.system.embedded import System

log = logging.getLogger("chcos.viewer")
#: The commands the page offers at all (a role may allow fewer).
PAGE_COMMANDS = ("setpri", "invoke")
COOKIE = "chcos_session"
TOKEN_HEADER = "X-CHCOS-Token"
#: Sessions kept at once (the oldest is ended beyond this).
MAX_SESSIONS = 64


def command_name(req: cmdline.Request) -> str:
    """The host command a parsed request is (``setpri``, ``invoke``, ``suspend``...)."""
    if isinstance(req, cmdline.SetPri):
        return "setpri"
    if isinstance(req, cmdline.Invoke):
        return "invoke"
    if isinstance(req, cmdline.TaskOp):
        return req.op
    if isinstance(req, cmdline.Inject):
        return "inject"
    if isinstance(req, cmdline.ShowMap):
        return "map"
    return "install"


def allowed(req: cmdline.Request) -> bool:
    """True for the host commands the page may issue at all: setpri and invoke."""
    return command_name(req) in PAGE_COMMANDS


@dataclass
class Session:
    """One logged-in browser: its user and the token its commands must carry."""

    user: User
    token: str
    started: float


class PageCommands:
    """The sessions of ``users`` (None: read-only) on the page of ``system``, and the request
    handlers that log in, out and command. ``secure``: the session cookie is sent over TLS
    only."""

    def __init__(self, system: System, users: Users | None, *, secure: bool = False,
                 throttle: LoginThrottle | None = None) -> None:
        from chcos.serving.auth import LoginThrottle

        self.system = system
        self.users = users
        self.throttle = throttle or LoginThrottle()
        self.secure = secure
        self.sessions: OrderedDict[str, Session] = OrderedDict()

    @property
    def read_only(self) -> bool:
        """True when nobody can log in: the page only shows."""
        return self.users is None

    def session_of(self, request: web.Request) -> Session | None:
        sid = request.cookies.get(COOKIE)
        return None if sid is None else self.sessions.get(sid)

    async def session(self, request: web.Request) -> web.Response:
        s = self.session_of(request)
        if s is None:
            return web.json_response({"user": None, "read_only": self.read_only})
        return web.json_response(self._session_json(s))

    def _session_json(self, s: Session) -> dict[str, Any]:
        from chcos.serving.auth import ROLE_COMMANDS

        return {"user": s.user.name, "role": s.user.role, "token": s.token,
                "read_only": self.read_only,
                "commands": [c for c in PAGE_COMMANDS if c in ROLE_COMMANDS[s.user.role]]}

    @staticmethod
    def _json_only(request: web.Request) -> web.Response | None:
        if request.content_type != "application/json":
            return web.json_response(
                {"ok": False, "error": f"Content-Type {request.content_type!r}: expected "
                                       "application/json (forms and text/plain are refused)"},
                status=415)
        return None

    async def login(self, request: web.Request) -> web.Response:
        if self.users is None:
            return web.json_response({"ok": False, "error": "this viewer is read-only: it was "
                                      "started without operator credentials"}, status=403)
        bad = self._json_only(request)
        if bad is not None:
            return bad
        try:
            body = await request.json()
            name, password = body["user"], body["password"]
            if not isinstance(name, str) or not isinstance(password, str):
                raise TypeError("user and password must be strings")
        except (ValueError, KeyError, TypeError) as exc:
            return web.json_response({"ok": False, "error": 'expected JSON {"user": ..., '
                                      f'"password": ...}}: {exc}'}, status=400)
        client = request.remote or "?"
        wait = self.throttle.begin(client, name)  # counted before the check: see LoginThrottle
        if wait > 0:
            retry = max(1, math.ceil(wait))
            return web.json_response(
                {"ok": False, "error": f"too many wrong logins from {client} or for {name!r}: "
                                       f"try again in {retry} s"},
                status=429, headers={"Retry-After": str(retry)})
        loop = asyncio.get_running_loop()
        user = await loop.run_in_executor(None, self.users.check, name, password)
        self.throttle.end(client, name, user is not None)
        if user is None:
            return web.json_response({"ok": False, "error": "unknown user or wrong password"},
                                     status=401)
        sid, token = secrets.token_urlsafe(32), secrets.token_urlsafe(32)
        self.sessions[sid] = s = Session(user, token, time.monotonic())
        while len(self.sessions) > MAX_SESSIONS:
            self.sessions.popitem(last=False)
        resp = web.json_response({"ok": True, **self._session_json(s)})
        resp.set_cookie(COOKIE, sid, httponly=True, samesite="Strict", path="/",
                        secure=self.secure)
        return resp

    async def logout(self, request: web.Request) -> web.Response:
        sid = request.cookies.get(COOKIE)
        if sid is not None:
            self.sessions.pop(sid, None)
        resp = web.json_response({"ok": True})
        resp.del_cookie(COOKIE, path="/")
        return resp

    async def command(self, request: web.Request) -> web.Response:
        def refuse(status: int, error: str) -> web.Response:
            return web.json_response({"ok": False, "error": error}, status=status)

        if self.users is None:
            return refuse(403, "this viewer is read-only: it was started without operator "
                               "credentials")
        bad = self._json_only(request)
        if bad is not None:
            return bad
        session = self.session_of(request)
        if session is None:
            return refuse(401, "not logged in: log in as an operator first")
        token = request.headers.get(TOKEN_HEADER, "")
        if not hmac.compare_digest(token.encode(), session.token.encode()):
            return refuse(403, f"missing or wrong {TOKEN_HEADER} header for this session")
        try:
            body = await request.json()
            line = body["line"]
            if not isinstance(line, str):
                raise TypeError("line must be a string")
        except (ValueError, KeyError, TypeError) as exc:
            return refuse(400, f'expected JSON {{"line": "setpri -9 C1 B1"}}: {exc}')
        loop = asyncio.get_running_loop()
        try:  # capped (cmdline.MAX_LINE) and parsed on a worker thread, never on the event loop
            req = await loop.run_in_executor(None, cmdline.parse, line)
        except (ChcosError, ValueError) as exc:
            return refuse(400, str(exc))
        if req is None:
            return refuse(400, "empty command line")
        name = command_name(req)
        if not allowed(req):
            return refuse(403, f"{name}: only {' and '.join(PAGE_COMMANDS)} may be issued "
                               "from the viewer")
        if not session.user.may(name):
            return refuse(403, f"{name}: role {session.user.role!r} of {session.user.name} "
                               "may not issue it")
        try:
            answer = await loop.run_in_executor(None, self.system.execute, line)
        except Busy as exc:
            return refuse(409, str(exc))
        except ChcosError as exc:
            return refuse(400, str(exc))
        except TimeoutError:
            return refuse(503, f"{line}: the kernel did not answer in time")
        except Exception as exc:  # a refused command never answers 500
            log.exception("viewer command %r failed", line)
            return refuse(422, f"{line}: {type(exc).__name__}: {exc}")
        log.info("viewer: %s (%s) ran %r", session.user.name, session.user.role, line)
        return web.json_response({"ok": True, "answer": answer})
