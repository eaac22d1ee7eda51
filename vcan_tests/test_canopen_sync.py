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
