"""opcua - the running system as an OPC UA server (asyncua), for SCADA, HMIs and historians.

Address space (namespace ``urn:chcos``, string node ids):

* ``Devices.<name>``: every device a Double variable (value in engineering units; StatusCode
  from the device's health: Good, UncertainLastUsableValue when stale, BadSensorFailure or
  BadDeviceFailure when failed, BadOutOfService when suspended, BadWaitingForInitialData before
  the first value; SourceTimestamp when the value was taken), with properties
  ``EngineeringUnits`` (EUInformation), ``EURange`` (from its limits, if any) and variables
  ``Age`` (seconds since the value, refreshed every 0.5 s) and ``Status`` (text with cause);
* ``Tasks.<name>``: every task an object with ``State``, ``Level``, ``Owner``, ``Priority``,
  ``Completions``, ``Abnormal`` and ``LastError`` (the last completion's error, "" if normal);
* ``Links.<src>/<dst>``: every link with ``Sent``, ``Delivered``, ``Overwritten``, ``Status``
  (msgstat) and ``Priority``;
* ``Buses.<bus>``: what a bus's driver shows beyond its counters
  (:meth:`chcos.devices.devtab.Devtab.bus_status`): ``Buses.<bus>.Node<id>`` an object per
  remote node (CANopen) with ``State`` (its lifecycle: WAITING_BOOT ... OPERATIONAL,
  PREOP_HELD, FAILED), ``Ready``, ``HeartbeatLost``, ``Boots`` (boot-ups seen), ``NmtStarts``,
  ``HeartbeatLosses`` (heartbeat losses declared), ``Emcys`` (EMCY messages received),
  ``ErrorRegister`` (0x1001, -1 if never read), ``LastEmcy`` and ``Reason``; ``Buses.<bus>.Sync``
  the SYNC cycle's ``Cycles``, ``Complete``, ``Missing``, ``Late``, ``LateWrites``, ``Period``
  and ``JitterP50``/``JitterP99``/``JitterMax`` (seconds); refreshed with the task figures;
* methods on the ``chcos`` object: ``Invoke(Task, Args, Priority)``, ``SetPri(Src, Dst,
  Priority)``, ``Suspend(Task)``, ``Resume(Task)``, ``EStop(Reason)``; each runs through the
  host's command path (:meth:`System.execute`, the system manager's checks) and is refused
  (BadUserAccessDenied) unless the session's user has a role that may issue it
  (:mod:`chcos.north.auth`); a refused or failed command answers a Bad status
  (BadInvalidArgument: the system manager refused it; BadResourceUnavailable: busy);
* events (BaseEventType, emitted by the ``chcos`` object): sensor failures and staleness,
  e-stops and abnormal completions, with severity 700-900 and the cause in the message;
* alarms (OffNormalAlarmType conditions, emitted by the Server object, ConditionId
  ``Alarms.<source>``): a device that fails or goes stale (Devtab's health listeners) raises an
  active alarm with the device's node as SourceNode, cleared (ActiveState False) when the device
  is healthy again; an e-stop (source: the ``chcos`` object) and an abnormal completion (source:
  ``Tasks.<name>``) raise one that stays active until acknowledged. Every state change is an
  event with ActiveState, AckedState, Retain, Severity and Message. ``Acknowledge(EventId,
  Comment)`` (the standard AcknowledgeableConditionType method, called on the condition) needs
  a user whose role may ``invoke`` (operator, supervisor): anonymous sessions and observers get
  BadUserAccessDenied, an outdated EventId BadEventIdUnknown. ``ConditionRefresh`` (asyncua's)
  sends a new subscriber every retained alarm.

Device values and health are copied from the tables on the server's own thread every ``period``
seconds (0.05), ages and the task and link figures every 0.5 s (only what changed is written;
subscriptions see it at their next publishing interval); the kernel only pays for the event hook
(and shares the interpreter: ``tools/bench_north.py`` measures what the server costs the control
loops). Connections are bounded (asyncua's cap and activation timeout, set from
:mod:`chcos.north.guard`: at most :data:`MAX_CONNECTIONS`, a session activated within
:data:`chcos.north.guard.REQUEST_TIMEOUT` seconds of connecting); what asyncua logs about junk
is rate-limited, once per cause per period. Wrong logins are throttled as the live view's
(:class:`chcos.north.auth.LoginThrottle`, per address and per user name). Anonymous sessions
may read and subscribe; username/password sessions get their role
(:mod:`chcos.north.opcua_methods`: sessions, rules and the methods; the alarms are
:mod:`chcos.north.opcua_alarms`). The endpoint is loopback by default; any other address needs
a certificate and private key and then offers only Basic256Sha256 Sign&Encrypt. On loopback
without a certificate the only endpoint has security policy None: a username and password then
cross the loopback interface unencrypted (readable only by a process that can capture loopback
traffic, i.e. root or CAP_NET_RAW); give a certificate and key (and ``secure=True``) to offer
Sign&Encrypt only there too (``docs/security.md``).
"""

from __future__ import annotations

import asyncio
import logging
import math
from datetime import UTC, datetime, timedelta
from typing import TYPE_CHECKING, Any
from urllib.parse import urlparse

from asyncua import ua as _ua
from asyncua.crypto.permission_rules import User, UserRole
from asyncua.server.internal_session import InternalSession
from asyncua.server.server import Server

from chcos.comm.config import is_loopback
from chcos.helpers import free_port
from chcos.kernel.instrument import Instrument
from chcos.north import NorthError
from chcos.north.health import add_health_listener, device_health, remove_health_listener
from chcos.north.opcua_alarms import Alarm, AlarmsMixin
from chcos.north.opcua_methods import CURRENT_USER, Logins, Rules, Session
from chcos.serving.guard import REQUEST_TIMEOUT, connection_cap, throttle_library_logs
from chcos.serving.loopthread import LoopThread

if TYPE_CHECKING:
    from asyncua.common.node import Node

    from chcos.serving.auth import Users
    from chcos.system.embedded import System

#: asyncua's ua module, untyped here: its NewType-wrapped scalars (UInt32, Int16, String...)
#: would need a cast at every call
ua: Any = _ua
log = logging.getLogger("chcos.north.opcua")
NAMESPACE = "urn:chcos"
EVENT_KINDS = {"device-failed": 900, "device-stale": 700, "estop": 900, "abnormal": 800}
#: Concurrent OPC UA connections the server takes (less if the descriptor limit is low).
MAX_CONNECTIONS = 64


def _status(direction: str, status: str, has_value: bool) -> ua.StatusCode:
    S = ua.StatusCodes
    if status == "failed":
        return ua.StatusCode(S.BadSensorFailure if direction == "sensor" else S.BadDeviceFailure)
    if status == "suspended":
        return ua.StatusCode(S.BadOutOfService)
    if not has_value:
        return ua.StatusCode(S.BadWaitingForInitialData)
    if status == "stale":
        return ua.StatusCode(S.UncertainLastUsableValue)
    return ua.StatusCode(S.Good)


class _Events(Instrument):
    """Hands the kernel's notable events to the server's loop (never blocks the kernel)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, queue: asyncio.Queue[tuple[Any, ...]]
                 ) -> None:
        self.loop = loop
        self.queue = queue

    def event(self, kind: str, detail: str) -> None:
        if kind in EVENT_KINDS and not self.loop.is_closed():
            self.loop.call_soon_threadsafe(self.queue.put_nowait, (kind, detail))


class OpcUaServer(AlarmsMixin):
    """The OPC UA server of ``system`` at ``endpoint`` (port 0: a free one), served from a
    background thread. ``users`` may log in (None: everyone is anonymous, read-only).
    ``certificate``/``private_key`` (PEM or DER paths) are required off loopback, where only
    Basic256Sha256 Sign&Encrypt is offered; ``secure=True`` asks for that on loopback too.
    ``refused`` lists (user, command, reason) of refused method calls, newest last."""

    def __init__(self, system: System, endpoint: str = "opc.tcp://127.0.0.1:4840/chcos/", *,
                 users: Users | None = None, certificate: str | None = None,
                 private_key: str | None = None, period: float = 0.05,
                 secure: bool | None = None) -> None:
        url = urlparse(endpoint)
        if url.scheme != "opc.tcp" or not url.hostname:
            raise NorthError(f"--opcua {endpoint!r}: expected opc.tcp://HOST:PORT/PATH")
        self.host = url.hostname
        self.port = 4840 if url.port is None else url.port
        self.path = url.path or "/"
        self.secure = not is_loopback(self.host) if secure is None else secure
        if self.secure and not (certificate and private_key):
            raise NorthError(f"--opcua {endpoint}: an endpoint off loopback needs a certificate "
                             "and private key (security policy Basic256Sha256)")
        self.system = system
        self.users = users
        self.certificate, self.private_key = certificate, private_key
        self.period = period
        #: seconds between refreshes of ages, task and link figures
        self.slow_period = 0.5
        self.refused: list[tuple[str, str, str]] = []
        #: the username/password check and its throttle (per address and per user name)
        self.logins = Logins(users)
        self._service = LoopThread("chcos-opcua")
        self._instrument: _Events | None = None
        self._nodes: dict[str, dict[str, Node]] = {}
        self._last: dict[str, Any] = {}
        #: the alarms (conditions) by key, as last told to clients
        self.alarms: dict[str, Alarm] = {}
        self._queue: asyncio.Queue[tuple[Any, ...]] | None = None
        #: listen to Devtab health here (False in the child process, which is told instead)
        self._listen_health = True

    @property
    def endpoint(self) -> str:
        """The endpoint URL (valid once started)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"opc.tcp://{host}:{self.port}{self.path}"

    # ---- life cycle -------------------------------------------------------------------------
    def start(self) -> OpcUaServer:
        """Build the address space and serve; returns self. Raises NorthError if it cannot."""
        if self.port == 0:
            try:
                self.port = free_port(self.host)
            except OSError as exc:
                raise NorthError(f"opcua: cannot serve {self.endpoint}: {exc}") from exc
        try:
            self._service.start(self._serve)
        except Exception as exc:
            raise NorthError(f"opcua: cannot serve {self.endpoint}: {exc}") from exc
        return self

    def stop(self) -> None:
        """Stop serving and join the thread (no error if not running)."""
        self._service.stop(timeout=15)

    def __enter__(self) -> OpcUaServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    async def _serve(self, service: LoopThread) -> None:
        """The server's life on its loop: build the address space, serve until stopped; the
        kernel and Devtab hooks are removed whatever happens."""
        try:
            await self._serve_until_stopped(service)
        finally:
            if self._instrument is not None:
                self.system.kernel.remove_instrument(self._instrument)
            if self._listen_health:
                remove_health_listener(self.system.devtab, self._on_health)

    async def _serve_until_stopped(self, service: LoopThread) -> None:
        throttle_library_logs()
        server = Server(user_manager=self.logins)
        await server.init()
        iserver = server.iserver
        # bounded as every north-side server (chcos.north.guard): a cap on connections, and
        # a connection that has not activated a session within REQUEST_TIMEOUT is closed
        iserver.max_connections = connection_cap(MAX_CONNECTIONS)
        iserver.max_pending_activation_seconds = REQUEST_TIMEOUT

        def create_session(name: str, user: User = User(role=UserRole.Anonymous),  # noqa: B008
                           external: bool = False) -> InternalSession:
            return Session(iserver, iserver.aspace, iserver.subscription_service, name,
                            user=user, external=external)

        iserver.create_session = create_session  # type: ignore[method-assign]
        server.set_endpoint(self.endpoint)
        server.set_server_name("chcos")
        policies = []
        if self.certificate and self.private_key:
            await server.load_certificate(self.certificate)
            await server.load_private_key(self.private_key)
            policies.append(ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt)
        if not self.secure:
            policies.insert(0, ua.SecurityPolicyType.NoSecurity)
        server.set_security_policy(policies, permission_ruleset=Rules())  # type: ignore[arg-type]
        tokens: list[type] = [ua.AnonymousIdentityToken]
        if self.users is not None:
            tokens.append(ua.UserNameIdentityToken)
        server.set_identity_tokens(tokens)
        idx = await server.register_namespace(NAMESPACE)
        self._idx, self._server = idx, server
        root = await server.nodes.objects.add_object(ua.NodeId("chcos", idx), self._qn("chcos"))
        self._folders = {k: await root.add_folder(ua.NodeId(k, idx), self._qn(k))
                         for k in ("Devices", "Tasks", "Links", "Buses")}
        await self._add_methods(root, idx)
        self._alarm_folder = await root.add_folder(ua.NodeId("Alarms", idx), self._qn("Alarms"))
        evgen = await server.get_event_generator(emitting_node=root.nodeid)
        self._alarmgen = await server.get_event_generator(ua.ObjectIds.OffNormalAlarmType,
                                                          emitting_node=ua.ObjectIds.Server)
        server.link_method(server.get_node(ua.ObjectIds.AcknowledgeableConditionType_Acknowledge),
                           self._acknowledge)
        iserver.bind_condition_methods = 100  # ConditionRefresh; Refresh events of severity 100
        await iserver.setup_condition_methods()
        queue: asyncio.Queue[tuple[Any, ...]] = asyncio.Queue()
        self._queue = queue
        await self._refresh(force=True)
        async with server:
            loop = asyncio.get_running_loop()
            self._instrument = _Events(loop, queue)
            self.system.kernel.add_instrument(self._instrument)
            if self._listen_health:
                add_health_listener(self.system.devtab, self._on_health)
            service.ready()
            refresher = asyncio.create_task(self._refresher())
            emitter = asyncio.create_task(self._emit(evgen, queue))
            await service.stopped()
            refresher.cancel()
            emitter.cancel()

    # ---- address space ----------------------------------------------------------------------
    async def _var(self, parent: Node, nid: str, name: str, value: Any,
                   vtype: ua.VariantType) -> Node:
        return await parent.add_variable(ua.NodeId(nid, self._idx), self._qn(name),
                                         ua.Variant(value, vtype))

    def _qn(self, name: str) -> Any:
        return ua.QualifiedName(name, self._idx)

    async def _add_device(self, d: Any) -> None:
        spec = d.spec
        nid = f"Devices.{d.name}"
        var = await self._var(self._folders["Devices"], nid, d.name, math.nan,
                              ua.VariantType.Double)
        await var.add_property(ua.NodeId(f"{nid}.EngineeringUnits", self._idx),
                               self._qn("EngineeringUnits"),
                               ua.EUInformation(
                                   NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
                                   UnitId=-1, DisplayName=ua.LocalizedText(spec.units),
                                   Description=ua.LocalizedText(spec.units)))
        lo, hi = spec.limits
        if lo is not None or hi is not None:
            await var.add_property(ua.NodeId(f"{nid}.EURange", self._idx), self._qn("EURange"),
                                   ua.Range(Low=-math.inf if lo is None else float(lo),
                                            High=math.inf if hi is None else float(hi)))
        age = await self._var(var, f"{nid}.Age", "Age", math.nan, ua.VariantType.Double)
        status = await self._var(var, f"{nid}.Status", "Status", "", ua.VariantType.String)
        self._nodes[nid] = {"value": var, "age": age, "status": status}

    async def _add_task(self, t: Any) -> None:
        nid = f"Tasks.{t.name}"
        obj = await self._folders["Tasks"].add_object(ua.NodeId(nid, self._idx),
                                                      self._qn(t.name))
        nodes: dict[str, Node] = {}
        for name, vt, init in (("State", ua.VariantType.String, ""),
                               ("Level", ua.VariantType.Int32, 0),
                               ("Owner", ua.VariantType.String, ""),
                               ("Priority", ua.VariantType.Int32, 0),
                               ("Completions", ua.VariantType.Int64, 0),
                               ("Abnormal", ua.VariantType.Int64, 0),
                               ("LastError", ua.VariantType.String, "")):
            nodes[name] = await self._var(obj, f"{nid}.{name}", name, init, vt)
        self._nodes[nid] = nodes

    async def _add_link(self, key: str) -> None:
        nid = f"Links.{key}"
        obj = await self._folders["Links"].add_object(ua.NodeId(nid, self._idx),
                                                      self._qn(key))
        nodes: dict[str, Node] = {}
        for name, vt, init in (("Sent", ua.VariantType.Int64, 0),
                               ("Delivered", ua.VariantType.Int64, 0),
                               ("Overwritten", ua.VariantType.Int64, 0),
                               ("Status", ua.VariantType.String, ""),
                               ("Priority", ua.VariantType.Int32, 0)):
            nodes[name] = await self._var(obj, f"{nid}.{name}", name, init, vt)
        self._nodes[nid] = nodes

    async def _add_object(self, parent: Node, nid: str, name: str,
                          fields: tuple[tuple[str, ua.VariantType, Any], ...]) -> None:
        obj = await parent.add_object(ua.NodeId(nid, self._idx), self._qn(name))
        self._nodes[nid] = {f: await self._var(obj, f"{nid}.{f}", f, init, vt)
                            for f, vt, init in fields}

    def bus_status(self) -> dict[str, dict[str, Any]]:
        """What the buses' drivers show (the server in a child process gets it by pipe)."""
        return self.system.devtab.bus_status()

    async def _refresh_buses(self) -> None:
        """``Buses.<bus>``: each remote node's lifecycle and the SYNC cycle's figures."""
        I64, STR, DBL, BOOL, I32 = (ua.VariantType.Int64, ua.VariantType.String,
                                    ua.VariantType.Double, ua.VariantType.Boolean,
                                    ua.VariantType.Int32)
        for bus, doc in self.bus_status().items():
            bid = f"Buses.{bus}"
            if bid not in self._nodes:
                obj = await self._folders["Buses"].add_object(ua.NodeId(bid, self._idx),
                                                              self._qn(bus))
                self._nodes[bid] = {"object": obj}
            parent = self._nodes[bid]["object"]
            for n in doc.get("nodes", ()):
                nid = f"{bid}.Node{n['node']}"
                reg = n.get("error_register")
                values: tuple[tuple[str, ua.VariantType, Any], ...] = (
                    ("State", STR, n["state"]), ("Ready", BOOL, bool(n["ready"])),
                    ("HeartbeatLost", BOOL, bool(n.get("heartbeat_lost"))),
                    ("Boots", I64, int(n["boots"])), ("NmtStarts", I64, int(n["nmt_starts"])),
                    ("HeartbeatLosses", I64, int(n.get("heartbeat_losses", 0))),
                    ("Emcys", I64, int(n.get("emcys", 0))),
                    ("ErrorRegister", I32, -1 if reg is None else int(reg)),
                    ("LastEmcy", STR, n.get("last_emcy") or ""),
                    ("Reason", STR, n.get("reason") or ""))
                if nid not in self._nodes:
                    await self._add_object(parent, nid, f"Node{n['node']}", values)
                for name, vt, value in values:
                    await self._set(self._nodes[nid][name], f"{nid}.{name}", value, vt)
            st = doc.get("sync")
            if st:
                nid = f"{bid}.Sync"
                values = (("Cycles", I64, int(st["cycles"])),
                          ("Complete", I64, int(st["complete"])),
                          ("Missing", I64, int(st["missing"])), ("Late", I64, int(st["late"])),
                          ("LateWrites", I64, int(st["late_writes"])),
                          ("Period", DBL, float(st["period"])),
                          ("JitterP50", DBL, float(st["jitter_p50"])),
                          ("JitterP99", DBL, float(st["jitter_p99"])),
                          ("JitterMax", DBL, float(st["jitter_max"])))
                if nid not in self._nodes:
                    await self._add_object(parent, nid, "Sync", values)
                for name, vt, value in values:
                    await self._set(self._nodes[nid][name], f"{nid}.{name}", value, vt)

    # ---- refreshing -------------------------------------------------------------------------
    async def _set(self, node: Node, key: str, value: Any, vtype: ua.VariantType,
                   status: ua.StatusCode | None = None, source: datetime | None = None) -> None:
        sig = (value, None if status is None else status.value, source)
        if self._last.get(key) == sig:
            return
        self._last[key] = sig
        dv = ua.DataValue(ua.Variant(value, vtype), StatusCode=status or ua.StatusCode(),
                          SourceTimestamp=source, ServerTimestamp=datetime.now(UTC))
        await self._server.write_attribute_value(node.nodeid, dv)

    async def _refresh(self, force: bool = False, ages: bool = False) -> None:
        """Copy what changed into the address space: device values and health every period;
        with ``ages`` (once a second) also ages and the task and link figures, which change
        with every message and are not worth an OPC UA write each time."""
        s = self.system
        now = s.kernel.clock.now()
        wall = datetime.now(UTC)
        I32, I64, STR, DBL = (ua.VariantType.Int32, ua.VariantType.Int64, ua.VariantType.String,
                              ua.VariantType.Double)
        for d in list(s.devtab):
            nid = f"Devices.{d.name}"
            if nid not in self._nodes:
                await self._add_device(d)
            n = self._nodes[nid]
            h = device_health(d)
            v, at = d.value, d.updated_at
            num = float(v) if isinstance(v, int | float) else math.nan
            src = None if at is None else wall - timedelta(seconds=max(0.0, now - at))
            # the source time is derived from the clock: only a new value moves it
            key_src = None if at is None else at
            sig = (num, h.status, key_src)
            if force or self._last.get(nid + "#") != sig:
                self._last[nid + "#"] = sig
                await self._set(n["value"], nid, num, DBL,
                                _status(d.spec.direction, h.status, at is not None), src)
                await self._set(n["status"], nid + ".Status",
                                h.status + (f": {h.cause}" if h.cause else ""), STR)
            if ages or force:
                await self._set(n["age"], nid + ".Age",
                                math.nan if at is None else max(0.0, now - at), DBL)
        if not (ages or force):
            return
        for t in list(s.tsktab):
            nid = f"Tasks.{t.name}"
            if nid not in self._nodes:
                await self._add_task(t)
            n = self._nodes[nid]
            for name, value, vt in (
                    ("State", "frozen" if t.frozen else t.state.value, STR),
                    ("Level", t.level, I32),
                    ("Owner", t.owner.src if t.owner is not None else "", STR),
                    ("Priority", t.prio, I32), ("Completions", t.completions, I64),
                    ("Abnormal", t.abnormal, I64), ("LastError", t.last_error or "", STR)):
                await self._set(n[name], f"{nid}.{name}", value, vt)
        for lk in list(s.msgtab):
            key = f"{lk.src}/{lk.dst}"
            nid = f"Links.{key}"
            if nid not in self._nodes:
                await self._add_link(key)
            n = self._nodes[nid]
            for name, value, vt in (("Sent", lk.sent, I64), ("Delivered", lk.delivered, I64),
                                    ("Overwritten", lk.overwritten, I64),
                                    ("Status", lk.status.value, STR),
                                    ("Priority", lk.priority, I32)):
                await self._set(n[name], f"{nid}.{name}", value, vt)
        await self._refresh_buses()

    async def _refresher(self) -> None:
        loop = asyncio.get_running_loop()
        last_age = 0.0
        while True:
            await asyncio.sleep(self.period)
            ages = loop.time() - last_age >= self.slow_period
            if ages:
                last_age = loop.time()
            try:
                await self._refresh(ages=ages)
            except (RuntimeError, KeyError, AttributeError):  # a table changed under us
                continue

    async def _emit(self, evgen: Any, queue: asyncio.Queue[tuple[Any, ...]]) -> None:
        while True:
            item = await queue.get()
            try:
                if item[0] == "health":
                    await self._health_alarm(*item[1:])
                    continue
                kind, detail = item
                evgen.event.Message = ua.LocalizedText(f"{kind}: {detail}")
                evgen.event.Severity = EVENT_KINDS[kind]
                evgen.event.SourceName = detail.split(":", 1)[0].strip()
                await evgen.trigger()
                if kind == "estop":
                    await self._raise("EStop", "chcos", 900, f"estop: {detail}")
                elif kind == "abnormal":
                    task = detail.split(":", 1)[0].strip()
                    if f"Tasks.{task}" not in self._nodes:
                        await self._refresh(ages=True)
                    await self._raise(f"Tasks.{task}", f"Tasks.{task}", 800,
                                      f"abnormal completion of {detail}")
            except Exception:  # one bad event must not end the emitter
                log.exception("opcua: cannot emit %r", item)

    # ---- alarms (conditions) ----------------------------------------------------------------
    def health_changed(self, device: str, healthy: bool, status: str, cause: str) -> None:
        """A device's health changed (any thread): raise or clear its alarm."""
        q = self._queue
        if q is not None:
            self._service.call(q.put_nowait, ("health", device, healthy, status, cause))

    def _on_health(self, device: str, healthy: bool, cause: str) -> None:
        if self._service.stopping:
            return
        e = self.system.devtab.get(device)
        self.health_changed(device, healthy, device_health(e).status, cause)

__all__ = ["CURRENT_USER", "NAMESPACE", "OpcUaServer"]
