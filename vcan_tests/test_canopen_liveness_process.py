"""A stopped controller (SIGSTOP) noticed by the node, on the host (issue 46): ``chcos run``
drives a durand node with a heartbeat consumer (:mod:`vcan_tests.support_canopen_node`) in
another process, both on python-can's ``udp_multicast`` interface inside a network namespace of
the test's own (as :mod:`vcan_tests.test_canopen_master_kill`). The run is stopped, not killed:
its process lives, its sockets stay open, yet nothing of it runs - the node's own process
reports that its consumer declared the master lost, sent EMCY 0x8130 and left OPERATIONAL; once
the run is continued (SIGCONT) the node hears its heartbeat again."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

from vcan_tests.test_canopen_master_kill import GROUP, MAP, NODE, ROOT, Lines, _in, netns

__all__ = ["netns"]     # the fixture, from the kill test


def test_the_node_notices_a_stopped_controller_and_hears_it_again(tmp_path: Path,
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
            '[system]\nname = "stop"\ndevmaps = ["co.toml"]\ninstall = "install.chcos"\n',
            encoding="utf-8")
        run = subprocess.Popen(_in(netns, sys.executable, "-m", "chcos.cli.main", "run",
                                   "system.toml", "--duration", "600"),
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env=env, cwd=tmp_path)
        run_out = Lines(run)
        assert node_out.wait("consumer of node 127 every 1000 ms", "state OPERATIONAL",
                             "consumer armed"), node_out.text() + "\n--- run:\n" + run_out.text()
        assert "producer heartbeat lost" not in node_out.text()
        stopped = node_out.count()
        os.kill(run.pid, signal.SIGSTOP)
        assert node_out.wait("producer heartbeat lost", "emcy 0x8130", "state PRE_OPERATIONAL",
                             after=stopped), node_out.text()
        assert run.poll() is None                        # stopped, not dead
        continued = node_out.count()
        os.kill(run.pid, signal.SIGCONT)
        assert node_out.wait("producer heartbeat back", after=continued), node_out.text()
    finally:
        if run is not None and run.poll() is None:
            os.kill(run.pid, signal.SIGCONT)
            run.kill()
            run.wait(timeout=60)
        if node.stdin is not None:
            node.stdin.close()
        try:
            node.wait(timeout=60)
        except subprocess.TimeoutExpired:
            node.kill()
            node.wait(timeout=60)
