"""support_view - helpers for the viewer tests: the figure 6.5 system, HTTP on 127.0.0.1, SSE,
and a headless Debian chromium driven by Playwright (never a downloaded browser)."""

from __future__ import annotations

import json
import shutil
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.apps import fig65
from chcos.apps.fig65.common import condense
from chcos.apps.fig65.runner import default_devmap
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import Clock, VirtualClock
from chcos.serving.auth import User, Users, hash_password
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from chcos.viewer.snapshot import EventLog

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
DOCS = Path(__file__).resolve().parent.parent / "docs"
TIMEOUT = 10.0
FIG65_TASKS = ("A1", "A2", "A3", "A4", "B1", "B2", "C1")

# loopback only, whatever proxy the environment names
_opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def fig65_system(workdir: Path, clock: Clock | None = None, invoke: bool = True) -> System:
    """The figure 6.5 system (thesis install script run, C1 invoked) with its files in
    ``workdir``; on a VirtualClock unless ``clock`` is given. Not started. An EventLog listens
    from the start, so a viewer shows the installs too."""
    shutil.copy(fig65.HERE / "testfile", workdir / "testfile")
    s = System([default_devmap()], clock=clock or VirtualClock(), task_path=[fig65.HERE],
               base_dir=workdir, map_path=workdir / "sysfile.map")
    s.kernel.add_instrument(EventLog(s.kernel.clock))
    s.run_script(fig65.SCRIPT)
    if invoke:
        s.execute("invoke C1")
    return s


async def follow(ctx: TaskContext, command: Any) -> None:
    """Task code: drive the actuator from the sensor (the fig65 loop)."""
    await condense(ctx, actuator=ctx.outputs[0])


async def halt(ctx: TaskContext, command: Any) -> None:
    """Task code: an emergency stop when invoked, then a normal completion."""
    ctx.estop(f"halt by {ctx.name}: {command}")
    ctx.complete("halted")


async def crash(ctx: TaskContext, command: Any) -> None:
    """Task code: fails at once (an abnormal completion)."""
    raise RuntimeError(f"{ctx.name} crashed on purpose")


def small_cell(workdir: Path, clock: Clock | None = None) -> System:
    """A cell that is not fig65: in-memory sensor P1 (stale after 0.3 s without data) and
    actuator V1 on machine 0; T1 follows P1 on V1, H2 above it halts (estop) and X2 above it
    crashes when invoked. Nothing is invoked; an EventLog listens from the start."""
    me = "vcan_tests.support_view"
    devmap = DeviceMap((BusSpec("mem", "memory"),), (
        DeviceSpec("P1", "sensor", 0, "mem", stale_after=0.3, units="bar"),
        DeviceSpec("V1", "actuator", 0, "mem", safe_value=0.0, limits=(-100, 100), units="%")))
    s = System(devmap, clock=clock or VirtualClock(), base_dir=workdir,
               map_path=workdir / "sysfile.map")
    s.kernel.add_instrument(EventLog(s.kernel.clock))
    for line in ("install -m0 sysfile",
                 f"install -m0i1o1 --code={me}:follow T1 P1 V1",
                 f"install -m0o1 --code={me}:halt H2 T1",
                 f"install -m0i1 --code={me}:crash X2 T1"):
        s.execute(line)
    return s


def get(url: str) -> tuple[int, str]:
    """GET ``url`` (127.0.0.1 only); (status, body) also for error statuses."""
    assert url.startswith("http://127.0.0.1:"), url
    try:
        with _opener.open(url, timeout=TIMEOUT) as resp:
            return int(resp.status), resp.read().decode()
    except urllib.error.HTTPError as exc:
        return int(exc.code), exc.read().decode()


def get_json(url: str) -> Any:
    """GET ``url`` and decode its JSON body (asserting status 200)."""
    status, body = get(url)
    assert status == 200, body
    return json.loads(body)


#: Accounts for the viewer tests (a cheap hash: 1000 PBKDF2 rounds).
PASSWORDS = {"alice": "alice-pw", "sam": "sam-pw", "olga": "olga-pw"}
ROLES = {"alice": "operator", "sam": "supervisor", "olga": "observer"}


def viewer_users() -> Users:
    """alice (operator), sam (supervisor), olga (observer); passwords in PASSWORDS."""
    return Users({n: User(n, ROLES[n], hash_password(pw, 1000)) for n, pw in PASSWORDS.items()})


@dataclass
class Login:
    """A logged-in viewer session: its cookie header and command token."""

    cookie: str
    token: str

    def headers(self) -> dict[str, str]:
        """The headers a command from this session carries."""
        return {"Cookie": self.cookie, "X-CHCOS-Token": self.token}


def login(base: str, user: str = "alice") -> Login:
    """Log ``user`` in on the viewer at ``base`` (its URL); raises AssertionError if refused."""
    req = urllib.request.Request(base + "api/login", method="POST",
                                 data=json.dumps({"user": user,
                                                  "password": PASSWORDS[user]}).encode(),
                                 headers={"Content-Type": "application/json"})
    with _opener.open(req, timeout=TIMEOUT) as resp:
        body = json.loads(resp.read())
        cookie = resp.headers["Set-Cookie"].split(";")[0]
    assert body["ok"] and "HttpOnly" in resp.headers["Set-Cookie"]
    return Login(cookie, body["token"])


def post_json(url: str, payload: Any, session: Login | None = None,
              headers: dict[str, str] | None = None) -> tuple[int, Any]:
    """POST ``payload`` as JSON (bytes as they are) with ``session``'s cookie and token;
    (status, decoded JSON answer)."""
    assert url.startswith("http://127.0.0.1:"), url
    data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
    hdrs = {"Content-Type": "application/json", **(session.headers() if session else {}),
            **(headers or {})}
    req = urllib.request.Request(url, data=data, method="POST", headers=hdrs)
    try:
        with _opener.open(req, timeout=TIMEOUT) as resp:
            return int(resp.status), json.loads(resp.read())
    except urllib.error.HTTPError as exc:
        return int(exc.code), json.loads(exc.read())


def sse_messages(url: str, count: int) -> list[dict[str, Any]]:
    """The first ``count`` server-sent ``data:`` messages of ``url``, decoded from JSON."""
    out: list[dict[str, Any]] = []
    with _opener.open(url, timeout=TIMEOUT) as resp:
        assert resp.headers["Content-Type"].startswith("text/event-stream")
        for raw in resp:
            line = raw.decode().rstrip("\n")
            if line.startswith("data: "):
                out.append(json.loads(line[6:]))
                if len(out) == count:
                    break
    return out


@contextmanager
def browser_page() -> Iterator[Any]:
    """A Playwright page in headless Debian chromium; skips the test (fails under CI=true) when
    chromium is missing."""
    from playwright import sync_api

    from vcan_tests.conftest import require

    require(CHROMIUM.exists(), f"{CHROMIUM} (apt-get install chromium): browser tests need it")
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1600, "height": 1100})
            page.set_default_timeout(TIMEOUT * 1000)
            yield page
        finally:
            browser.close()


async def idle(ctx: TaskContext, command: Any) -> None:
    """Task code: completes at once."""
    ctx.complete("ok")


def big_cell(workdir: Path, clock: Clock | None = None, tasks: int = 60) -> System:
    """A wide hierarchy of ``tasks`` tasks (half on level 1 over one sensor each, a third on
    level 2 above them, the rest on level 3 commanding them), for the legibility tests."""
    n1, n2 = tasks // 2, tasks // 3
    n3 = tasks - n1 - n2
    devmap = DeviceMap((BusSpec("mem", "memory"),), tuple(
        DeviceSpec(f"D{i}", "sensor", 0, "mem", units="mm") for i in range(n1)))
    s = System(devmap, clock=clock or VirtualClock(), base_dir=workdir,
               map_path=workdir / "sysfile.map")
    s.kernel.add_instrument(EventLog(s.kernel.clock))
    code = "--code=vcan_tests.support_view:idle"
    s.execute("install -m0 sysfile")
    for i in range(n1):
        s.execute(f"install -m0i1 {code} T{i} D{i}")
    for i in range(n2):
        s.execute(f"install -m0i1 {code} U{i} T{i}")
    for i in range(n3):
        s.execute(f"install -m0o1 {code} V{i} U{i}")
    return s
