"""Noise and small truths of the CANopen driver (issue 46): the heartbeats of a node not in the
map are counted each and reported once per period (not one WARNING per heartbeat, forever); an
SDO abort chcos sends names the object of the transfer it aborts (CiA 301), as an observer on
the wire sees it. Against durand nodes on python-can's virtual bus."""

from __future__ import annotations

import time
from pathlib import Path

from vcan_tests.peers.durand_node import DurandNode, Stored
from vcan_tests.support_canopen import NODE, durand_rig
from vcan_tests.support_fb import make_device

DEVICES = [make_device("pos", "sensor", "co", node=NODE, index=0x6064)]


def test_heartbeats_of_an_unknown_node_are_counted_and_reported_once_per_period(
        tmp_path: Path) -> None:
    with durand_rig(tmp_path, DEVICES, heartbeat_timeout=0.3,
                    node_kw={"stored": Stored(heartbeat_ms=20)}) as r:
        stranger = DurandNode(r.channel, 9, stored=Stored(heartbeat_ms=10))
        try:
            since = time.monotonic()
            assert r.wire.wait_for(lambda w: len(w.of(0x709, since)) >= 20)
            assert r.host.wait_for(lambda h: h.stats.get("unknown-node-frames", 0) >= 20)
            reports = [d for _b, k, d in r.host.errors if k == "unknown-node"]
            assert len(reports) == 1, reports        # the first at once, then one per period
            assert "of node 9 (COB-ID 0x709)" in reports[0]
            assert "not in the bus's nodes" in reports[0]
        finally:
            stranger.close()
        r.driver.stop()                              # what is pending is reported at stop
        reports = [d for _b, k, d in r.host.errors if k == "unknown-node"]
        assert len(reports) == 2 and "heartbeat(s) of node 9" in reports[1]
        counted = int(reports[1].split()[0])
        assert counted >= 19


def test_an_sdo_abort_chcos_sends_names_the_object(tmp_path: Path) -> None:
    """A node that stops answering SDO: canopen's client gives up and sends an abort transfer
    (0x05040000, SDO protocol timed out); its multiplexer is that of the request it gave up on
    (the last initiate request before it on the wire), never 0x0000:00."""
    devices = [make_device("pos", "sensor", "co", node=NODE, index=0x6064, poll_period=0.05)]
    with durand_rig(tmp_path, devices, node_kw={"stored": Stored(heartbeat_ms=20)},
                    nmt_start=False) as r:
        assert r.host.wait_for(lambda h: r.driver.node_states()[NODE].ready)
        r.node.power_off()                           # no more answers
        r.host.tick(0.05)                            # a poll falls due
        assert r.wire.wait_for(lambda w: any(f.data[:1] == b"\x80"
                                             for f in w.of(0x600 + NODE)))
        requests = r.wire.of(0x600 + NODE)
        aborts = [i for i, f in enumerate(requests) if f.data[:1] == b"\x80"]
        for at in aborts:
            asked = next(f.data for f in reversed(requests[:at]) if f.data[0] >> 5 in (1, 2))
            data = requests[at].data
            assert data[1:4] == asked[1:4] and data[1:4] == b"\x64\x60\x00", data.hex()
            assert int.from_bytes(data[4:8], "little") == 0x05040000
