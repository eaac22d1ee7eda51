"""Faults at the CANopen boundary, against canopen's own LocalNode on python-can's virtual bus (no
chcos simulator in between): heartbeat lost and back, fatal EMCY and its reset, safe values at
shutdown. Each test asserts what the node holds and the frames it saw (issue 15, items 1, 4, 5)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import canopen
import pytest

from chcos.apps.sim.canopen_slave import SERVO_EDS
from chcos.kernel.clock import VirtualClock
from chcos.system.embedded import System
from vcan_tests.netutil import unique_channel
from vcan_tests.support_faults import run_until

NODE = 5
SPEED, TARGET, TEMP = 0x6081, 0x607A, 0x2000
MAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
nodes = [{{ id = {node}, eds = "{eds}", heartbeat_timeout = 0.15, nmt_start = false }}]

[[device]]
name = "speed"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x6081 }}
limits = [0, 100000]
safe_value = 0

[[device]]
name = "target"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x607A }}
limits = [-100000, 100000]
safe_value = 0

[[device]]
name = "temp"
direction = "sensor"
bus = "co"
address = {{ node = {node}, index = 0x2000, poll_period = 0.1 }}
"""


class Candump(can.Listener):
    """Every frame the peer's bus received, with time.monotonic() stamps."""

    def __init__(self) -> None:
        self.frames: list[tuple[float, int, bytes]] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))


class Peer:
    """canopen.LocalNode ``NODE`` with the servo EDS, heartbeat producer, EMCY producer."""

    def __init__(self, channel: str) -> None:
        self.od: Any = canopen.import_od(str(SERVO_EDS), NODE)
        self.net: Any = canopen.Network()
        self.net.NOTIFIER_CYCLE = 0.05
        self.net.connect(interface="virtual", channel=channel)
        self.node: Any = canopen.LocalNode(NODE, self.od)
        self.net.add_node(self.node)
        self.dump = Candump()
        notifier: Any = self.net.notifier
        notifier.add_listener(self.dump)
        self.node.nmt.state = "OPERATIONAL"
        self.beat()

    def beat(self) -> None:
        self.node.nmt.start_heartbeat(20)

    def silence(self) -> None:
        self.node.nmt.stop_heartbeat()

    def value(self, index: int) -> int:
        """The node's own object ``index``:0 (SDO downloads land here)."""
        return int(self.od[index].decode_raw(self.node.get_data(index, 0)))

    def sdo_writes(self, index: int, since: float = 0.0) -> list[int]:
        """Values of expedited SDO downloads to ``index``:0 the node received since ``since``."""
        out = []
        for at, cob, data in self.dump.frames:
            if (at >= since and cob == 0x600 + NODE and data[0] & 0xE0 == 0x20
                    and int.from_bytes(data[1:3], "little") == index and data[3] == 0):
                n = 4 - ((data[0] >> 2) & 3) if data[0] & 1 else 4
                out.append(int.from_bytes(data[4:4 + n], "little", signed=True))
        return out

    def rpdo_values(self, since: float = 0.0) -> list[int]:
        """Target positions in RPDO1 frames the node received since ``since``."""
        return [int.from_bytes(d[:4], "little", signed=True) for at, cob, d in self.dump.frames
                if at >= since and cob == 0x200 + NODE]

    def close(self) -> None:
        self.silence()
        self.net.disconnect()


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
    before = s.devtab.get("temp").readings
    # the node still answers SDO: readings arrive, the failure the driver reported stays
    assert run_until(s, lambda: s.devtab.get("temp").readings >= before + 3)
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
    before = s.devtab.get("temp").readings
    assert run_until(s, lambda: s.devtab.get("temp").readings >= before + 3)
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
