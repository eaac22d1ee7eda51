"""The CANopen node lifecycle against durand (issue 36): boot-time identity check and
configuration download read back from the node, one NMT start per boot, OPERATIONAL confirmed by
the heartbeat, a reboot noticed and the node configured again, a node held in PRE-OPERATIONAL
reported, the error register deciding at boot, the master heartbeat on the wire and gone after
the driver stops. Everything asserted is what durand's object dictionary holds or what an
independent observer saw on the wire."""

from __future__ import annotations

import time
from pathlib import Path

from durand.services.nmt import StateEnum

from drivers.canopen_lifecycle import NmtState, NodeLifecycle
from vcan_tests.peers.durand_node import Stored, mapping_entry, sdo_downloads
from vcan_tests.support_canopen import IDENTITY, NODE, durand_rig
from vcan_tests.support_fb import WAIT, make_device

DEVICES = [
    make_device("pos", "sensor", "co", node=NODE, index=0x6064),
    make_device("target", "actuator", "co", node=NODE, index=0x607A),
    make_device("speed", "actuator", "co", node=NODE, index=0x6081),
]

CONFIG = {
    "heartbeat_producer_ms": 20,
    "master_consumer_ms": 100,
    "error_behaviour": 0,
    "pdos": [
        {"pdo": "rpdo1", "transmission_type": 255, "map": [[0x607A, 0]]},
        {"pdo": "tpdo1", "transmission_type": 255, "map": [[0x6064, 0], [0x6041, 0]]},
    ],
    "sdo": [{"index": 0x6081, "value": 500}],
}
MASTER = {"master_heartbeat_ms": 30}


def test_boot_checks_identity_configures_starts_once_and_confirms(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, identity=IDENTITY,
                    config=CONFIG, bus_opts=MASTER) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        st = r.driver.node_states()[NODE]
        assert st.lifecycle is NodeLifecycle.OPERATIONAL and st.confirmed
        assert st.nmt is NmtState.OPERATIONAL and st.error_register == 0
        # what the node holds: the configuration, read back by the driver as well
        assert r.node.state == StateEnum.OPERATIONAL
        assert r.node.read(0x1017, 0) == 20
        assert r.node.read(0x1016, 1) == (127 << 16) | 100
        assert r.node.read(0x1600, 0) == 1
        assert r.node.read(0x1600, 1) == mapping_entry(0x607A, 0, 32)
        assert r.node.read(0x1A00, 0) == 2
        assert r.node.read(0x1A00, 2) == mapping_entry(0x6041, 0, 16)
        assert r.node.read(0x6081, 0) == 500
        # the configured PDOs carry the devices both ways
        r.node.write(0x6064, 0, -4321)
        assert r.host.wait_for(lambda h: -4321 in h.values("pos"))
        # one reading per TPDO on the wire (the reconfigured TPDO is subscribed once)
        tpdo = 0x180 + NODE
        assert r.wire.wait_for(lambda w: len(w.of(tpdo)) == len(r.host.values("pos")))
        r.driver.write("target", 2500)
        assert r.node.wait(lambda: r.node.read(0x607A, 0) == 2500)
        # heartbeats keep coming; the NMT start went out once
        since = time.monotonic()
        assert r.wire.wait_for(lambda w: len(w.of(0x700 + NODE, since)) >= 5)
        assert r.wire.nmt_starts(NODE) == 1 and st.nmt_starts == 1
        assert r.host.failures == [] and r.host.errors == []


def test_identity_mismatch_names_both_values_and_keeps_the_node_failed(tmp_path: Path) -> None:
    wrong = {**IDENTITY, "product": 0x43}
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, identity=wrong,
                    config={"heartbeat_producer_ms": 20},
                    node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        reason = r.host.failed("target")[0]
        assert "product (0x1018:02) is 0x00000042 on the node, 0x00000043 in the map" in reason
        assert "identity" in r.host.error_kinds()
        st = r.driver.node_states()[NODE]
        assert st.lifecycle is NodeLifecycle.FAILED and not st.ready
        since = time.monotonic()
        assert r.wire.wait_for(lambda w: len(w.of(0x700 + NODE, since)) >= 5)
        # not configured, not started, not recovered by its heartbeats
        assert r.wire.nmt_starts(NODE) == 0 and r.node.state == StateEnum.PRE_OPERATIONAL
        assert sdo_downloads(r.wire.frames, NODE, 0x1017) == []
        assert r.host.recoveries == []


def test_reboot_without_stored_configuration_is_configured_again(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, identity=IDENTITY,
                    config=CONFIG, bus_opts=MASTER) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.driver.write("speed", 999)
        assert r.driver.settle(WAIT) and r.node.read(0x6081, 0) == 999
        booted = time.monotonic()
        r.node.power_cycle()                     # everything configured is lost
        assert r.node.read(0x1017, 0) == 0 and r.node.read(0x1600, 0) == 0
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        assert "rebooted (boot-up message)" in r.host.failed("speed")[0]
        assert "boot-up" in r.host.error_kinds()
        assert r.host.wait_for(lambda h: len(h.recoveries) == len(DEVICES))
        # configured again (read from the node), started once more, confirmed
        assert r.node.read(0x1017, 0) == 20 and r.node.read(0x1600, 1) == mapping_entry(
            0x607A, 0, 32)
        assert r.node.read(0x6081, 0) == 500     # the configuration's value, not the old 999
        assert r.node.state == StateEnum.OPERATIONAL
        st = r.driver.node_states()[NODE]
        assert st.boots == 1 and st.nmt_starts == 2 and st.ready
        assert r.wire.nmt_starts(NODE, since=booted) == 1
        # the configuration went out after the boot-up and before the NMT start
        boot_up = next(f for f in r.wire.of(0x700 + NODE, booted) if f.data == b"\x00")
        start = next(f for f in r.wire.of(0x000, booted))
        hb_writes = [f for f in r.wire.frames if f.at >= boot_up.at
                     and sdo_downloads([f], NODE, 0x1017)]
        assert hb_writes and boot_up.at <= hb_writes[0].at <= start.at
        r.node.write(0x6064, 0, 77)              # the reconfigured TPDO is heard again
        assert r.host.wait_for(lambda h: 77 in h.values("pos"))


def test_a_node_held_in_preoperational_is_reported_and_not_restarted(tmp_path: Path) -> None:
    """durand configured to refuse the NMT start while 0x1001 is set: one start per boot, the
    failure names the error register and the last EMCY."""
    stored = Stored(heartbeat_ms=20, rpdo={1: [(0x607A, 0)]})
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, start=False,
                    eds_defaults={"1600sub0": 1, "1600sub1": mapping_entry(0x607A, 0, 32)},
                    node_kw={"refuse_start_on_error": True, "stored": stored}) as r:
        r.driver.start()
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.node.emcy(0x6100, 0x01)              # software error: not fatal, 0x1001 set
        recovered = len(r.host.recoveries)
        r.node.power_cycle()
        r.node.emcy(0x6100, 0x01)              # again after the boot: it refuses to start
        assert r.host.wait_for(lambda h: "preop-held" in h.error_kinds())
        text = next(d for _, k, d in r.host.errors if k == "preop-held")
        assert "stays PRE-OPERATIONAL after the NMT start" in text
        assert "error register 0x1001 = 0x01" in text and "0x6100" in text
        st = r.driver.node_states()[NODE]
        assert st.lifecycle is NodeLifecycle.PREOP_HELD and not st.ready
        held = time.monotonic()
        assert r.wire.wait_for(lambda w: len(w.of(0x700 + NODE, held)) >= 10)
        assert all(f.data == b"\x7f" for f in r.wire.of(0x700 + NODE, held))
        assert r.wire.nmt_starts(NODE) == 2       # one per boot, not one per heartbeat
        assert r.host.failed("target") and r.host.recoveries[recovered:] == []
        # a command to it goes on the wire, but is not reported done: the node ignores RPDOs
        r.driver.write("target", 5)
        assert r.driver.settle(WAIT)
        assert r.host.writes[-1][:2] == ("target", 5) and "ignores it" in r.host.writes[-1][2]
        assert r.wire.wait_for(lambda w: any(f.data == (5).to_bytes(4, "little")
                                             for f in w.of(0x200 + NODE)))
        assert r.node.read(0x607A, 0) == 0


def test_the_error_register_at_boot_decides_not_the_emcy_chcos_happened_to_see(
        tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3,
                    node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.node.emcy(0x4210, 0x08)                 # temperature: fatal
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        assert "EMCY" in r.host.failed("pos")[0]
        r.node.power_cycle()                      # boots clean: 0x1001 reads 0
        assert r.host.wait_for(lambda h: h.recoveries.count("pos") == 1
                               and r.driver.node_states()[NODE].ready)
        assert r.driver.node_states()[NODE].error_register == 0
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, start=False,
                    node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        r.node.write(0x1001, 0, 0x08)             # in error before chcos ever ran
        r.driver.start()
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        assert "error register 0x1001 = 0x08 at boot" in r.host.failed("pos")[0]


def test_master_heartbeat_is_on_the_wire_and_stops_with_the_driver(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, node_kw={"stored": Stored(heartbeat_ms=20)},
                    bus_opts={"master_heartbeat_ms": 20, "master_node_id": 100}) as r:
        assert r.wire.wait_for(lambda w: len(w.of(0x700 + 100)) >= 5)
        assert {f.data for f in r.wire.of(0x700 + 100)} == {b"\x05"}   # OPERATIONAL
        assert "unknown-node" not in r.host.error_kinds()
        r.driver.stop()
        stopped = time.monotonic()
        # the node's own heartbeats go on: the wire was watched long enough
        assert r.wire.wait_for(lambda w: len(w.of(0x700 + NODE, stopped)) >= 10)
        assert r.wire.of(0x700 + 100, stopped) == []


def test_an_sdo_abort_during_configuration_names_the_object_and_the_code(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, start=False,
                    config={"heartbeat_producer_ms": 20,
                            "sdo": [{"index": 0x6081, "value": 500}]}) as r:
        r.node.abort_writes(0x6081)
        r.driver.start()
        assert r.host.wait_for(lambda h: "config" in h.error_kinds())
        text = next(d for _, k, d in r.host.errors if k == "config")
        assert "0x6081:00 (sdo write) = 500 aborted" in text
        assert "Code 0x08000020" in text
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        assert r.driver.node_states()[NODE].lifecycle is NodeLifecycle.FAILED
        assert r.wire.nmt_starts(NODE) == 0


def test_an_absent_node_waits_for_its_boot_up_and_is_brought_up_then(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, start=False,
                    config={"heartbeat_producer_ms": 20}) as r:
        r.node.power_off()
        r.driver.start()
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        assert "no SDO answer" in r.host.failed("pos")[0]
        assert r.driver.node_states()[NODE].lifecycle is NodeLifecycle.WAITING_BOOT
        r.node.power_on()
        assert r.host.wait_for(lambda h: len(h.recoveries) == len(DEVICES))
        assert r.node.read(0x1017, 0) == 20 and r.node.state == StateEnum.OPERATIONAL


SYSTEM_MAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2

[[bus.nodes]]
id = {node}
eds = "{eds}"
heartbeat_timeout = 0.3
[bus.nodes.config]
heartbeat_producer_ms = 20
pdos = [{{ pdo = "rpdo1", transmission_type = 255, map = [[0x607A, 0]] }}]

[[device]]
name = "target"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x607A }}
limits = [-100000, 100000]
safe_value = 11

[[device]]
name = "speed"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x6081 }}
limits = [0, 100000]
safe_value = 7
"""


def test_a_rebooted_node_gets_its_configuration_then_the_safe_values(tmp_path: Path) -> None:
    """With the device table: a node that reboots without its stored configuration is
    configured again, started, and the first commands it gets are the safe values (not the
    values commanded before the reboot), on the wire after its configuration and its start."""
    from chcos.kernel.clock import VirtualClock
    from chcos.system.embedded import System
    from vcan_tests.netutil import unique_channel
    from vcan_tests.peers.durand_node import DurandNode, Wire
    from vcan_tests.support_faults import run_until

    channel = unique_channel("sys")
    node = DurandNode(channel, NODE)
    eds = node.write_eds(tmp_path / "node.eds")
    wire = Wire(channel)
    path = tmp_path / "co.toml"
    path.write_text(SYSTEM_MAP.format(channel=channel, node=NODE, eds=eds), encoding="utf-8")
    s = System([path], clock=VirtualClock(), machines=[0])
    try:
        drv = next(d for d in s.devtab.drivers if d.bus.name == "co")
        states = drv.node_states  # type: ignore[attr-defined]
        assert run_until(s, lambda: states()[NODE].ready)
        s.devtab.write("target", 999)
        s.devtab.write("speed", 999)
        assert run_until(s, lambda: node.read(0x607A, 0) == 999 and node.read(0x6081, 0) == 999)
        booted = time.monotonic()
        node.power_cycle()
        assert node.read(0x607A, 0) == 0 and node.read(0x1017, 0) == 0
        assert run_until(s, lambda: s.devtab.get("target").status.value == "failed")
        assert "rebooted" in s.devtab.get("target").reason
        assert run_until(s, lambda: s.devtab.get("target").status.value == "OK"
                         and s.devtab.get("speed").status.value == "OK"
                         and node.read(0x607A, 0) == 11 and node.read(0x6081, 0) == 7)
        assert node.read(0x1017, 0) == 20 and node.state == StateEnum.OPERATIONAL
        # what the wire carried after the node's boot-up message, in the order it carried it
        # (not by time stamp: a frame sent just before the reboot may be stamped after it)
        seen = list(wire.frames)
        boot = min(i for i, f in enumerate(seen)
                   if f.cob_id == 0x700 + NODE and f.data == b"\x00" and f.at >= booted)
        frames = seen[boot + 1:]
        rpdos = [f for f in frames if f.cob_id == 0x200 + NODE]
        speeds = sdo_downloads(frames, NODE, 0x6081)
        assert rpdos[0].data == (11).to_bytes(4, "little") and speeds[:1] == [7]
        start = next(f for f in frames if f.cob_id == 0 and f.data == bytes((1, NODE)))
        configured = next(f for f in frames if sdo_downloads([f], NODE, 0x1017))
        assert configured.at <= start.at <= rpdos[0].at
    finally:
        s.shutdown()
        wire.close()
        node.close()


def test_a_node_heard_without_a_boot_up_is_brought_up(tmp_path: Path) -> None:
    """Absent at start, then heartbeating without a boot-up anyone saw (connected late): its
    heartbeat starts the boot procedure again."""
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3, start=False,
                    node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        r.node.power_off()
        r.driver.start()
        assert r.host.wait_for(lambda h: len(h.failures) == len(DEVICES))
        since = time.monotonic()
        r.node.power_on(announce=False)
        assert r.host.wait_for(lambda h: len(h.recoveries) == len(DEVICES))
        assert r.node.state == StateEnum.OPERATIONAL
        assert [f for f in r.wire.of(0x700 + NODE, since) if f.data == b"\x00"] == []
        st = r.driver.node_states()[NODE]
        assert st.boots == 0 and st.nmt_starts == 1 and st.ready
