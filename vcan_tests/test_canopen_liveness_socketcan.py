"""A frozen controller on real SocketCAN (runs inside the User-Mode-Linux guest; issue 46): the
master heartbeat and SYNC come from producer processes of the driver's own
(:mod:`drivers.canopen_heartbeat`, :mod:`drivers.canopen_sync`), which live on when the
controller process is stopped (SIGSTOP) - so they go out only while the controller feeds their
liveness gate. candump (can-utils, an observer written by nobody here) shows the heartbeat and
SYNC stop while the controller is stopped and come back after SIGCONT; the controller then
reports what was held (``controller-stalled``) and the SYNC cycles given up. A controller whose
kernel is held by a task (the process running) stops them the same way."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from drivers.canopen_sync import producer_processes
from vcan_tests.support_controller import ROOT
from vcan_tests.support_faults import wait_until
from vcan_tests.support_fb import WAIT

MASTER = 100
LIVENESS_MS = 200
#: the longest a heartbeat may still come after the controller froze: the gate's time, a
#: quarter of it for the feed's look, a period in flight - and a loaded guest's scheduling
BOUND = 1.0

#: a controller (a driver on the guest's bus) that says "started", runs until its stdin ends,
#: then prints its bus errors and the SYNC cycles given up
CONTROLLER = """
import sys
from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.support_fb import FakeHost

bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={{
    "interface": "socketcan", "channel": "{channel}", "master_heartbeat_ms": 20,
    "master_node_id": {master}, "sync_period": 0.01, "liveness_ms": {liveness},
    "sdo_timeout": 0.05, "nodes": [{{"id": 42, "eds": "{eds}", "nmt_start": False}}]}})
host = FakeHost()
driver = CanopenDriver(bus, [], host)
driver.start()
print("started", flush=True)
sys.stdin.read()
stats = driver.sync_stats()
driver.stop()
print("given-up", stats.given_up if stats else -1, flush=True)
for e in host.errors:
    print("error", e[1], e[2], flush=True)
"""


class Candump:
    """``candump -L`` on the channel for the master heartbeat and SYNC: each frame's receive
    time (the kernel's, as candump prints it) and id, read on a thread."""

    def __init__(self, channel: str) -> None:
        self.frames: list[tuple[float, int]] = []
        self._cond = threading.Condition()
        self._proc = subprocess.Popen(
            ["candump", "-L", f"{channel},{0x700 + MASTER:03X}:7FF,080:7FF"],
            stdout=subprocess.PIPE, text=True)
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        assert self._proc.stdout is not None
        for line in self._proc.stdout:
            parts = line.split()          # (1700000000.123456) vcan0 764#05
            if len(parts) == 3 and "#" in parts[2]:
                with self._cond:
                    self.frames.append((float(parts[0].strip("()")),
                                        int(parts[2].split("#")[0], 16)))
                    self._cond.notify_all()

    def of(self, cob: int, since: float = 0.0) -> list[float]:
        with self._cond:
            return [t for t, c in self.frames if c == cob and t >= since]

    def wait(self, cob: int, n: int, since: float = 0.0) -> bool:
        with self._cond:
            return self._cond.wait_for(lambda: len(self.of(cob, since)) >= n, WAIT)

    def close(self) -> None:
        self._proc.terminate()
        self._proc.wait(WAIT)


def quiet_since(dump: Candump, cob: int, gap: float) -> float | None:
    """Wait until ``cob`` has not been seen for ``gap`` s (wall clock); the time of its last
    frame then, or None if it kept coming for :data:`WAIT` s."""
    deadline = time.time() + WAIT
    while time.time() < deadline:
        last = max(dump.of(cob), default=0.0)
        if time.time() - last >= gap:
            return last
        threading.Event().wait(0.05)
    return None


@pytest.mark.socketcan
def test_a_stopped_controller_stops_its_heartbeat_and_sync_and_says_so(tmp_path: Path) -> None:
    from vcan_tests import uml

    channel = uml.can_channel("socketcan")
    dump = Candump(channel)
    script = tmp_path / "controller.py"
    script.write_text(textwrap.dedent(CONTROLLER.format(
        channel=channel, master=MASTER, eds=SERVO_EDS, liveness=LIVENESS_MS)),
        encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert proc.stdout is not None and proc.stdin is not None
        assert proc.stdout.readline().strip() == "started"
        assert dump.wait(0x700 + MASTER, 100) and dump.wait(0x080, 10)
        assert producer_processes(proc.pid, "heartbeat") and producer_processes(proc.pid)
        beats = dump.of(0x700 + MASTER)
        gaps = sorted(b - a for a, b in itertools.pairwise(beats))
        print(f"master heartbeat every 20 ms: {len(gaps)} intervals, median "
              f"{gaps[len(gaps) // 2] * 1000:.1f} ms, max {gaps[-1] * 1000:.1f} ms")
        stopped = time.time()
        os.kill(proc.pid, signal.SIGSTOP)          # the controller freezes, its children not
        last_beat = quiet_since(dump, 0x700 + MASTER, 0.5)
        last_sync = quiet_since(dump, 0x080, 0.5)
        assert last_beat is not None and last_sync is not None, "still produced while stopped"
        assert last_beat - stopped < BOUND and last_sync - stopped < BOUND, \
            (last_beat - stopped, last_sync - stopped)
        print(f"SIGSTOP: last master heartbeat {last_beat - stopped:.3f} s after it, last SYNC "
              f"{last_sync - stopped:.3f} s (liveness_ms {LIVENESS_MS})")
        held = time.time()
        assert wait_until(lambda: time.time() > held + 0.3)     # held for a while more
        assert dump.of(0x700 + MASTER, last_beat + 1e-6) == []
        resumed = time.time()
        os.kill(proc.pid, signal.SIGCONT)
        assert dump.wait(0x700 + MASTER, 5, resumed) and dump.wait(0x080, 5, resumed)
        proc.stdin.close()
        out = proc.stdout.read()
        assert proc.wait(WAIT) == 0, out
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
            proc.wait(WAIT)
        dump.close()
    lines = out.splitlines()
    given_up = int(next(line for line in lines if line.startswith("given-up")).split()[1])
    assert given_up > 0, out
    stalls = [line for line in lines if line.startswith("error controller-stalled")]
    assert any("master heartbeat" in s and "held" in s for s in stalls), out
    assert any("SYNC" in s and "held" in s for s in stalls), out


#: a controller with a device table (a System on SocketCAN) whose task holds the kernel while
#: the process runs: released, and the run ended, when its stdin ends
HELD_KERNEL = """
import sys, threading
from pathlib import Path
from chcos.system.embedded import System

release = threading.Event()
entered = threading.Event()

async def hog(ctx, cmd):
    entered.set()
    release.wait(60)

map_path = Path("{where}") / "co.toml"
map_path.write_text('''
[[bus]]
name = "co"
kind = "canopen"
interface = "socketcan"
channel = "{channel}"
master_heartbeat_ms = 20
master_node_id = {master}
liveness_ms = {liveness}
sdo_timeout = 0.05
nodes = [{{ id = 42, eds = "{eds}", nmt_start = false }}]

[[device]]
name = "type"
direction = "sensor"
bus = "co"
address = {{ node = 42, index = 0x1000, poll_period = 0.5 }}
''')
s = System([map_path], machines=[0])
s.execute("install -m0 --code=__main__:hog T")
s.start()
print("started", flush=True)
sys.stdin.readline()
s.call(s.invoke, "T", {{}})
entered.wait(60)
print("held", flush=True)
sys.stdin.readline()
release.set()
print("released", flush=True)
sys.stdin.read()
s.shutdown()
"""


@pytest.mark.socketcan
def test_a_held_kernel_stops_the_heartbeat_while_the_process_runs(tmp_path: Path) -> None:
    from vcan_tests import uml

    channel = uml.can_channel("socketcan")
    dump = Candump(channel)
    script = tmp_path / "controller.py"
    script.write_text(textwrap.dedent(HELD_KERNEL.format(
        where=tmp_path, channel=channel, master=MASTER, eds=SERVO_EDS, liveness=LIVENESS_MS)),
        encoding="utf-8")
    proc = subprocess.Popen([sys.executable, str(script)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)})
    try:
        assert proc.stdout is not None and proc.stdin is not None
        assert proc.stdout.readline().strip() == "started"
        assert dump.wait(0x700 + MASTER, 10)
        proc.stdin.write("hold\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "held"
        held = time.time()
        last = quiet_since(dump, 0x700 + MASTER, 0.5)
        assert last is not None, "the heartbeat went on while the kernel was held"
        assert last - held < BOUND
        print(f"held kernel: last master heartbeat {last - held:.3f} s after the hold began "
              f"(liveness_ms {LIVENESS_MS})")
        proc.stdin.write("release\n")
        proc.stdin.flush()
        assert proc.stdout.readline().strip() == "released"
        assert dump.wait(0x700 + MASTER, 5, time.time())
        proc.stdin.close()
        assert proc.wait(WAIT) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)
        dump.close()
