"""The SYNC cycle against durand: synchronous TPDOs (transmission type 1) collected per cycle,
missing ones counted when the node is gone, the counters in the bus statistics, waiting for a
cycle, and the check that refuses a synchronous TPDO on a bus without SYNC."""

from __future__ import annotations

from pathlib import Path

from vcan_tests.support_canopen import NODE, durand_rig
from vcan_tests.support_fb import WAIT, make_device

SYNC_TPDO = {"pdos": [{"pdo": "tpdo1", "transmission_type": 1, "map": [[0x6064, 0]]}],
             "heartbeat_producer_ms": 20}


def test_synchronous_tpdos_are_collected_per_cycle(tmp_path: Path) -> None:
    devices = [make_device("pos", "sensor", "co", node=NODE, index=0x6064)]
    with durand_rig(tmp_path, devices, heartbeat_timeout=0.3, config=SYNC_TPDO,
                    bus_opts={"sync_period": 0.01}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        r.node.write(0x6064, 0, 321)                 # sent at the next SYNC, not at once
        assert r.host.wait_for(lambda h: 321 in h.values("pos"))
        # the node answers every SYNC: a cycle after now completes
        stats = r.driver.sync_stats()
        assert stats is not None
        n = stats.cycles + 2
        assert any(r.driver.wait_cycle(m, WAIT) for m in range(n, n + 20))
        syncs = r.wire.of(0x080)                    # SYNC without a counter
        assert len(r.wire.of(0x180 + NODE, syncs[0].at)) >= 2
        assert len(syncs) >= 3 and all(f.data == b"" for f in syncs)
        stats = r.driver.sync_stats()
        assert stats is not None and stats.complete >= 1 and stats.period == 0.01
        assert 0 <= stats.jitter_p50 <= stats.jitter_p99 <= stats.jitter_max
        # the node is gone: its TPDO goes missing, cycle after cycle
        before = stats.missing
        r.node.power_off()
        assert r.node.wait(lambda: (s := r.driver.sync_stats()) is not None
                           and s.missing >= before + 5)
        assert not r.driver.wait_cycle(r.driver.sync_stats().cycles, WAIT)  # type: ignore[union-attr]
        assert r.driver.settle(WAIT)
        assert r.host.stats.get("sync-cycles", 0) >= 5 and r.host.stats.get("sync-missing", 0) >= 5


def test_a_synchronous_tpdo_needs_sync_on_the_bus(tmp_path: Path) -> None:
    from drivers.canopen_node import CanopenDriver
    from vcan_tests.support_canopen import canopen_bus

    with durand_rig(tmp_path, [], start=False) as r:
        bus = canopen_bus(r.channel, r.eds, config=SYNC_TPDO)
        errs = CanopenDriver.check_bus(bus)
        assert len(errs) == 1 and "config.pdos[0].transmission_type: a synchronous TPDO (type 1)" \
            " on a bus without sync_period is never sent" in errs[0]
        assert CanopenDriver.check_bus(canopen_bus(r.channel, r.eds, {"sync_period": 0.01},
                                                   config=SYNC_TPDO)) == []


def test_acyclic_synchronous_tpdos_are_counted_when_they_come_never_missing(
        tmp_path: Path) -> None:
    """Transmission type 0: the node sends the TPDO after a SYNC only when its data changed.
    Cycles without it are not missing it (nothing else is due: the count stays exactly 0),
    and each one received is counted in the cycle it came in."""
    devices = [make_device("pos", "sensor", "co", node=NODE, index=0x6064)]
    config = {"pdos": [{"pdo": "tpdo1", "transmission_type": 0, "map": [[0x6064, 0]]}],
              "heartbeat_producer_ms": 20}
    with durand_rig(tmp_path, devices, heartbeat_timeout=0.3, config=config,
                    bus_opts={"sync_period": 0.01}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        assert r.node.read(0x1800, 2) == 0                    # what the node was configured to
        tpdo = 0x180 + NODE
        syncs = len(r.wire.of(0x080))
        assert r.wire.wait_for(lambda w: len(w.of(0x080)) >= syncs + 10)
        quiet = r.driver.sync_stats()
        assert quiet is not None and quiet.cycles >= 10
        assert quiet.missing == 0 and quiet.complete == 0
        sent = len(r.wire.of(tpdo))
        r.node.write(0x6064, 0, 4711)                         # changed: sent after next SYNC
        assert r.host.wait_for(lambda h: 4711 in h.values("pos"))
        assert r.node.wait(lambda: (s := r.driver.sync_stats()) is not None and s.acyclic >= 1)
        assert r.wire.wait_for(lambda w: len(w.of(tpdo)) > sent)   # the recorder's own thread
        frame = r.wire.of(tpdo)[sent]
        assert frame.data[:4] == (4711).to_bytes(4, "little", signed=True)
        # sent in answer to a SYNC (the one on the wire when the value changed, or the next:
        # a loaded node's thread may take a SYNC sent just before the write after it)
        assert any(s.at <= frame.at for s in r.wire.of(0x080))
        # unchanged again: more cycles go by, none of them missing anything, and the node sends
        # no TPDO in them (acyclic: only a change is sent)
        syncs = len(r.wire.of(0x080))
        assert r.wire.wait_for(lambda w: len(w.of(0x080)) >= syncs + 10)
        assert len(r.wire.of(tpdo)) == sent + 1, r.wire.of(tpdo)[sent:]
        stats = r.driver.sync_stats()
        assert stats is not None and stats.missing == 0 and stats.cycles >= quiet.cycles + 10
        assert r.driver.status_doc()["sync"]["acyclic"] == stats.acyclic >= 1
