"""``chcos sim --from`` and ``chcos run`` in two processes on a machine without vcan (issue 39):
the map's CAN bus on python-can's ``udp_multicast`` interface (group and port in the map), both
processes inside a network namespace of the test's own whose only interface is loopback (so no
datagram leaves it), and the real-time run hears the simulator's frames and drives its node."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from chcos.devices.devmap import check
from vcan_tests.support_netns import loopback_only

ROOT = Path(__file__).resolve().parent.parent

MAP = """\
[[bus]]
name = "cell"
kind = "can"
interface = "udp_multicast"
channel = "239.74.163.{group}"
port = {port}

[[device]]
name = "pressure"
direction = "sensor"
bus = "cell"
address = {{ id = 0x100, start = 0, length = 16 }}
stale_after = 0.5

[[device]]
name = "pump"
direction = "actuator"
bus = "cell"
address = {{ id = 0x200, start = 0, length = 16 }}
limits = [0, 1000]
safe_value = 0
"""

TASK = '''\
async def main(ctx, command):
    while True:
        pressure = await ctx.read("pressure")
        ctx.write("pump", 500 if pressure < 100 else 0)
'''


@pytest.fixture
def netns() -> object:
    """A network namespace with loopback only (and a multicast route on it); removed after."""
    with loopback_only("c39x") as name:
        yield name


def _cmd(ns: str, *args: str) -> list[str]:
    return ["ip", "netns", "exec", ns, sys.executable, "-m", "chcos.cli.main", *args]


def test_sim_and_run_in_two_processes_over_udp_multicast(tmp_path: Path, netns: str) -> None:
    (tmp_path / "can.toml").write_text(MAP.format(group=7, port=43117), encoding="utf-8")
    (tmp_path / "tasks").mkdir()
    (tmp_path / "tasks" / "hold.py").write_text(TASK, encoding="utf-8")
    (tmp_path / "install.chcos").write_text("install -m0 sysfile\n"
                                            "install -m0i1o1 hold pressure pump\n"
                                            "invoke hold\n", encoding="utf-8")
    (tmp_path / "system.toml").write_text(
        '[system]\nname = "two"\ndevmaps = ["can.toml"]\ntask_path = ["tasks"]\n'
        'install = "install.chcos"\n', encoding="utf-8")
    dmap, errors, _ = check([tmp_path / "can.toml"])
    assert dmap is not None, errors
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    sim = subprocess.Popen(_cmd(netns, "sim", "--from", "can.toml", "--value", "pressure=42",
                                "--every", "0.2"),
                           cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, env=env)
    lines: list[str] = []
    ready = threading.Event()

    def read() -> None:
        assert sim.stdout is not None
        for line in sim.stdout:
            lines.append(line)
            if "simulating cell" in line:
                ready.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert ready.wait(60), "".join(lines)
        assert "udp_multicast channel 239.74.163.7" in "".join(lines)
        run = subprocess.run(_cmd(netns, "run", "system.toml", "--duration", "3",
                                  "--outputs", "on"),
                             cwd=tmp_path, capture_output=True, text=True, env=env, timeout=120)
        assert run.returncode == 0, run.stdout + run.stderr
        summary = run.stdout.split("summary")[-1]
        assert "sensor   pressure         last 42" in summary, summary
        assert "healthy" in summary
        # what the simulated node received from the other process: 500 while it ran, then the
        # safe value
        deadline = threading.Event()
        for _ in range(100):
            if any("pump=0" in ln for ln in lines) and any("pump=500" in ln for ln in lines):
                break
            deadline.wait(0.1)
        shown = "".join(lines)
        assert "pump=500" in shown and shown.rfind("pump=0") > shown.find("pump=500"), shown
    finally:
        sim.terminate()
        sim.wait(timeout=30)
