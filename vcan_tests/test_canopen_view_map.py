"""What users see of a CANopen node's lifecycle and of the SYNC cycle, against durand rebooted
during the run (issue 36): the system map file (sysfile.map), the Prometheus metrics text and
``chcos run``'s progress and summary. Each test also asserts what the node itself holds."""

from __future__ import annotations

from pathlib import Path

from prometheus_client import CollectorRegistry
from prometheus_client.exposition import generate_latest

from chcos.kernel.clock import VirtualClock
from chcos.north.metrics import SystemCollector
from chcos.system import sysmap
from chcos.system.embedded import System
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import DurandNode
from vcan_tests.support_canopen_system import NODE, write_devmap
from vcan_tests.support_faults import run_until


def node_doc(s: System) -> dict:
    return s.devtab.bus_status()["co"]["nodes"][0]


def test_map_and_metrics_show_the_nodes_lifecycle_and_the_sync_cycle(tmp_path: Path) -> None:
    node = DurandNode(unique_channel("view"), NODE)
    s = System([write_devmap(tmp_path, node)], clock=VirtualClock(), machines=[0],
               map_path=tmp_path / "sysfile.map")
    try:
        assert run_until(s, lambda: node_doc(s)["state"] == "OPERATIONAL")
        assert node_doc(s)["boots"] == 0           # it booted before the driver started
        node.power_cycle()                         # a reboot: its configuration is lost
        assert run_until(s, lambda: node_doc(s)["boots"] == 1
                         and node_doc(s)["state"] == "OPERATIONAL")
        assert node.read(0x1017) == 20             # configured again (read from the node)
        assert run_until(s, lambda: s.devtab.bus_status()["co"]["sync"]["complete"] >= 3)
        text = s.execute("map")                    # chcos map: written, and drawn
        assert f"node     co/{NODE}" in text and "OPERATIONAL, 1 boot-up(s) seen, 2 NMT " \
            "start(s), " in text and "EMCY(s), error register 0x00, last EMCY none" in text
        assert "SYNC     co" in text and "cycles of 10 ms" in text
        doc = sysmap.read(tmp_path / "sysfile.map")
        n = doc["bus_status"]["co"]["nodes"][0]
        assert (n["node"], n["state"], n["ready"], n["confirmed"], n["nmt"], n["boots"]) == \
            (NODE, "OPERATIONAL", True, True, "OPERATIONAL", 1)
        assert n["nmt_starts"] == 2 and n["error_register"] == 0 and n["reason"] == ""
        sync = doc["bus_status"]["co"]["sync"]
        assert sync["period"] == 0.01 and sync["cycles"] >= sync["complete"] >= 3
        assert 0 <= sync["jitter_p50"] <= sync["jitter_p99"] <= sync["jitter_max"]
        assert doc["buses"]["co"]["counts"]["sync-cycles"] >= 3
        # the metrics, as Prometheus scrapes them
        registry = CollectorRegistry(auto_describe=False)
        registry.register(SystemCollector(s))
        text = generate_latest(registry).decode()
        assert f'chcos_node_state{{bus="co",node="{NODE}",state="OPERATIONAL"}} 1.0' in text
        assert f'chcos_node_state{{bus="co",node="{NODE}",state="WAITING_BOOT"}} 0.0' in text
        assert f'chcos_node_ready{{bus="co",node="{NODE}"}} 1.0' in text
        assert f'chcos_node_heartbeat_lost{{bus="co",node="{NODE}"}} 0.0' in text
        assert f'chcos_node_boots_total{{bus="co",node="{NODE}"}} 1.0' in text
        assert f'chcos_node_nmt_starts_total{{bus="co",node="{NODE}"}} 2.0' in text
        assert 'chcos_sync_period_seconds{bus="co"} 0.01' in text
        for q in ("0.5", "0.99", "max"):
            assert f'chcos_sync_jitter_seconds{{bus="co",quantile="{q}"}}' in text
        cycles = float(text.split('chcos_sync_cycles_total{bus="co"} ')[1].split()[0])
        assert cycles >= 3
        # the node gone: the map says so
        node.power_off()
        assert run_until(s, lambda: node_doc(s)["heartbeat_lost"])
        assert "heartbeat LOST" in s.execute("map")
        m = sysmap.read(tmp_path / "sysfile.map")
        n = m["bus_status"]["co"]["nodes"][0]
        assert m["buses"]["co"]["counts"]["heartbeat-losses"] >= 1
        assert n["heartbeat_lost"] and n["boots"] == 1 and n["heartbeat_losses"] >= 1
        assert n["emcys"] == 0
        registry = CollectorRegistry(auto_describe=False)
        registry.register(SystemCollector(s))
        text = generate_latest(registry).decode()
        losses = float(text.split(f'chcos_node_heartbeat_losses_total{{bus="co",node="{NODE}"}} '
                                  )[1].split()[0])
        assert losses >= 1
        assert f'chcos_node_emcys_total{{bus="co",node="{NODE}"}} 0.0' in text
    finally:
        s.shutdown()
        node.close()
