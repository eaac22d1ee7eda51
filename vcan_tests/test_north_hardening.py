"""The north-side servers against hostile clients (issue 50): logins counted before the password
check under concurrency (view and OPC UA, per address and per user), unknown users costing the
same time as known ones, a connection flood against the view, the metrics endpoint, the Modbus
facade and OPC UA while the cell's control loop runs (descriptors bounded, refusals counted,
half-open requests timed out, a new Modbus connection still served), a junk flood whose log
stays small, junk exception-function requests answered in Modbus' own form, and the metrics'
bearer token."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
import statistics
import struct
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from opcua import Client
from pyModbusTCP.client import ModbusClient

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import RealClock
from chcos.north import NorthError
from chcos.north.metrics import serve as serve_metrics
from chcos.north.modbus_facade import ModbusFacade
from chcos.north.opcua import OpcUaServer
from chcos.serving.auth import LoginThrottle, User, Users, hash_password
from chcos.serving.guard import throttle_library_logs
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from chcos.viewer.server import Viewer
from vcan_tests.support_view import PASSWORDS, viewer_users

ME = "vcan_tests.test_north_hardening"


async def ticker(ctx: TaskContext, cmd: Any) -> None:
    """Task code: a control loop stepping every 5 ms for ever."""
    n = 0
    while True:
        await ctx.sleep(0.005)
        n += 1
        ctx.world.sensory["ticks"] = n


def _wait(pred: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, f"{what} not within {timeout} s"
        threading.Event().wait(0.05)


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[System]:
    """A real-time cell whose task TICK steps every 5 ms; V1 writable from the north."""
    devmap = DeviceMap((BusSpec("mem", "memory"),), (
        DeviceSpec("P1", "sensor", 0, "mem", units="bar"),
        DeviceSpec("V1", "actuator", 0, "mem", safe_value=0.0, limits=(-100, 100), units="%",
                   north_writable=True)))
    s = System(devmap, clock=RealClock(), base_dir=tmp_path)
    for line in ("install -m0 sysfile", f"install -m0 --code={ME}:ticker TICK", "invoke TICK",
                 "inject P1 2.5"):
        s.execute(line)
    s.start()
    yield s
    s.shutdown()


# ---- logins --------------------------------------------------------------------------------
def _login_burst(viewer: Viewer, n: int, user: str, local: str = "127.0.0.1") -> list[int]:
    async def main() -> list[int]:
        connector = aiohttp.TCPConnector(limit=0, local_addr=(local, 0))
        async with aiohttp.ClientSession(connector=connector) as session:
            async def one() -> int:
                async with session.post(f"{viewer.url}api/login",
                                        json={"user": user, "password": "wrong"}) as r:
                    return r.status
            return list(await asyncio.gather(*(one() for _ in range(n))))
    return asyncio.run(main())


def test_concurrent_wrong_logins_are_checked_at_most_six_times(cell: System) -> None:
    with Viewer(cell, users=viewer_users()) as viewer:
        viewer.start()
        statuses = _login_burst(viewer, 100, "alice")
        checked = viewer.login_throttle.checked
        print(f"100 concurrent wrong logins from one address: {checked} password checks, "
              f"{statuses.count(429)} answered 429")
        assert statuses.count(401) == checked <= 6
        assert statuses.count(429) == 100 - checked
        # per user: the same name from another (loopback) address is barred too
        assert set(_login_burst(viewer, 5, "alice", "127.0.0.2")) == {429}
        # per address: another name from the first address is barred too
        assert set(_login_burst(viewer, 5, "sam")) == {429}
        assert viewer.login_throttle.checked == checked


def test_opcua_wrong_logins_meet_the_same_bar(cell: System) -> None:
    with OpcUaServer(cell, "opc.tcp://127.0.0.1:0/chcos/", users=viewer_users()) as o:
        o.start()
        refused = 0
        for _ in range(12):
            c = Client(o.endpoint, timeout=10)
            c.set_user("alice")
            c.set_password("wrong")
            try:
                c.connect()
                c.disconnect()
            except Exception:  # BadUserAccessDenied
                refused += 1
        assert refused == 12
        assert o.logins.throttle.checked <= 6
        assert o.logins.throttle.refused == 12 - o.logins.throttle.checked
        c = Client(o.endpoint, timeout=10)  # even the right password waits out the bar
        c.set_user("alice")
        c.set_password(PASSWORDS["alice"])
        with pytest.raises(Exception):  # noqa: B017 - python-opcua raises its own UaError
            c.connect()
        print(f"OPC UA: 12 wrong logins, {o.logins.throttle.checked} checked")


def test_unknown_users_cost_the_same_time_as_known_ones() -> None:
    n = 20_000  # a cheaper hash than the default, so that many samples fit
    users = Users({"alice": User("alice", "operator", hash_password("pw", n))})
    for _ in range(3):  # warm up
        users.check("alice", "x")
        users.check("nobody", "x")
    known: list[float] = []
    unknown: list[float] = []
    for _ in range(40):  # side by side: a load change hits both
        for name, into in (("alice", known), ("nobody", unknown)):
            t0 = time.perf_counter()
            assert users.check(name, "wrong") is None
            into.append(time.perf_counter() - t0)
    ratio = statistics.median(unknown) / statistics.median(known)
    print(f"unknown/known user check time (medians of 40): {ratio:.3f}")
    assert 0.8 <= ratio <= 1.25


def test_the_throttle_counts_before_the_check_and_clears_on_success() -> None:
    now = [0.0]
    t = LoginThrottle(free=2, base=1.0, longest=8.0, clock=lambda: now[0])
    assert [t.begin("a", "u") for _ in range(3)] == [0.0, 0.0, 0.0]  # 3rd: bars 1 s
    assert t.begin("a", "u") == 1.0 and t.begin("b", "u") == 1.0 and t.begin("a", "v") == 1.0
    assert t.begin("b", "v") == 0.0
    now[0] = 1.0
    assert t.begin("a", "u") == 0.0
    t.end("a", "u", ok=True)
    assert t.wait("address a") == 0.0 and t.wait("user u") == 0.0
    assert t.checked == 5 and t.refused == 3


# ---- connection floods ---------------------------------------------------------------------
def _fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _flood(port: int, n: int, payload: bytes = b"") -> list[socket.socket]:
    socks = []
    for _ in range(n):
        s = socket.create_connection(("127.0.0.1", port), timeout=5)
        if payload:
            s.sendall(payload)
        socks.append(s)
    return socks


def _read_registers(port: int) -> list[int] | None:
    c = ModbusClient(host="127.0.0.1", port=port, timeout=5.0, auto_open=True)
    try:
        regs: list[int] | None = c.read_input_registers(0, 2)
        return regs
    finally:
        c.close()


def test_a_connection_flood_is_bounded_and_the_cell_keeps_running(cell: System) -> None:
    viewer = Viewer(cell, max_connections=20)
    viewer.gate.request_timeout = 1.0
    facade = ModbusFacade(cell)
    facade.gate.cap, facade.gate.idle_timeout = 20, 1.0
    metrics = serve_metrics(cell)
    metrics.gate.cap, metrics.gate.request_timeout = 20, 1.0
    opcua = OpcUaServer(cell, "opc.tcp://127.0.0.1:0/chcos/")
    with viewer, facade, opcua:
        viewer.start()
        facade.start()
        opcua.start()
        try:
            cell.sysmgr  # noqa: B018 - the cell is up
            base_fds = _fds()
            steps0 = cell.kernel.steps
            half_open = b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: "  # never finished
            socks: list[socket.socket] = []
            ports = {"view": viewer.port, "metrics": int(metrics.url.rsplit(":", 1)[1]
                                                         .split("/")[0]),
                     "modbus": facade.port, "opcua": opcua.port}
            for name, port in ports.items():
                socks += _flood(port, 80 if name == "opcua" else 60,
                                half_open if name in ("view", "metrics") else b"")
            gates = {"view": viewer.gate, "metrics": metrics.gate, "modbus": facade.gate}
            _wait(lambda: all(g.refused >= 40 for g in gates.values()), 20, "refusals")
            peak_fds = _fds()
            print(f"flood of 4 x 60 connections: fds {base_fds} -> {peak_fds}; refused "
                  f"{ {k: g.refused for k, g in gates.items()} }, open "
                  f"{ {k: g.open for k, g in gates.items()} }")
            for g in gates.values():
                assert g.open <= g.cap and g.peak <= g.cap
            assert peak_fds - base_fds <= 260 + 3 * 20 + 64 + 10  # ours + the servers' caps
            library = throttle_library_logs().counts  # asyncua's refusals, counted
            _wait(lambda: any("Refusing connection" in k for k in library), 20, "OPC UA cap")
            # the half-open and silent ones are closed after their timeout
            _wait(lambda: all(g.open == 0 for g in gates.values()), 20, "timeouts")
            assert cell.kernel.steps > steps0 + 50  # the control loop kept running
            assert _read_registers(facade.port) is not None  # a new Modbus client is served
            counts = {**viewer.gate.throttle.counts, **facade.gate.throttle.counts}
            assert any("refused at the cap" in k for k in counts), counts
            assert any("no complete request" in k for k in counts), counts
            assert any("silent for" in k for k in counts), counts
        finally:
            for s in socks:
                s.close()
            metrics.stop()


# ---- junk, and its log ---------------------------------------------------------------------
class _Bytes(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.size = 0
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        text = self.format(record)
        self.size += len(text) + 1
        self.lines.append(text)


def test_a_junk_flood_leaves_a_short_log_and_answers_in_modbus_form(cell: System) -> None:
    root = logging.getLogger()
    sink = _Bytes()
    sink.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    old = root.level
    root.addHandler(sink)
    root.setLevel(logging.INFO)
    try:
        with ModbusFacade(cell) as facade, \
                OpcUaServer(cell, "opc.tcp://127.0.0.1:0/chcos/") as opcua:
            facade.start()
            opcua.start()
            sink.size, sink.lines = 0, []
            # a request with the exception bit set: answered ILLEGAL_FUNCTION, Modbus' form
            with socket.create_connection(("127.0.0.1", facade.port), timeout=5) as s:
                s.sendall(struct.pack(">HHHBBB", 7, 0, 3, 1, 0x81, 0x02))
                answer = s.recv(64)
            assert answer == struct.pack(">HHHBBB", 7, 0, 3, 1, 0x81, 0x01), answer.hex()
            junk = [os.urandom(40), b"\xff" * 300, struct.pack(">HHHBB", 1, 0, 2, 1, 0x99),
                    struct.pack(">HHHBBB", 1, 0, 3, 1, 0x83, 0), b"HEL\x00junkjunk",
                    b"MSGF" + os.urandom(60), b"OPNF\xff\xff\x00\x00" + os.urandom(20)]
            sent = 0
            for port in (facade.port, opcua.port):
                for i in range(1050):
                    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
                        s.sendall(junk[i % len(junk)])
                        sent += 1
            assert _read_registers(facade.port) is not None
        size = sink.size
    finally:
        root.removeHandler(sink)
        root.setLevel(old)
    print(f"junk flood: {sent} packets, {size} bytes of log in {len(sink.lines)} lines")
    assert sent == 2100
    assert size < 10_000, "\n".join(sink.lines[:40])
    assert not any("Traceback" in line for line in sink.lines)
    assert not any("update datastore called wrongly" in line for line in sink.lines)


# ---- metrics access ------------------------------------------------------------------------
def test_metrics_need_the_bearer_token(cell: System, tmp_path: Path) -> None:
    token = tmp_path / "token"
    token.write_text("0123456789abcdef0123456789abcdef\n")
    with pytest.raises(NorthError, match="--metrics-token"):
        serve_metrics(cell, "192.0.2.1", 0, certfile="c.pem", keyfile="k.pem")
    short = tmp_path / "short"
    short.write_text("abc\n")
    with pytest.raises(NorthError, match="at least 16 characters"):
        serve_metrics(cell, token_file=str(short))
    m = serve_metrics(cell, token_file=str(token))
    try:
        async def fetch(headers: dict[str, str]) -> tuple[int, str]:
            async with aiohttp.ClientSession() as session, \
                    session.get(m.url, headers=headers) as r:
                return r.status, await r.text()
        status, body = asyncio.run(fetch({}))
        assert status == 401 and "chcos_" not in body
        status, body = asyncio.run(fetch({"Authorization": "Bearer wrong"}))
        assert status == 401 and "chcos_" not in body
        status, body = asyncio.run(fetch(
            {"Authorization": "Bearer 0123456789abcdef0123456789abcdef"}))
        assert status == 200 and "chcos_device_value" in body
        assert m.unauthorized == 2
    finally:
        m.stop()
