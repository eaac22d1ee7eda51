"""Per-node counters of the CANopen driver against durand (issue 36): heartbeat losses (a node
silenced then back counts one loss, a loss that lasts counts once, a second silence another),
EMCYs received, both in the driver's status document and the bus statistics. What is asserted
of the node is what durand did; counts a loaded machine could change are bounded, not exact."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from vcan_tests.support_canopen import NODE, Rig, durand_rig
from vcan_tests.support_fb import WAIT, make_device

DEVICES = [make_device("target", "actuator", "co", node=NODE, index=0x607A)]
#: the master's heartbeat on the wire measures time while the node is silent
MASTER_MS = 30


def node_doc(r: Rig) -> dict[str, Any]:
    doc: dict[str, Any] = r.driver.status_doc()["nodes"][0]
    return doc


def test_a_silenced_node_counts_one_heartbeat_loss_until_it_is_back(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3,
                    config={"heartbeat_producer_ms": 20},
                    bus_opts={"master_heartbeat_ms": MASTER_MS}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        before = node_doc(r)["heartbeat_losses"]
        r.node.write(0x1017, 0, 0)                  # the node's heartbeat producer stops
        assert r.node.wait(lambda: node_doc(r)["heartbeat_lost"])
        lost = node_doc(r)["heartbeat_losses"]
        assert lost >= before + 1
        assert r.host.wait_for(lambda h: "heartbeat" in " ".join(h.failed("target")))
        # a loss that lasts (four timeouts, measured by the master's own heartbeats on the
        # wire) is one loss, not one per check
        since = time.monotonic()
        master = 0x700 + 127
        assert r.wire.wait_for(lambda w: len(w.of(master, since)) >= 1200 // MASTER_MS)
        assert node_doc(r)["heartbeat_losses"] == lost and node_doc(r)["heartbeat_lost"]
        r.node.write(0x1017, 0, 20)                 # back
        assert r.node.wait(lambda: not node_doc(r)["heartbeat_lost"])
        assert r.host.wait_for(lambda h: "target" in h.recoveries)
        back = node_doc(r)["heartbeat_losses"]
        assert back >= lost
        r.node.write(0x1017, 0, 0)                  # silenced again: another loss
        assert r.node.wait(lambda: node_doc(r)["heartbeat_lost"])
        again = node_doc(r)["heartbeat_losses"]
        assert again >= back + 1
        # the bus statistics count the same losses
        assert r.driver.settle(WAIT)
        assert r.host.wait_for(lambda h: h.stats.get("heartbeat-losses", 0) == again)
        assert r.driver.node_states()[NODE].heartbeat_losses == again


def test_emcys_received_are_counted_per_node(tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3,
                    config={"heartbeat_producer_ms": 20}) as r:
        assert r.node.wait(lambda: r.driver.node_states()[NODE].ready)
        assert node_doc(r)["emcys"] == 0
        r.node.emcy(0x1000, 0x01)                   # a generic error: not fatal
        assert r.node.wait(lambda: node_doc(r)["emcys"] == 1)
        r.node.emcy(0x0000, 0x00)                   # the error reset is an EMCY too
        assert r.node.wait(lambda: node_doc(r)["emcys"] == 2)
        assert "register 0x00" in node_doc(r)["last_emcy"]
        assert r.driver.node_states()[NODE].emcys == 2
        assert r.host.error_kinds().count("emcy") == 2
