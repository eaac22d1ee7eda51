"""The SYNC producer process on real SocketCAN (runs inside the User-Mode-Linux guest): the
driver starts a process of its own that sends SYNC (drivers.canopen_sync.SyncProducerProcess);
SYNC is on the wire while the driver runs, and stops when the driver stops, when the controller
process is killed (SIGKILL: no shutdown code runs) and, reported, when the producer itself dies.
Asserted on the wire, through a socket of the test's own."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import can
import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from vcan_tests.support_faults import wait_until
from vcan_tests.support_fb import WAIT

ROOT = Path(__file__).resolve().parent.parent

CONTROLLER = """
import threading
from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.support_fb import FakeHost

bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={{
    "interface": "socketcan", "channel": "{channel}", "sync_period": 0.005,
    "sdo_timeout": 0.05, "nodes": [{{"id": 42, "eds": "{eds}", "nmt_start": False}}]}})
CanopenDriver(bus, [], FakeHost()).start()
print("started", flush=True)
threading.Event().wait()
"""


def producers_of(pid: int) -> list[int]:
    """The SYNC producer processes among ``pid``'s children (what ``ps`` would show)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        try:                                     # a thread or child may end meanwhile
            children = (task / "children").read_text().split()
        except FileNotFoundError:
            continue
        for child in children:
            try:
                cmd = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            except FileNotFoundError:
                continue
            if any(arg.endswith(b"canopen_sync.py") for arg in cmd):
                found.append(int(child))
    return found


def gone(pid: int) -> bool:
    """The process has exited (no longer there, or a zombie nobody reaped yet)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except FileNotFoundError:
        return True
    return state in ("Z", "X")


def sync_listener(channel: str) -> can.BusABC:
    return can.Bus(interface="socketcan", channel=channel,
                   can_filters=[{"can_id": 0x080, "can_mask": 0x7FF}])


def assert_quiet(seen: can.BusABC, what: str) -> None:
    """No SYNC on the wire any more: what was queued before is drained, then none comes."""
    while seen.recv(0) is not None:
        pass
    assert seen.recv(0.3) is None, what


@pytest.mark.socketcan
def test_sync_stops_when_the_controller_is_killed(tmp_path: Path) -> None:
    from vcan_tests import uml

    channel = uml.can_channel("socketcan")
    script = tmp_path / "controller.py"
    script.write_text(textwrap.dedent(CONTROLLER.format(channel=channel, eds=SERVO_EDS)),
                      encoding="utf-8")
    seen = sync_listener(channel)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, env=env,
                            text=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline().strip() == "started"
        for _ in range(10):
            msg = seen.recv(WAIT)
            assert msg is not None, "no SYNC on the wire"
            assert msg.data == b""
        producers = producers_of(proc.pid)
        assert len(producers) == 1, f"SYNC producer processes of the controller: {producers}"
        proc.kill()
        proc.wait(WAIT)
        assert wait_until(lambda: gone(producers[0])), "the producer outlived the controller"
        assert_quiet(seen, "SYNC outlived the controller")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)
        seen.shutdown()


@pytest.mark.socketcan
def test_a_producer_that_dies_is_reported_and_sync_stops(tmp_path: Path) -> None:
    from chcos.devices.spec import BusSpec
    from drivers.canopen_node import CanopenDriver
    from vcan_tests import uml
    from vcan_tests.support_fb import FakeHost

    channel = uml.can_channel("socketcan")
    seen = sync_listener(channel)
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "socketcan", "channel": channel, "sync_period": 0.005,
        "sdo_timeout": 0.05, "nodes": [{"id": 42, "eds": str(SERVO_EDS), "nmt_start": False}]})
    host = FakeHost()
    driver = CanopenDriver(bus, [], host)
    driver.start()
    try:
        for _ in range(10):
            assert seen.recv(WAIT) is not None, "no SYNC on the wire"
        producers = producers_of(os.getpid())
        assert len(producers) == 1, f"SYNC producer processes: {producers}"
        os.kill(producers[0], signal.SIGKILL)
        assert host.wait_for(lambda h: any("SYNC producer process exited" in e[2]
                                           for e in h.errors)), host.errors
        assert_quiet(seen, "SYNC without its producer")
    finally:
        driver.stop()
        seen.shutdown()
    assert producers_of(os.getpid()) == []
