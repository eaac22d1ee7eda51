"""The SYNC producer process on real SocketCAN (runs inside the User-Mode-Linux guest): the
driver starts a process of its own that sends SYNC (drivers.canopen_sync.SyncProducerProcess);
SYNC is on the wire while the driver runs, and stops when the driver stops, when the controller
process is killed (SIGKILL: no shutdown code runs) and, reported, when the producer itself dies.
Asserted on the wire, through a socket of the test's own. The producer runs SCHED_FIFO at the
bus's ``sync_priority`` where the process may set it (as the kernel reports the producer's
policy), else SCHED_OTHER, reported once with the reason (a controller without CAP_SYS_NICE)."""

from __future__ import annotations

import os
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import can
import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from drivers.canopen_node import CanopenDriver
from drivers.canopen_sync import producer_processes
from vcan_tests.support_controller import ROOT, assert_quiet, controller
from vcan_tests.support_faults import wait_until
from vcan_tests.support_fb import WAIT, FakeHost

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

#: a controller that says "started" once its SYNC producer reported a refused priority, runs
#: until its stdin ends, then prints its bus errors, one a line
REPORTING = """
import sys
from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.support_fb import FakeHost

bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={{
    "interface": "socketcan", "channel": "{channel}", "sync_period": 0.005,
    "sync_priority": {priority}, "sdo_timeout": 0.05,
    "nodes": [{{"id": 42, "eds": "{eds}", "nmt_start": False}}]}})
host = FakeHost()
driver = CanopenDriver(bus, [], host)
driver.start()
host.wait_for(lambda h: any("real-time" in e[2] for e in h.errors), {wait})
print("started", flush=True)
sys.stdin.read()
driver.stop()
for e in host.errors:
    print("error", e[2], flush=True)
"""


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


@pytest.mark.socketcan
def test_sync_stops_when_the_controller_is_killed(tmp_path: Path) -> None:
    from vcan_tests import uml

    channel = uml.can_channel("socketcan")
    seen = sync_listener(channel)
    try:
        with controller(CONTROLLER.format(channel=channel, eds=SERVO_EDS), tmp_path) as proc:
            for _ in range(10):
                msg = seen.recv(WAIT)
                assert msg is not None, "no SYNC on the wire"
                assert msg.data == b""
            producers = producer_processes(proc.pid)
            assert len(producers) == 1, f"SYNC producer processes of the controller: {producers}"
            proc.kill()
            proc.wait(WAIT)
            assert wait_until(lambda: gone(producers[0])), "the producer outlived the controller"
            assert_quiet(seen, "SYNC outlived the controller")
    finally:
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
        producers = producer_processes(os.getpid())
        assert len(producers) == 1, f"SYNC producer processes: {producers}"
        os.kill(producers[0], signal.SIGKILL)
        assert host.wait_for(lambda h: any("SYNC producer process exited" in e[2]
                                           for e in h.errors)), host.errors
        assert_quiet(seen, "SYNC without its producer")
    finally:
        driver.stop()
        seen.shutdown()
    assert producer_processes(os.getpid()) == []


def real_time_allowed(priority: int) -> bool:
    """Whether a process started as this one is may make itself SCHED_FIFO at ``priority``
    (root, CAP_SYS_NICE or RLIMIT_RTPRIO), asked of the kernel in a child of its own."""
    probe = ("import os; os.sched_setscheduler(0, os.SCHED_FIFO, "
             f"os.sched_param({priority}))")
    return subprocess.run([sys.executable, "-c", probe], capture_output=True,
                          timeout=WAIT, check=False).returncode == 0


def run_driver(channel: str, priority: int) -> tuple[FakeHost, CanopenDriver]:
    """A driver on ``channel`` producing SYNC with ``sync_priority`` = ``priority``, started."""
    from chcos.devices.spec import BusSpec

    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "socketcan", "channel": channel, "sync_period": 0.005,
        "sync_priority": priority, "sdo_timeout": 0.05,
        "nodes": [{"id": 42, "eds": str(SERVO_EDS), "nmt_start": False}]})
    host = FakeHost()
    driver = CanopenDriver(bus, [], host)
    driver.start()
    return host, driver


@pytest.mark.socketcan
@pytest.mark.parametrize("priority", [42, 0])
def test_the_producer_runs_sched_fifo_at_sync_priority_when_allowed(priority: int) -> None:
    from vcan_tests import uml

    channel = uml.can_channel("socketcan")
    allowed = real_time_allowed(42)
    seen = sync_listener(channel)
    host, driver = run_driver(channel, priority)
    try:
        for _ in range(10):
            assert seen.recv(WAIT) is not None, "no SYNC on the wire"
        producers = producer_processes(os.getpid())
        assert len(producers) == 1, f"SYNC producer processes: {producers}"
        policy = os.sched_getscheduler(producers[0])
        prio = os.sched_getparam(producers[0]).sched_priority
        reports = [e[2] for e in host.errors if "real-time" in e[2]]
        if priority and allowed:
            assert (policy, prio) == (os.SCHED_FIFO, priority)
            assert reports == []
        elif priority:                           # not allowed here: reported, not real-time
            assert (policy, prio) == (os.SCHED_OTHER, 0)
            assert host.wait_for(lambda h: any("real-time" in e[2] for e in h.errors))
        else:                                    # 0: not asked for, nothing to report
            assert (policy, prio) == (os.SCHED_OTHER, 0)
            assert reports == []
    finally:
        driver.stop()
        seen.shutdown()


@pytest.mark.socketcan
def test_a_controller_without_cap_sys_nice_reports_sync_without_real_time_once(
        tmp_path: Path) -> None:
    from vcan_tests import uml

    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("needs setpriv (util-linux) to drop CAP_SYS_NICE")
    channel = uml.can_channel("socketcan")
    script = tmp_path / "controller.py"
    script.write_text(textwrap.dedent(REPORTING.format(channel=channel, eds=SERVO_EDS,
                                                       priority=42, wait=WAIT)),
                      encoding="utf-8")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}

    def no_rtprio() -> None:
        resource.setrlimit(resource.RLIMIT_RTPRIO, (0, 0))

    # without CAP_SYS_NICE (root included) and with RLIMIT_RTPRIO 0, as an ordinary user
    proc = subprocess.Popen([setpriv, "--inh-caps=-sys_nice", "--bounding-set=-sys_nice",
                             sys.executable, str(script)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, env=env, text=True, preexec_fn=no_rtprio)
    try:
        assert proc.stdout is not None and proc.stdin is not None
        assert proc.stdout.readline().strip() == "started"
        producers = producer_processes(proc.pid)
        assert len(producers) == 1, f"SYNC producer processes of the controller: {producers}"
        assert os.sched_getscheduler(producers[0]) == os.SCHED_OTHER
        proc.stdin.close()
        out = proc.stdout.read()
        assert proc.wait(WAIT) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(WAIT)
    reports = [line for line in out.splitlines() if "real-time" in line]
    assert len(reports) == 1, out
    assert "SCHED_FIFO priority 42 refused" in reports[0]
    assert "CAP_SYS_NICE" in reports[0] and "sync_priority = 0" in reports[0]
