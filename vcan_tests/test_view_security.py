"""The live view's security with aiohttp's test client: Host and Origin checked against the
viewer's own address (DNS rebinding, cross-site pages), commands only with a session cookie and
its token as JSON (no CSRF through forms or text/plain), roles, refusals 4xx with a reason; and
stalled stream clients dropped with their buffers (real sockets that never read)."""

from __future__ import annotations

import asyncio
import gc
import socket
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp.test_utils import TestClient, TestServer

from chcos.kernel.clock import RealClock, VirtualClock
from chcos.system.embedded import System
from chcos.viewer.server import Viewer, serve
from vcan_tests.support_view import PASSWORDS, fig65_system, viewer_users


@pytest.fixture
def fig65(tmp_path: Path) -> Iterator[System]:
    """The figure 6.5 system on virtual time, C1 invoked, 1 s run."""
    s = fig65_system(tmp_path, VirtualClock())
    s.run_for(1.0)
    yield s
    s.shutdown()


async def _with_client(viewer: Viewer, body: Any) -> Any:
    server = TestServer(viewer.app(), host="127.0.0.1")
    async with TestClient(server) as client:
        viewer.port = server.port or 0
        return await body(client, f"127.0.0.1:{viewer.port}")


def run(viewer: Viewer, body: Any) -> Any:
    """Run ``body(client, own_host)`` against the viewer's app on a test server."""
    return asyncio.run(_with_client(viewer, body))


async def _login(client: TestClient[Any, Any], user: str = "alice") -> str:
    resp = await client.post("/api/login", json={"user": user, "password": PASSWORDS[user]})
    assert resp.status == 200, await resp.text()
    body = await resp.json()
    assert "HttpOnly" in resp.headers["Set-Cookie"]
    assert "SameSite=Strict" in resp.headers["Set-Cookie"]
    return str(body["token"])


def test_cross_origin_and_simple_requests_are_refused(fig65: System) -> None:
    viewer = Viewer(fig65, users=viewer_users())
    before = fig65.sysmgr.map_doc()

    async def body(client: TestClient[Any, Any], own: str) -> None:
        token = await _login(client)  # even a logged-in operator's browser is safe
        # the attack: text/plain from another origin
        r = await client.post("/api/command", data='{"line": "invoke C1"}',
                              headers={"Content-Type": "text/plain",
                                       "Origin": "http://evil.example"})
        assert r.status == 403 and "cross-site" in (await r.json())["error"]
        # same, no Origin (old browsers, forms): refused because it is not JSON
        r = await client.post("/api/command", data='{"line": "invoke C1"}',
                              headers={"Content-Type": "text/plain", "X-CHCOS-Token": token})
        assert r.status == 415 and "application/json" in (await r.json())["error"]
        r = await client.post("/api/command", data={"line": "invoke C1"})
        assert r.status == 415
        # JSON but without the session's token (a cross-site fetch cannot read it)
        r = await client.post("/api/command", json={"line": "invoke C1"})
        assert r.status == 403 and "X-CHCOS-Token" in (await r.json())["error"]
        r = await client.post("/api/command", json={"line": "invoke C1"},
                              headers={"X-CHCOS-Token": "guess"})
        assert r.status == 403
        # DNS rebinding: the page reaches us under another name; neither read nor command
        r = await client.get("/api/snapshot", headers={"Host": "evil.example"})
        assert r.status == 421 and "DNS rebinding" in (await r.json())["error"]
        r = await client.get("/api/stream", headers={"Host": f"evil.example:{viewer.port}"})
        assert r.status == 421
        r = await client.post("/api/command", json={"line": "invoke C1"},
                              headers={"Host": "evil.example", "X-CHCOS-Token": token})
        assert r.status == 421
        # a same-origin page with the token is obeyed
        r = await client.post("/api/command", json={"line": "setpri -11 C1 B1"},
                              headers={"Origin": f"http://{own}", "X-CHCOS-Token": token})
        assert r.status == 200 and (await r.json())["answer"] == "C1/B1 priority 11"
        r = await client.get("/api/snapshot?svg=0",
                             headers={"Host": f"localhost:{viewer.port}"})
        assert r.status == 200

    run(viewer, body)
    after = fig65.sysmgr.map_doc()
    assert [t["activations"] for t in after["tasks"]] == \
        [t["activations"] for t in before["tasks"]]  # no refused invoke ran


def test_roles_and_refusals_are_4xx_with_a_reason(fig65: System) -> None:
    viewer = Viewer(fig65, users=viewer_users())

    async def body(client: TestClient[Any, Any], own: str) -> None:
        r = await client.post("/api/command", json={"line": "invoke C1"})
        assert r.status == 401 and "log in" in (await r.json())["error"]
        r = await client.post("/api/login", json={"user": "alice", "password": "wrong"})
        assert r.status == 401 and "wrong password" in (await r.json())["error"]
        r = await client.post("/api/login", data="user=alice&password=alice-pw",
                              headers={"Content-Type": "application/x-www-form-urlencoded"})
        assert r.status == 415
        token = await _login(client, "olga")  # an observer may look, not command
        r = await client.post("/api/command", json={"line": "invoke C1"},
                              headers={"X-CHCOS-Token": token})
        assert r.status == 403 and "role 'observer'" in (await r.json())["error"]
        token = await _login(client, "sam")  # a supervisor: still only setpri/invoke here
        for line in ("suspend A1", "resume A1", "install -m0i1 Z1 S1", "inject S1 3"):
            r = await client.post("/api/command", json={"line": line},
                                  headers={"X-CHCOS-Token": token})
            assert r.status == 403 and "only setpri and invoke" in (await r.json())["error"]
        for line, status in (("invoke C1 'x", 400), ("setpri -500 C1 B1", 400),
                             ("invoke NOPE", 400), ("frobnicate", 400)):
            r = await client.post("/api/command", json={"line": line},
                                  headers={"X-CHCOS-Token": token})
            assert r.status == status, (line, await r.text())
            assert (await r.json())["ok"] is False
        r = await client.get("/api/session")
        assert (await r.json())["role"] == "supervisor"
        await client.post("/api/logout", json={})
        r = await client.get("/api/session")
        assert (await r.json())["user"] is None

    run(viewer, body)
    assert all(t["status"] != "suspended" or t["name"] != "A1"
               for t in fig65.sysmgr.map_doc()["tasks"])


def _stalled_client(port: int) -> socket.socket:
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1024)
    s.connect(("127.0.0.1", port))
    s.sendall(f"GET /api/stream HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    return s


def test_stalled_clients_are_dropped_and_their_memory_released(tmp_path: Path) -> None:
    system = fig65_system(tmp_path, RealClock())  # live: every update differs
    system.start()
    tracemalloc.start()
    try:
        with serve(system, period=0.01, svg_period=0.0, stall_timeout=0.5,
                   max_buffer=64 * 1024) as v:
            gc.collect()
            base = tracemalloc.get_traced_memory()[0]
            socks = [_stalled_client(v.port) for _ in range(60)]
            try:
                assert v.wait_clients(lambda n: n == 60, 30), v.clients
                # every one of them stops reading: the viewer drops them all
                assert v.wait_clients(lambda n: n == 0, 60), v.clients
                assert v.dropped == 60
                gc.collect()
                held = tracemalloc.get_traced_memory()[0] - base
                assert held < 4 * 1024 * 1024, f"{held} bytes still held"
                # and it keeps serving
                live = _stalled_client(v.port)
                assert v.wait_clients(lambda n: n == 1, 30)
                live.close()
            finally:
                for s in socks:
                    s.close()
    finally:
        tracemalloc.stop()
        system.shutdown()
