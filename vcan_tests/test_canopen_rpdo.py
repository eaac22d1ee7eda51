"""RPDO images, no latch after a failed write, heartbeat supervision beside blocking SDO
transfers and the kernel filters, against durand (issues 36 and 38): what the node's object
dictionary holds and what the wire carried."""

from __future__ import annotations

import time
from pathlib import Path

import can

from chcos.devices.spec import BusSpec
from drivers.canopen_node import CanopenDriver
from vcan_tests.peers.durand_node import DurandNode, Stored, Wire, mapping_entry
from vcan_tests.support_canopen import NODE, durand_rig
from vcan_tests.support_fb import WAIT, FakeHost, make_device

#: a CiA 402 drive's usual default mapping: the controlword in RPDO1 and, with the modes of
#: operation, in RPDO2
DRIVE_RPDOS = {1: [(0x6040, 0)], 2: [(0x6040, 0), (0x6060, 0)]}
DRIVE_EDS = {"1600sub0": 1, "1600sub1": mapping_entry(0x6040, 0, 16),
             "1601sub0": 2, "1601sub1": mapping_entry(0x6040, 0, 16),
             "1601sub2": mapping_entry(0x6060, 0, 8)}
RPDO2 = 0x300 + NODE


def test_an_object_in_two_rpdos_is_never_sent_stale(tmp_path: Path) -> None:
    devices = [make_device("control_word", "actuator", "co", node=NODE, index=0x6040),
               make_device("mode", "actuator", "co", node=NODE, index=0x6060)]
    with durand_rig(tmp_path, devices, heartbeat_timeout=0.3, eds_defaults=DRIVE_EDS,
                    node_kw={"stored": Stored(heartbeat_ms=20, rpdo=DRIVE_RPDOS)}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.driver.write("control_word", 0x0F)          # RPDO1
        assert r.node.wait(lambda: r.node.read(0x6040, 0) == 0x0F)
        r.driver.write("mode", 1)                     # RPDO2 carries the controlword too
        assert r.node.wait(lambda: r.node.read(0x6060, 0) == 1)
        assert r.node.read(0x6040, 0) == 0x0F
        assert r.wire.of(RPDO2)[-1].data == bytes([0x0F, 0x00, 0x01])
        r.driver.write("control_word", 2)             # quick stop (a safe value)
        r.driver.write("mode", 3)
        assert r.node.wait(lambda: r.node.read(0x6060, 0) == 3)
        assert r.node.read(0x6040, 0) == 2
        assert [f.data for f in r.wire.of(RPDO2)] == [bytes([0x0F, 0, 1]), bytes([2, 0, 3])]


def test_rpdo_images_start_from_the_nodes_values(tmp_path: Path) -> None:
    """Objects nobody wrote yet go out with the value the node holds (read at boot), not 0."""
    devices = [make_device("mode", "actuator", "co", node=NODE, index=0x6060)]
    with durand_rig(tmp_path, devices, heartbeat_timeout=0.3, eds_defaults=DRIVE_EDS,
                    start=False,
                    node_kw={"stored": Stored(heartbeat_ms=20, rpdo=DRIVE_RPDOS)}) as r:
        r.node.write(0x6040, 0, 0x06)                 # "shutdown", set by the drive's panel
        r.driver.start()
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.driver.write("mode", 1)
        assert r.node.wait(lambda: r.node.read(0x6060, 0) == 1)
        assert r.node.read(0x6040, 0) == 0x06


def test_a_failed_sdo_write_does_not_latch(tmp_path: Path) -> None:
    devices = [make_device("speed", "actuator", "co", node=NODE, index=0x6081)]
    with durand_rig(tmp_path, devices, node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.node.abort_writes(0x6081)
        r.driver.write("speed", 5)
        assert r.driver.settle(WAIT)
        assert r.host.writes[-1][0:2] == ("speed", 5) and "Code 0x08000020" in r.host.writes[-1][2]
        reason = r.host.failed("speed")[0]
        assert "0x6081:00" in reason and "aborted" in reason
        r.node.accept_writes(0x6081)
        r.host.tick(0.1)                              # the probe the driver armed itself
        assert r.driver.settle(WAIT)
        assert r.host.recoveries == ["speed"]
        r.driver.write("speed", 9)                    # the command after the recovery
        assert r.driver.settle(WAIT)
        assert r.node.read(0x6081, 0) == 9 and r.host.writes[-1] == ("speed", 9, "")


def test_a_silent_node_is_probed_until_it_answers(tmp_path: Path) -> None:
    devices = [make_device("speed", "actuator", "co", node=NODE, index=0x6081)]
    with durand_rig(tmp_path, devices, node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.node.power_off()
        r.driver.write("speed", 5)
        assert r.driver.settle(WAIT)
        assert "No SDO response" in r.host.failed("speed")[0]
        for _ in range(3):                            # probes while it is away
            r.host.tick(0.1)
            assert r.driver.settle(WAIT)
        assert r.host.recoveries == []
        r.node.power_on()                             # its boot-up: it is brought up again
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.host.tick(0.1)
        assert r.driver.settle(WAIT)
        assert r.host.wait_for(lambda h: h.recoveries[-1:] == ["speed"])
        r.driver.write("speed", 9)
        assert r.driver.settle(WAIT)
        assert r.node.read(0x6081, 0) == 9


def test_heartbeat_loss_is_seen_while_sdo_transfers_block_the_io_thread(tmp_path: Path) -> None:
    """Node 6 is absent: one poll of its 20 objects blocks the I/O thread for 20 SDO timeouts
    (at least 4 s). Node 5 dies meanwhile: its loss is reported while that poll still runs."""
    channel = "hb-" + tmp_path.name
    node = DurandNode(channel, NODE, stored=Stored(heartbeat_ms=20))
    eds = node.write_eds(tmp_path / "node.eds")
    devices = [make_device("pos", "sensor", "co", node=NODE, index=0x6064)]
    devices += [make_device(f"far{i}", "sensor", "co", node=6, index=0x6064, poll_period=0.1)
                for i in range(20)]
    bus = BusSpec(name="co", kind="canopen", key="bus[0]", options={
        "interface": "virtual", "channel": channel, "sdo_timeout": 0.2, "poll_period": 5.0,
        "nodes": [{"id": NODE, "eds": str(eds), "heartbeat_timeout": 0.3},
                  {"id": 6, "eds": str(eds), "nmt_start": False}]})
    host = FakeHost()
    driver = CanopenDriver(bus, devices, host)
    driver.start()
    try:
        assert node.wait(lambda: driver.node_states()[NODE].ready)
        assert driver.settle(WAIT)                    # node 6's boot procedure gave up
        host.tick(0.1)                                # the far poll: 20 SDO timeouts in a row
        node.power_off()
        assert host.wait_for(lambda h: any("no heartbeat" in r for r in h.failed("pos")))
        assert not driver.settle(0.0), "the blocking poll should still be running"
    finally:
        driver.stop()
        node.close()


def test_frames_of_other_ids_do_not_reach_the_driver(tmp_path: Path) -> None:
    devices = [make_device("pos", "sensor", "co", node=NODE, index=0x6064)]
    with durand_rig(tmp_path, devices, node_kw={"stored": Stored(tpdo={1: [(0x6064, 0)]})},
                    eds_defaults={"1A00sub0": 1, "1A00sub1": mapping_entry(0x6064, 0, 32)}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        assert r.driver.settle(WAIT)
        base = r.host.stats.get("frames", 0)
        with can.Bus(interface="virtual", channel=r.channel) as other:
            for i in range(50):                       # raw CAN sharing the wire
                other.send(can.Message(arbitration_id=0x123 + (i % 3), data=b"\x01\x02",
                                       is_extended_id=False))
        r.node.write(0x6064, 0, 42)                   # one TPDO, behind them on the wire
        assert r.host.wait_for(lambda h: 42 in h.values("pos"))
        assert r.driver.settle(WAIT)
        assert r.host.stats.get("frames", 0) - base == 1
        assert r.host.errors == []


def test_wire_sees_what_the_test_expects() -> None:
    """The observer itself: it sees a frame another bus sends (the assertions above rely on it)."""
    wire = Wire("wire-self-check")
    try:
        with can.Bus(interface="virtual", channel="wire-self-check") as bus:
            t0 = time.monotonic()
            bus.send(can.Message(arbitration_id=0x77, data=b"\x01", is_extended_id=False))
            assert wire.wait_for(lambda w: len(w.of(0x77, t0)) == 1)
    finally:
        wire.close()
