"""Support for the multi-satellite tests: a cluster of satellite processes on loopback, and the
tasks they run (module-level so satellites can load them by reference)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from chcos.comm.manager import machine_of
from chcos.satellites import sysfile
from chcos.satellites.host import Host
from chcos.user.context import TaskContext
from vcan_tests.netutil import free_port

ROOT = Path(__file__).resolve().parent.parent

DEVMAP = """
[[bus]]
name = "mem"
kind = "memory"

[[device]]
name = "S0"
direction = "sensor"
machine = 0
bus = "mem"

[[device]]
name = "S1"
direction = "sensor"
machine = 1
bus = "mem"

[[device]]
name = "M0"
direction = "actuator"
machine = 0
bus = "mem"
safe_value = 0
"""


async def worker(ctx: TaskContext, cmd: dict[str, Any]) -> str:
    """Works ``work`` seconds for whoever invoked it, then completes."""
    ctx.world.command["serving"] = cmd.get("who")
    await ctx.sleep(float(cmd.get("work", 1.0)))
    return f"done for {cmd.get('who')}"


async def boss(ctx: TaskContext, cmd: dict[str, Any] | None) -> None:
    """Invokes W (its only output), asks W's world model whom it serves, and keeps both and
    how the command ended in its own world model."""
    cmd = cmd or {}
    await ctx.invoke("W", {"who": ctx.name, "work": cmd.get("work", 1.0)})
    ctx.world.command["owns"] = "W"
    ctx.world.command["W serves"] = await ctx.ask("W", "serving", timeout=10.0)
    done = await ctx.done("W")
    ctx.world.sensory["W"] = done.status.value


async def relay(ctx: TaskContext, cmd: Any) -> None:
    """Passes every reading of its input up and to its actuator, if it has one."""
    while True:
        value = await ctx.read(0)
        ctx.put(value)
        if ctx.outputs:
            ctx.write(0, value)


class Cluster:
    """Satellite processes of one system on free loopback ports, and a host to drive them."""

    def __init__(self, tmp: Path, machines: tuple[int, ...] = (0, 1, 2),
                 auth: bool = False, cpus: dict[int, list[int]] | None = None) -> None:
        self.tmp = tmp
        (tmp / "devices.toml").write_text(DEVMAP)
        name = f"t{os.getpid()}{free_port()}"
        pins = cpus or {}
        sats = "\n".join(f"[[satellite]]\nmachine = {m}\nport = {free_port()}\n"
                         + (f"cpus = {pins[m]}\n" if m in pins else "")
                         for m in machines)
        link = ""
        if auth:
            (tmp / "users.txt").write_text("host:s3cret\nsat:s3cret\n")
            link = ('[link.auth]\nuser = "sat"\npassword = "s3cret"\n'
                    'dictionary_file = "users.txt"\n')
        (tmp / "system.toml").write_text(
            f'[system]\nname = "{name}"\ndevmaps = ["devices.toml"]\nbase_dir = "."\n'
            f'state_dir = "state"\n\n'
            f"{sats}\n{link}")
        self.sf = sysfile.load(tmp / "system.toml")
        self.procs: dict[int, subprocess.Popen[bytes]] = {}
        self._host: Host | None = None

    def start(self, machine: int, env: dict[str, str] | None = None) -> None:
        """Start satellite ``machine`` as a separate process (``env``: more environment)."""
        env = dict(os.environ, PYTHONPATH=str(ROOT), **(env or {}))
        log = open(self.tmp / f"sat{machine}.log", "ab")  # noqa: SIM115 - the child keeps it
        self.procs[machine] = subprocess.Popen(
            [sys.executable, "-m", "chcos.cli.main", "-v", "satellite", "-m", str(machine),
             "--system", str(self.sf.path)], cwd=ROOT, env=env, stdout=log, stderr=log,
            stdin=subprocess.DEVNULL)

    def kill(self, machine: int, timeout: float = 20.0) -> None:
        """kill -9 satellite ``machine``; with a host session, also wait until the host no
        longer sees its liveliness token (a dead process's token outlives it until Zenoh
        notices the closed link: a restart right after would otherwise find the old token, and
        ``wait_for`` would answer before the new satellite serves). Raises AssertionError if
        the token is still there after ``timeout`` seconds."""
        p = self.procs.pop(machine)
        p.send_signal(signal.SIGKILL)
        p.wait(10)
        if self._host is None:
            return
        host = self._host
        gone = threading.Event()

        def left(key: str) -> None:
            if machine_of(key) == machine:
                gone.set()

        with host.transport.watch(f"{self.sf.prefix}/alive/*", lambda key: None, left):
            if machine not in host.tokens():  # the token, not a hello: see above
                return
            assert gone.wait(timeout), f"satellite {machine} still seen {timeout} s after kill -9"

    @property
    def host(self) -> Host:
        """A host session (made on first use)."""
        if self._host is None:
            self._host = Host(self.sf, timeout=15.0)
        return self._host

    def wait_until(self, pred: Callable[[dict[str, Any]], bool], timeout: float = 20.0,
                   machine: int | None = None) -> dict[str, Any]:
        """Poll the merged system map (each poll is a round trip to the satellites) until
        ``pred(map)`` holds; raises AssertionError with the last map after ``timeout``."""
        deadline = time.monotonic() + timeout
        doc: dict[str, Any] = {}
        while time.monotonic() < deadline:
            doc = self.host.map_doc(machine)
            if pred(doc):
                return doc
        raise AssertionError(f"condition not met in {timeout} s; last map: {doc}")

    def close(self) -> None:
        """Stop the host and every satellite."""
        if self._host is not None:
            self._host.close()
        for p in self.procs.values():
            p.terminate()
        for p in self.procs.values():
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def task(doc: dict[str, Any], name: str) -> dict[str, Any]:
    """The map entry of task ``name``."""
    return next(t for t in doc["tasks"] if t["name"] == name)


def link(doc: dict[str, Any], src: str, dst: str) -> dict[str, Any]:
    """The map entry of link ``src``/``dst``."""
    return next(lk for lk in doc["links"] if lk["src"] == src and lk["dst"] == dst)


def device(doc: dict[str, Any], name: str) -> dict[str, Any]:
    """The map entry of device ``name``."""
    return next(d for d in doc["devices"] if d["name"] == name)
