"""opcua_methods - who may do what on the OPC UA server (:mod:`chcos.north.opcua`).

Sessions carry their user (:class:`Session` sets :data:`CURRENT_USER` while a method call runs;
:class:`Logins` checks username/password against :class:`chcos.north.auth.Users`, anonymous
otherwise, through the same :class:`chcos.north.auth.LoginThrottle` bar as the live view: per
client address and per user name, each attempt counted before its password is checked, a
barred attempt refused (BadUserAccessDenied) unchecked); :class:`Rules` lets everyone read,
browse, subscribe and call and nobody write attributes or change the address space. The
methods on the ``chcos`` object -
``Invoke(Task, Args, Priority)``, ``SetPri(Src, Dst, Priority)``, ``Suspend(Task)``,
``Resume(Task)``, ``EStop(Reason)`` - are :class:`MethodsMixin`'s: each checks the caller's role
(BadUserAccessDenied), runs through the host's command path (:meth:`System.execute`) or
:func:`estop`, and answers a Bad status for a refusal (BadInvalidArgument, or
BadResourceUnavailable when busy).
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import shlex
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from asyncua import ua as _ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.server.internal_session import InternalSession
from asyncua.server.user_managers import UserManager

from chcos.comm.secret import Throttle
from chcos.errors import Busy, ChcosError

if TYPE_CHECKING:
    from asyncua.common.node import Node

    from chcos.serving.auth import LoginThrottle, Users
    from chcos.system.embedded import System

#: asyncua's ua module, untyped here (see :mod:`chcos.north.opcua`)
ua: Any = _ua
log = logging.getLogger("chcos.north.opcua")
#: The client address of the session being activated (for the login throttle).
CURRENT_PEER: contextvars.ContextVar[str] = contextvars.ContextVar("chcos_opcua_peer",
                                                                   default="?")
#: The user of the OPC UA session whose method call is running.
CURRENT_USER: contextvars.ContextVar[User | None] = contextvars.ContextVar("chcos_opcua_user",
                                                                           default=None)
_WRITE = ua.NodeId(ua.ObjectIds.WriteRequest_Encoding_DefaultBinary)


def estop(system: System, who: str, reason: str) -> str:
    """An emergency stop from the north: logged as ``estop``, told to the other satellites,
    every local actuator with a safe value gets it (on the kernel thread). Returns the answer
    text."""
    def on_kernel() -> int:
        return system.msgmgr.estop(who, reason)

    n = system.call(on_kernel)
    return f"estop: {n} actuator(s) at safe values"


class Rules(PermissionRuleset):
    """Everyone may read, browse, subscribe and call; nobody writes attributes or changes the
    address space (methods check roles themselves)."""

    def __init__(self) -> None:
        self._allowed = {ua.NodeId(i) for i in USER_TYPES} - {_WRITE}

    def check_validity(self, user: Any, action_type_id: Any, body: Any) -> bool:
        return action_type_id in self._allowed


class Logins(UserManager):
    """Username/password sessions get their account (role checked per method); no name and no
    certificate: anonymous; a bad password: refused."""

    def __init__(self, users: Users | None, throttle: LoginThrottle | None = None) -> None:
        from chcos.serving.auth import LoginThrottle

        self.users = users
        self.throttle = throttle or LoginThrottle()
        #: logins refused unchecked, logged once per period with a count
        self.rejected = Throttle(log)

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: Any = None) -> User | None:
        if not username and not certificate:
            return User(role=UserRole.Anonymous)
        if self.users is None or not username:
            return None
        peer = CURRENT_PEER.get()
        if self.throttle.begin(peer, username) > 0:
            self.rejected.note("opcua: logins refused unchecked (too many wrong logins)",
                               f"{username[:64]!r} from {peer}")
            return None
        u = self.users.check(username, password or "")
        self.throttle.end(peer, username, u is not None)
        return None if u is None else User(role=UserRole.User, name=u.name)


class Session(InternalSession):
    """A session whose method calls see its user in :data:`CURRENT_USER`, and whose
    activation tells the login check its client address (:data:`CURRENT_PEER`)."""

    def activate_session(self, params: Any, peer_certificate: bytes | None) -> Any:
        peer = self.name[0] if isinstance(self.name, tuple) and self.name else str(self.name)
        token = CURRENT_PEER.set(str(peer))
        try:
            return super().activate_session(params, peer_certificate)
        finally:
            CURRENT_PEER.reset(token)

    async def call(self, params: list[ua.CallMethodRequest]) -> list[ua.CallMethodResult]:
        token = CURRENT_USER.set(self.user)
        try:
            return await super().call(params)
        finally:
            CURRENT_USER.reset(token)


class MethodsMixin:
    """The ``chcos`` object's methods, for :class:`chcos.north.opcua.OpcUaServer` (which
    supplies ``system``, ``users``, ``refused`` and ``_qn``). A subclass may run commands
    elsewhere by overriding :meth:`_execute`, :meth:`_do_estop` and :meth:`_refusal`."""

    system: System
    users: Users | None
    refused: list[tuple[str, str, str]]

    def _qn(self, name: str) -> Any:
        raise NotImplementedError

    def _user(self) -> tuple[str, Any]:
        u = CURRENT_USER.get()
        name = u.name if u is not None and u.name else ""
        account = self.users.users.get(name) if self.users is not None and name else None
        return name or "anonymous", account

    def _method(self, command: str, build: Callable[..., str | Callable[[str], str]]
                ) -> Callable[..., Awaitable[Any]]:
        async def call(parent: ua.NodeId, *args: ua.Variant) -> Any:
            who, account = self._user()
            if account is None or not account.may(command):
                reason = (f"{command}: {who} may not issue it (role "
                          f"{account.role if account else 'anonymous'})")
                self._refusal(who, command, reason)
                log.warning("opcua: %s", reason)
                return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
            values = [a.Value if isinstance(a, ua.Variant) else a for a in args]
            loop = asyncio.get_running_loop()
            try:
                what = build(*values)
                if isinstance(what, str):
                    answer = await loop.run_in_executor(None, self._execute, what)
                else:
                    answer = await loop.run_in_executor(None, what, who)
            except Busy as exc:
                self._refusal(who, command, str(exc))
                return ua.StatusCode(ua.StatusCodes.BadResourceUnavailable)
            except (ChcosError, ValueError, TypeError) as exc:
                self._refusal(who, command, str(exc))
                log.warning("opcua: %s by %s refused: %s", command, who, exc)
                return ua.StatusCode(ua.StatusCodes.BadInvalidArgument)
            log.info("opcua: %s by %s: %s", command, who, answer)
            return [ua.Variant(str(answer), ua.VariantType.String)]

        return call

    def _refusal(self, who: str, command: str, reason: str) -> None:
        """Remember a refused method call."""
        self.refused.append((who, command, reason))

    def _execute(self, line: str) -> str:
        """Run one host command line on the system (raises ChcosError)."""
        return self.system.execute(line)

    def _do_estop(self, who: str, reason: str) -> str:
        """Every actuator to its safe value, on the kernel thread; the answer text."""
        return estop(self.system, f"opcua {who}", reason)

    def _estop(self, reason: str) -> Callable[[str], str]:
        def run(who: str) -> str:
            return self._do_estop(who, reason)

        return run

    async def _add_methods(self, root: Node, idx: int) -> None:
        S, I32 = ua.VariantType.String, ua.VariantType.Int32

        def arg(name: str, vt: ua.VariantType) -> ua.Argument:
            a = ua.Argument()
            a.Name = name
            a.DataType = ua.NodeId(vt.value)
            a.ValueRank = -1
            return a

        out = [arg("Answer", S)]
        q = shlex.quote

        def invoke(task: str, args: str = "", prio: int = -1) -> str:
            return (f"invoke {'-' + str(prio) + ' ' if prio >= 0 else ''}{q(task)} "
                    f"{args}").strip()

        for name, command, build, inputs in (
                ("Invoke", "invoke", invoke,
                 [arg("Task", S), arg("Args", S), arg("Priority", I32)]),
                ("SetPri", "setpri",
                 lambda src, dst, prio: f"setpri -{int(prio)} {q(src)} {q(dst)}",
                 [arg("Src", S), arg("Dst", S), arg("Priority", I32)]),
                ("Suspend", "suspend", lambda task: f"suspend {q(task)}", [arg("Task", S)]),
                ("Resume", "resume", lambda task: f"resume {q(task)}", [arg("Task", S)]),
                ("EStop", "estop", self._estop, [arg("Reason", S)])):
            await root.add_method(ua.NodeId(f"chcos.{name}", idx), self._qn(name),
                                  self._method(command, build), inputs, out)
