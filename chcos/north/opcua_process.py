"""opcua_process - the OPC UA server in a process of its own, so that encoding notifications for
many subscribed clients never holds the control loops' interpreter lock.

:class:`OpcUaProcess` has the interface of :class:`chcos.north.opcua.OpcUaServer` (``start``,
``stop``, ``endpoint``, ``refused``). It spawns a child process that runs that very server over
a mirror of the tables; the parent only sends what the server shows — device values and health
every ``period`` seconds, task and link figures every ``slow_period`` — and the kernel's notable
events, down a pipe (a few hundred bytes; no OPC UA work in the parent). Method calls come back
up the pipe: the parent runs them through ``System.execute`` and the same e-stop as the host
and answers; the child checks the session's role before it asks, and reports refusals.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing
import queue
import threading
from concurrent.futures import Future, ThreadPoolExecutor
from types import SimpleNamespace
from typing import TYPE_CHECKING, Any

from chcos.devices.entry import DeviceEntry, DeviceStatus
from chcos.errors import Busy, ChcosError
from chcos.kernel.instrument import Instrument
from chcos.north import NorthError
from chcos.north.health import add_health_listener, device_health, remove_health_listener
from chcos.north.opcua import EVENT_KINDS, OpcUaServer
from chcos.north.opcua_methods import estop

if TYPE_CHECKING:
    from multiprocessing.connection import Connection

    from chcos.devices.spec import DeviceSpec
    from chcos.serving.auth import Users
    from chcos.system.embedded import System

log = logging.getLogger("chcos.north.opcua")
START_TIMEOUT = 60.0
CALL_TIMEOUT = 35.0


def _plain(v: Any) -> Any:
    return v if v is None or isinstance(v, int | float | str | bool) else repr(v)


def snapshot(system: System, slow: bool) -> dict[str, Any]:
    """What the server shows, as plain data (read without locks, torn reads accepted)."""
    snap: dict[str, Any] = {
        "now": system.kernel.clock.now(),
        "devices": [(d.name, d.status.value, d.reason, _plain(d.value), d.updated_at)
                    for d in list(system.devtab)]}
    if slow:
        snap["tasks"] = [(t.name, t.frozen, t.state.value, t.level,
                          t.owner.src if t.owner is not None else None, t.prio, t.completions,
                          t.abnormal, t.last_error) for t in list(system.tsktab)]
        snap["links"] = [(lk.src, lk.dst, lk.sent, lk.delivered, lk.overwritten,
                          lk.status.value, lk.priority) for lk in list(system.msgtab)]
        snap["bus_status"] = system.devtab.bus_status()
    return snap


class _Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t


class _MirrorKernel:
    def __init__(self) -> None:
        self.clock = _Clock()
        self.instruments: list[Instrument] = []

    def add_instrument(self, i: Instrument) -> None:
        self.instruments.append(i)

    def remove_instrument(self, i: Instrument) -> None:
        if i in self.instruments:
            self.instruments.remove(i)


class Mirror:
    """The tables as the child sees them, rebuilt from the parent's snapshots."""

    def __init__(self, specs: list[DeviceSpec]) -> None:
        self.kernel = _MirrorKernel()
        self.devtab = [DeviceEntry(spec) for spec in specs]
        self._by_name = {d.name: d for d in self.devtab}
        self.tsktab: list[Any] = []
        self.msgtab: list[Any] = []
        #: what the buses' drivers show (Devtab.bus_status), as last told
        self.bus_status: dict[str, dict[str, Any]] = {}

    def update(self, snap: dict[str, Any]) -> None:
        """Apply one snapshot."""
        self.kernel.clock.t = snap["now"]
        for name, status, reason, value, at in snap["devices"]:
            e = self._by_name.get(name)
            if e is not None:
                e.status, e.reason, e.value, e.updated_at = DeviceStatus(status), reason, \
                    value, at
        if "tasks" in snap:
            self.tsktab = [SimpleNamespace(
                name=n, frozen=fr, state=SimpleNamespace(value=st), level=lv,
                owner=None if ow is None else SimpleNamespace(src=ow), prio=pr, completions=co,
                abnormal=ab, last_error=le) for n, fr, st, lv, ow, pr, co, ab, le in snap["tasks"]]
        if "bus_status" in snap:
            self.bus_status = snap["bus_status"]
        if "links" in snap:
            self.msgtab = [SimpleNamespace(src=s, dst=d, sent=se, delivered=de, overwritten=ov,
                                           status=SimpleNamespace(value=st), priority=pr)
                           for s, d, se, de, ov, st, pr in snap["links"]]


class _ChildServer(OpcUaServer):
    """The server in the child: commands and refusals go up the pipe."""

    def __init__(self, mirror: Mirror, endpoint: str, conn: Connection, **kw: Any) -> None:
        super().__init__(mirror, endpoint, **kw)  # type: ignore[arg-type]
        self.conn = conn
        self.lock = threading.Lock()
        self.ids = itertools.count(1)
        self.pending: dict[int, Future[str]] = {}
        self._listen_health = False  # the parent tells health changes down the pipe

    def bus_status(self) -> dict[str, dict[str, Any]]:
        """The parent's, from its last snapshot."""
        mirror: Mirror = self.system  # type: ignore[assignment]
        return mirror.bus_status

    def send(self, msg: tuple[Any, ...]) -> None:
        with self.lock:
            self.conn.send(msg)

    def _ask(self, msg: tuple[Any, ...]) -> str:
        n = next(self.ids)
        fut: Future[str] = Future()
        self.pending[n] = fut
        self.send((msg[0], n, *msg[1:]))
        try:
            return fut.result(timeout=CALL_TIMEOUT)
        finally:
            self.pending.pop(n, None)

    def answer(self, n: int, ok: bool, text: str, busy: bool) -> None:
        fut = self.pending.get(n)
        if fut is None:
            return
        if ok:
            fut.set_result(text)
        else:
            fut.set_exception(Busy(text) if busy else ChcosError(text))

    def _execute(self, line: str) -> str:
        return self._ask(("exec", line))

    def _do_estop(self, who: str, reason: str) -> str:
        return self._ask(("estop", who, reason))

    def _refusal(self, who: str, command: str, reason: str) -> None:
        super()._refusal(who, command, reason)
        self.send(("refused", who, command, reason))


def _child_main(conn: Connection, endpoint: str, specs: list[DeviceSpec], users: Users | None,
                certificate: str | None, private_key: str | None, period: float) -> None:
    logging.basicConfig(level=logging.ERROR, format="%(levelname)s %(name)s: %(message)s")
    mirror = Mirror(specs)
    try:
        # the parent's first snapshot (tasks and links too) before the address space is built:
        # a client connecting once the server says it is ready finds every task and link there
        first = conn.recv()
    except (EOFError, OSError):
        return
    if first[0] == "snap":
        mirror.update(first[1])
    try:
        server = _ChildServer(mirror, endpoint, conn, users=users, certificate=certificate,
                              private_key=private_key, period=period)
        server.start()
    except BaseException as exc:  # told to the parent
        conn.send(("error", str(exc)))
        return
    server.send(("ready", server.endpoint))
    try:
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                break
            kind = msg[0]
            if kind == "snap":
                mirror.update(msg[1])
            elif kind == "event":
                for i in list(mirror.kernel.instruments):
                    i.event(msg[1], msg[2])
            elif kind == "health":
                server.health_changed(*msg[1:])
            elif kind == "answer":
                server.answer(*msg[1:])
            elif kind == "stop":
                break
    finally:
        server.stop()


class _Events(Instrument):
    def __init__(self, q: queue.SimpleQueue[tuple[Any, ...]]) -> None:
        self.q = q

    def event(self, kind: str, detail: str) -> None:
        if kind in EVENT_KINDS:
            self.q.put((kind, detail))


class OpcUaProcess:
    """The OPC UA server of ``system`` at ``endpoint``, run in a child process (see the module
    doc); arguments as :class:`~chcos.north.opcua.OpcUaServer`. ``refused`` lists (user,
    command, reason) of refused method calls as the child reports them."""

    def __init__(self, system: System, endpoint: str = "opc.tcp://127.0.0.1:4840/chcos/", *,
                 users: Users | None = None, certificate: str | None = None,
                 private_key: str | None = None, period: float = 0.05,
                 slow_period: float = 0.5) -> None:
        OpcUaServer(system, endpoint, users=users, certificate=certificate,
                    private_key=private_key)  # checks the endpoint and TLS (NorthError)
        self.system = system
        self.endpoint = endpoint
        self.users = users
        self.certificate, self.private_key = certificate, private_key
        self.period, self.slow_period = period, slow_period
        self.refused: list[tuple[str, str, str]] = []
        self.refusals = threading.Condition()
        self._proc: Any = None
        self._conn: Connection | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._events: queue.SimpleQueue[tuple[Any, ...]] = queue.SimpleQueue()
        self._instrument = _Events(self._events)
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="chcos-opcua-call")

    def start(self) -> OpcUaProcess:
        """Spawn the server process and wait until it serves; returns self. Raises NorthError
        if it cannot start."""
        ctx = multiprocessing.get_context("spawn")
        parent, child = ctx.Pipe()
        specs = [d.spec for d in self.system.devtab]
        self._proc = ctx.Process(target=_child_main, name="chcos-opcua", daemon=True,
                                 args=(child, self.endpoint, specs, self.users,
                                       self.certificate, self.private_key, self.period))
        self._proc.start()
        child.close()
        self._conn = parent
        self._send(("snap", snapshot(self.system, True)))
        if not parent.poll(START_TIMEOUT):
            self._kill()
            raise NorthError(f"opcua: the server process did not start in {START_TIMEOUT} s")
        msg = parent.recv()
        if msg[0] != "ready":
            self._kill()
            raise NorthError(f"opcua: cannot serve {self.endpoint}: {msg[1]}")
        self.endpoint = msg[1]
        self.system.kernel.add_instrument(self._instrument)
        add_health_listener(self.system.devtab, self._on_health)
        for target, name in ((self._feed, "chcos-opcua-feed"), (self._read, "chcos-opcua-read")):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def _on_health(self, device: str, healthy: bool, cause: str) -> None:
        """Devtab's health listener (kernel thread): queued for the feed, in order with the
        kernel's events."""
        if not self._stop.is_set():
            status = device_health(self.system.devtab.get(device)).status
            self._events.put(("health", device, healthy, status, cause))

    def _send(self, msg: tuple[Any, ...]) -> None:
        assert self._conn is not None
        with self._lock:
            self._conn.send(msg)

    def _feed(self) -> None:
        slow_every = max(1, round(self.slow_period / self.period))
        for n in itertools.count():
            if self._stop.wait(self.period):
                return
            try:
                while True:
                    item = self._events.get_nowait()
                    self._send(item if item[0] == "health" else ("event", *item))
            except queue.Empty:
                pass
            try:
                self._send(("snap", snapshot(self.system, n % slow_every == 0)))
            except (RuntimeError, KeyError, AttributeError):  # a table changed under us
                continue
            except (OSError, ValueError):  # the child is gone
                return

    def _run(self, msg: tuple[Any, ...]) -> None:
        kind, n = msg[0], msg[1]
        try:
            if kind == "exec":
                text, ok, busy = self.system.execute(msg[2]), True, False
            else:
                text, ok, busy = estop(self.system, f"opcua {msg[2]}", msg[3]), True, False
        except Busy as exc:
            text, ok, busy = str(exc), False, True
        except (ChcosError, ValueError) as exc:
            text, ok, busy = str(exc), False, False
        with contextlib.suppress(OSError, ValueError):
            self._send(("answer", n, ok, text, busy))

    def _read(self) -> None:
        assert self._conn is not None
        while not self._stop.is_set():
            try:
                msg = self._conn.recv()
            except (EOFError, OSError):
                return
            if msg[0] in ("exec", "estop"):
                self._pool.submit(self._run, msg)
            elif msg[0] == "refused":
                with self.refusals:
                    self.refused.append(tuple(msg[1:]))
                    self.refusals.notify_all()

    def wait_refused(self, count: int, timeout: float) -> bool:
        """Wait until at least ``count`` refusals were reported (True) or ``timeout`` s pass."""
        with self.refusals:
            return self.refusals.wait_for(lambda: len(self.refused) >= count, timeout)

    def _kill(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._proc.kill()
            self._proc.join(10)

    def stop(self) -> None:
        """Stop the server process and the parent's threads (no error if not running)."""
        if self._proc is None:
            return
        self.system.kernel.remove_instrument(self._instrument)
        remove_health_listener(self.system.devtab, self._on_health)
        self._stop.set()
        with contextlib.suppress(OSError, ValueError):
            self._send(("stop",))
        self._proc.join(20)
        self._kill()
        if self._conn is not None:
            self._conn.close()
        for th in self._threads:
            th.join(10)
        self._pool.shutdown(wait=False)
        self._proc = None

    def __enter__(self) -> OpcUaProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


__all__ = ["Mirror", "OpcUaProcess", "snapshot"]
