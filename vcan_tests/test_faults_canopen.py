"""Faults at the CANopen boundary, against canopen's own LocalNode on python-can's virtual bus (no
chcos simulator in between): heartbeat lost and back, fatal EMCY and its reset, safe values at
shutdown. Each test asserts what the node holds and the frames it saw (issue 15, items 1, 4, 5)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from tools.peers import CANOPEN_MAP as MAP
from tools.peers import NODE, SPEED
from tools.peers import CanopenPeer as Peer
from vcan_tests.netutil import unique_channel
from vcan_tests.support_faults import run_until


@pytest.fixture
def rig(tmp_path: Path) -> Iterator[tuple[System, Peer]]:
    channel = unique_channel("faults")
    peer = Peer(channel)
    path = tmp_path / "co.toml"
    path.write_text(MAP.format(channel=channel, node=NODE, eds=SERVO_EDS), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    try:
        yield s, peer
    finally:
        s.shutdown()
        peer.close()


def status(s: System, name: str) -> str:
    return s.devtab.get(name).status.value


def test_heartbeat_lost_is_not_cleared_by_readings_and_recovery_writes_safe_values(
        rig: tuple[System, Peer]) -> None:
    s, peer = rig
    s.devtab.write("speed", 5000)
    s.devtab.write("target", 1234)
    assert run_until(s, lambda: s.devtab.get("temp").readings > 0)
    assert peer.value(SPEED) == 5000 and peer.rpdo_values()[-1:] == [1234]
    peer.silence()
    assert run_until(s, lambda: status(s, "temp") == "failed")
    assert "heartbeat" in s.devtab.get("temp").reason
    before = s.devtab.get("temp").dropped
    # the node still answers SDO: readings arrive, the failure the driver reported stays (and
    # a failed sensor delivers nothing until it ends: they are dropped, issue 48)
    assert run_until(s, lambda: s.devtab.get("temp").dropped >= before + 3)
    assert status(s, "temp") == "failed" and status(s, "speed") == "failed"
    back = time.monotonic()
    peer.beat()
    assert run_until(s, lambda: status(s, "speed") == "OK" and status(s, "target") == "OK")
    s.run_for(0.05)
    assert peer.sdo_writes(SPEED, since=back)[:1] == [0] and peer.value(SPEED) == 0
    assert peer.rpdo_values(since=back)[:1] == [0]
    assert status(s, "temp") == "OK"


def test_fatal_emcy_holds_until_the_error_reset(rig: tuple[System, Peer]) -> None:
    s, peer = rig
    health: list[tuple[str, bool, str]] = []
    s.devtab.add_health_listener(lambda d, ok, c: health.append((d, ok, c)))
    s.devtab.write("speed", 5000)
    assert run_until(s, lambda: s.devtab.get("temp").readings > 0)
    peer.node.emcy.send(0x3210, 0x04)                  # DC link over-voltage: fatal
    assert run_until(s, lambda: status(s, "temp") == "failed")
    assert "EMCY" in s.devtab.get("temp").reason and s.devtab.get("temp").since is not None
    before = s.devtab.get("temp").dropped              # answers, dropped while failed
    assert run_until(s, lambda: s.devtab.get("temp").dropped >= before + 3)
    assert status(s, "temp") == "failed"                 # an SDO answer is not the reset
    assert s.devtab.bus_stats["co"].errors["emcy"] == 1
    reset = time.monotonic()
    peer.node.emcy.send(0x0000, 0x00)                  # error reset
    assert run_until(s, lambda: status(s, "temp") == "OK" and status(s, "speed") == "OK")
    s.run_for(0.05)
    assert peer.sdo_writes(SPEED, since=reset)[:1] == [0] and peer.value(SPEED) == 0
    assert ("temp", True, f"canopen node {NODE}: error-reset EMCY") in health


def test_shutdown_puts_queued_writes_and_safe_values_on_the_wire(
        rig: tuple[System, Peer]) -> None:
    s, peer = rig
    assert run_until(s, lambda: s.devtab.get("temp").readings > 0)
    t0 = time.monotonic()
    s.devtab.write("speed", 7)
    s.devtab.write("target", 7)
    undelivered = s.devtab.stop_drivers()              # at once: the 7s are still queued
    assert undelivered == []
    assert peer.sdo_writes(SPEED, since=t0) == [7, 0] and peer.value(SPEED) == 0
    assert peer.rpdo_values(since=t0) == [7, 0]


def test_driver_stop_runs_the_writes_queued_before_it(tmp_path: Path) -> None:
    from chcos.devices.devmap import load
    from drivers.canopen_node import CanopenDriver
    from vcan_tests.support_fb import FakeHost

    channel = unique_channel("faults")
    peer = Peer(channel)
    path = tmp_path / "co.toml"
    path.write_text(MAP.format(channel=channel, node=NODE, eds=SERVO_EDS), encoding="utf-8")
    dm = load([path])
    host = FakeHost()
    drv = CanopenDriver(dm.buses[0], dm.devices, host)
    try:
        drv.start()
        t0 = time.monotonic()
        for v in (7, 8, 9, 0):                  # SDO downloads: each waits for its answer
            drv.write("speed", v)
        drv.stop()                              # no settle first: stop itself must flush
        assert peer.sdo_writes(SPEED, since=t0) == [7, 8, 9, 0] and peer.value(SPEED) == 0
        assert [(d, v, r) for d, v, r in host.writes] == [("speed", v, "") for v in (7, 8, 9, 0)]
    finally:
        drv.stop()
        peer.close()
