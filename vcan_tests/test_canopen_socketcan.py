"""The master heartbeat on real SocketCAN (runs inside the User-Mode-Linux guest): it is a
cyclic job of the kernel's broadcast manager, so when the controller process is killed
(SIGKILL: no shutdown code runs) the kernel closes its socket and the heartbeat stops; a drive
watching it with 0x1016 then reacts (docs/canopen.md)."""

from __future__ import annotations

from pathlib import Path

import can
import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from vcan_tests.support_controller import assert_quiet, controller
from vcan_tests.support_fb import WAIT

MASTER = 100

CONTROLLER = """
import sys, threading
from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.support_fb import FakeHost

bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={{
    "interface": "socketcan", "channel": "{channel}", "master_heartbeat_ms": 10,
    "master_node_id": {master}, "sdo_timeout": 0.05,
    "nodes": [{{"id": 42, "eds": "{eds}", "nmt_start": False}}]}})
CanopenDriver(bus, [], FakeHost()).start()
print("started", flush=True)
threading.Event().wait()
"""


@pytest.mark.socketcan
def test_master_heartbeat_stops_when_the_controller_is_killed(tmp_path: Path) -> None:
    from vcan_tests import uml

    channel = uml.can_channel("socketcan")
    seen = can.Bus(interface="socketcan", channel=channel,
                   can_filters=[{"can_id": 0x700 + MASTER, "can_mask": 0x7FF}])
    try:
        with controller(CONTROLLER.format(channel=channel, master=MASTER, eds=SERVO_EDS),
                        tmp_path) as proc:
            for _ in range(5):
                msg = seen.recv(WAIT)
                assert msg is not None, "no master heartbeat on the wire"
                assert msg.data == b"\x05"
            proc.kill()
            proc.wait(WAIT)
            assert_quiet(seen, "the heartbeat outlived the controller")
    finally:
        seen.shutdown()


@pytest.mark.socketcan
def test_the_producer_sends_sync_and_the_driver_counts_what_went_out(tmp_path: Path) -> None:
    """On SocketCAN the SYNC producer is a process of the driver's own; the driver counts the
    cycles and the jitter from the SYNCs its reader sees on the wire (kernel time stamps)."""
    from chcos.devices.spec import BusSpec
    from drivers.canopen_node import CanopenDriver
    from vcan_tests import uml
    from vcan_tests.support_fb import FakeHost

    channel = uml.can_channel("socketcan")
    seen = can.Bus(interface="socketcan", channel=channel,
                   can_filters=[{"can_id": 0x080, "can_mask": 0x7FF}])
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "socketcan", "channel": channel, "sync_period": 0.01, "sdo_timeout": 0.05,
        "nodes": [{"id": 42, "eds": str(SERVO_EDS), "nmt_start": False}]})
    host = FakeHost()
    driver = CanopenDriver(bus, [], host)
    driver.start()
    try:
        for _ in range(10):
            assert seen.recv(WAIT) is not None, "no SYNC on the wire"
        driver.wait_cycle(10, WAIT)
        stats = driver.sync_stats()
        assert stats is not None and stats.cycles >= 10
        assert 0 <= stats.jitter_p50 <= stats.jitter_p99 <= stats.jitter_max < 1.0
    finally:
        driver.stop()
        seen.shutdown()


@pytest.mark.socketcan
def test_the_sync_producer_stops_with_the_driver(tmp_path: Path) -> None:
    """The SYNC producer process (drivers.canopen_sync.SyncProducerProcess) catches up after
    late SYNCs; once the driver stopped, no SYNC is on the wire, on a fast period where late
    SYNCs are common in the guest."""
    from chcos.devices.spec import BusSpec
    from drivers.canopen_node import CanopenDriver
    from vcan_tests import uml
    from vcan_tests.support_fb import FakeHost

    channel = uml.can_channel("socketcan")
    seen = can.Bus(interface="socketcan", channel=channel,
                   can_filters=[{"can_id": 0x080, "can_mask": 0x7FF}])
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "socketcan", "channel": channel, "sync_period": 0.002,
        "sdo_timeout": 0.05, "nodes": [{"id": 42, "eds": str(SERVO_EDS), "nmt_start": False}]})
    driver = CanopenDriver(bus, [], FakeHost())
    driver.start()
    try:
        for _ in range(200):
            assert seen.recv(WAIT) is not None, "no SYNC on the wire"
        stats = driver.sync_stats()
        assert stats is not None and stats.cycles >= 1
    finally:
        driver.stop()
    try:
        while seen.recv(0) is not None:          # what was on the wire before the stop
            pass
        assert seen.recv(0.3) is None, "SYNC outlived the driver"
    finally:
        seen.shutdown()
