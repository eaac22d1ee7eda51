"""The viewer against password guessing and hostile bodies (issue 41): repeated wrong logins
from one client are slowed down (429 with Retry-After, growing waits on a virtual clock, other
clients unaffected, a right login clears the count) and a JSON body nested too deeply is a 400
naming the problem, never a 500, for a logged-in operator as for anybody; the metrics
endpoint refused off loopback names the options that give it TLS."""

from __future__ import annotations

import asyncio
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from aiohttp.test_utils import TestClient, TestServer

from chcos.kernel.clock import VirtualClock
from chcos.serving.auth import LoginThrottle
from chcos.system.embedded import System
from chcos.viewer.server import Viewer
from vcan_tests.support_view import PASSWORDS, fig65_system, viewer_users


class Clock:
    """Seconds, moved by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def fig65(tmp_path: Path) -> Iterator[System]:
    s = fig65_system(tmp_path, VirtualClock())
    s.run_for(1.0)
    yield s
    s.shutdown()


def run(viewer: Viewer, body: Any) -> Any:
    async def main() -> Any:
        server = TestServer(viewer.app(), host="127.0.0.1")
        async with TestClient(server) as client:
            viewer.port = server.port or 0
            return await body(client)
    return asyncio.run(main())


def test_repeated_wrong_logins_are_slowed_down(fig65: System) -> None:
    clock = Clock()
    viewer = Viewer(fig65, users=viewer_users(),
                    login_throttle=LoginThrottle(free=5, base=1.0, longest=60.0, clock=clock))

    async def body(client: TestClient[Any, Any]) -> None:
        async def attempt(password: str) -> tuple[int, Any, str | None]:
            r = await client.post("/api/login", json={"user": "alice", "password": password})
            return r.status, await r.json(), r.headers.get("Retry-After")

        for _ in range(5):  # the free attempts
            assert (await attempt("wrong"))[0] == 401
        status, _, _ = await attempt("wrong")  # the sixth is still judged, then bars 1 s
        assert status == 401
        status, doc, retry = await attempt(PASSWORDS["alice"])  # even the right one waits
        assert status == 429 and retry == "1" and "too many wrong logins" in doc["error"]
        clock.now += 1.0
        assert (await attempt("wrong"))[0] == 401  # barred 2 s now
        status, _, retry = await attempt("wrong")
        assert status == 429 and retry == "2"
        clock.now += 2.0
        assert (await attempt("wrong"))[0] == 401  # 4 s
        clock.now += 3.0
        assert (await attempt(PASSWORDS["alice"]))[1:] == (
            {"ok": False, "error": "too many wrong logins from 127.0.0.1 or for 'alice': "
                         "try again in 1 s"},
            "1")
        clock.now += 1.0
        assert (await attempt(PASSWORDS["alice"]))[0] == 200  # and the count is cleared
        for _ in range(5):
            assert (await attempt("wrong"))[0] == 401
        assert viewer.login_throttle.refused == 3

    run(viewer, body)


def test_throttle_is_per_client_and_bounded() -> None:
    clock = Clock()
    t = LoginThrottle(free=0, base=10.0, longest=30.0, clients=2, clock=clock)
    t.failed("10.0.0.1")
    assert t.wait("10.0.0.1") == 10.0 and t.wait("10.0.0.2") == 0.0
    for _ in range(5):
        t.failed("10.0.0.1")
    assert t.wait("10.0.0.1") == 30.0  # capped
    t.failed("10.0.0.2")
    t.failed("10.0.0.3")  # a third address: the least recently failed is forgotten
    assert t.wait("10.0.0.1") == 0.0 and t.wait("10.0.0.3") == 10.0


def test_deeply_nested_json_is_a_400(fig65: System) -> None:
    viewer = Viewer(fig65, users=viewer_users())
    deep = "[" * 20_000 + "]" * 20_000  # within the 64 KiB body limit, far past the parser

    async def body(client: TestClient[Any, Any]) -> None:
        r = await client.post("/api/login", json={"user": "alice",
                                                  "password": PASSWORDS["alice"]})
        token = (await r.json())["token"]
        for path in ("/api/command", "/api/login"):
            r = await client.post(path, data=deep, headers={
                "Content-Type": "application/json", "X-CHCOS-Token": token})
            assert r.status == 400, await r.text()
            assert "nested too deeply" in (await r.json())["error"]
        r = await client.post("/api/command", json={"line": "invoke C1"},
                              headers={"X-CHCOS-Token": token})
        assert r.status < 500  # the server is still there and answering

    run(viewer, body)


def test_metrics_off_loopback_names_options_that_exist(fig65: System) -> None:
    import argparse
    import re

    from chcos.north import NorthError
    from chcos.north.metrics import serve
    from chcos.north.services import add_north_arguments

    with pytest.raises(NorthError) as info:
        serve(fig65, "192.0.2.7", 0)
    named = re.findall(r"--[a-z-]+", str(info.value))
    assert named == ["--north-tls-cert", "--north-tls-key"]
    parser = argparse.ArgumentParser()
    add_north_arguments(parser)
    args = parser.parse_args(["--metrics", "192.0.2.7:9464", named[0], "c.pem", named[1],
                              "k.pem"])
    assert (args.north_tls_cert, args.north_tls_key) == ("c.pem", "k.pem")
