"""A controller killed with SIGKILL, noticed by the node (issue 36): ``chcos run`` drives a durand
node with a heartbeat consumer (:mod:`vcan_tests.support_canopen_node`) in another process, both
on python-can's ``udp_multicast`` interface inside a network namespace of the test's own whose only
interface is loopback (no datagram leaves it). The run configures the node to watch the master's
heartbeat (0x1016) and to go PRE-OPERATIONAL on its loss (0x1029 = 0); the run is then killed
(no safe value, no clean stop: only its silence) and the node's own process reports that its
consumer declared the master lost, sent EMCY 0x8130 and left OPERATIONAL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from vcan_tests.support_netns import loopback_only

ROOT = Path(__file__).resolve().parent.parent
WAIT = 60.0
NODE = 5
GROUP = "239.74.163.36"

MAP = """\
[[bus]]
name = "co"
kind = "canopen"
interface = "udp_multicast"
channel = "{group}"
sdo_timeout = 0.5
master_heartbeat_ms = 50

[[bus.nodes]]
id = {node}
eds = "node.eds"
heartbeat_timeout = 1.0

[bus.nodes.config]
heartbeat_producer_ms = 50
master_consumer_ms = 1000
error_behaviour = 0

[[device]]
name = "target"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x607A }}
limits = [-1000000, 1000000]
safe_value = 0
"""


@pytest.fixture
def netns() -> Iterator[str]:
    """A network namespace with loopback only (and a multicast route on it); removed after."""
    with loopback_only("c36x") as name:
        yield name


class Lines:
    """The lines a process prints, read on a thread, waited on by content."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        self._cond = threading.Condition()
        self._proc = proc
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            with self._cond:
                self.lines.append(line.rstrip("\n"))
                self._cond.notify_all()

    def count(self) -> int:
        with self._cond:
            return len(self.lines)

    def wait(self, *texts: str, after: int = 0, timeout: float = WAIT) -> bool:
        """True once a line starting with each of ``texts`` was printed, in order, from line
        ``after`` on."""
        def seen() -> bool:
            at = after
            for text in texts:
                at = next((i for i, ln in enumerate(self.lines) if i >= at
                           and ln.startswith(text)), -1)
                if at < 0:
                    return False
            return True
        with self._cond:
            return self._cond.wait_for(seen, timeout)

    def text(self) -> str:
        with self._cond:
            return "\n".join(self.lines)


def _in(ns: str, *cmd: str) -> list[str]:
    return ["ip", "netns", "exec", ns, *cmd]


def test_the_node_notices_a_killed_controller_by_its_heartbeat(tmp_path: Path,
                                                               netns: str) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    node = subprocess.Popen(_in(netns, sys.executable, "-m", "vcan_tests.support_canopen_node",
                                "--interface", "udp_multicast", "--channel", GROUP,
                                "--node", str(NODE), "--eds", str(tmp_path / "node.eds")),
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env=env, cwd=tmp_path)
    node_out = Lines(node)
    run: subprocess.Popen[str] | None = None
    try:
        assert node_out.wait("ready"), node_out.text()
        (tmp_path / "co.toml").write_text(MAP.format(group=GROUP, node=NODE), encoding="utf-8")
        (tmp_path / "install.chcos").write_text("install -m0 sysfile\n", encoding="utf-8")
        (tmp_path / "system.toml").write_text(
            '[system]\nname = "kill"\ndevmaps = ["co.toml"]\ninstall = "install.chcos"\n',
            encoding="utf-8")
        # ip netns exec replaces itself with the command: the pid is chcos's own
        run = subprocess.Popen(_in(netns, sys.executable, "-m", "chcos.cli.main", "run",
                                   "system.toml", "--duration", "600"),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env=env, cwd=tmp_path)
        run_out = Lines(run)
        # configured by the run (consumer of node 127, 1 s), started, watching the master
        assert node_out.wait("consumer of node 127 every 1000 ms", "state OPERATIONAL"), \
            node_out.text() + "\n--- run:\n" + run_out.text()
        assert node_out.wait("consumer armed"), node_out.text()
        assert "producer heartbeat lost" not in node_out.text()
        killed = node_out.count()
        os.kill(run.pid, signal.SIGKILL)
        assert run.wait(timeout=WAIT) == -signal.SIGKILL
        # the node's side, after the kill: its consumer noticed, it said so (EMCY) and left
        # OPERATIONAL as 0x1029 says
        assert node_out.wait("producer heartbeat lost", "emcy 0x8130", "state PRE_OPERATIONAL",
                             after=killed), node_out.text()
        assert "safe value" not in run_out.text()        # killed: nothing of it but silence
    finally:
        if run is not None and run.poll() is None:
            run.kill()
            run.wait(timeout=WAIT)
        if node.stdin is not None:
            node.stdin.close()
        try:
            node.wait(timeout=WAIT)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait(timeout=WAIT)
