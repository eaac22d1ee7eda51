"""``chcos monitor`` shows each CANopen node's life as the wire shows it (NMT state of its
heartbeat, boot-ups seen, heartbeat losses, EMCYs, last EMCY) and another master's SYNC cycle
(issue 36), listening to a durand node driven by chcos's CANopen driver as the master, the node
rebooted meanwhile."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Callable
from pathlib import Path

from chcos.cli import monitor
from chcos.devices.devmap import load
from drivers.canopen_node import CanopenDriver
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import WAIT, DurandNode
from vcan_tests.support_canopen_system import NODE, write_devmap
from vcan_tests.support_fb import FakeHost


def until(pred: Callable[[], bool], timeout: float = 4 * WAIT) -> bool:
    """Poll ``pred`` (what the monitor shows) until it holds; False on timeout."""
    deadline = time.monotonic() + timeout
    pause = threading.Event()
    while not pred():
        if time.monotonic() > deadline:
            return False
        pause.wait(0.02)
    return True


def test_monitor_shows_node_lives_and_the_masters_sync(tmp_path: Path) -> None:
    node = DurandNode(unique_channel("mon"), NODE)
    devmap = write_devmap(tmp_path, node)
    system = tmp_path / "system.toml"
    system.write_text('[system]\nname = "cell"\ndevmaps = ["devices.toml"]\n', encoding="utf-8")
    dm = load([devmap])
    master = CanopenDriver(dm.buses[0], dm.devices, FakeHost())   # another master on the bus
    mon = monitor.Monitor(system, grace=0.5)
    try:
        master.start()
        line = f"bus co: node {NODE}: "

        def shown(*parts: str) -> bool:
            return any(line in x and all(p in x for p in parts) for x in mon.node_lines())

        def count(what: str) -> int:
            """The number before ``what`` on the node's line."""
            text = next(x for x in mon.node_lines() if line in x)
            return int(text.split(what)[0].rsplit(" ", 1)[-1])

        assert until(lambda: shown(": OPERATIONAL (heartbeat", "0 boot-up(s) seen",
                                   "last EMCY none")), mon.node_lines()
        node.power_cycle()
        assert until(lambda: shown(": OPERATIONAL (heartbeat", "1 boot-up(s) seen")), \
            (mon.node_lines(), master.node_states())

        def sync_seen() -> int:
            syncs = [x for x in mon.node_lines() if x.startswith("bus co: SYNC: ")]
            return int(syncs[0].split()[3]) if syncs else 0

        assert until(lambda: sync_seen() >= 10)
        sync = next(x for x in mon.node_lines() if x.startswith("bus co: SYNC: "))
        assert "jitter against 10 ms p50" in sync and "period" in sync, sync
        assert master.sync_stats() is not None
        # the position, decoded from TPDO1 as the node's config maps it (not as its EDS)
        node.write(0x6064, 0, 4321)
        assert until(lambda: next(r for r in mon.rows() if r["name"] == "pos")["value"]
                     == 4321), mon.rows()
        assert not [f for f in mon.bus_flags() if "unknown id" in f], mon.bus_flags()
        out = io.StringIO()
        monitor._show(mon.rows(), mon.bus_flags(), 1.0, out, mon.node_lines())
        assert f"  bus co: node {NODE}: OPERATIONAL" in out.getvalue(), out.getvalue()
        assert shown("0 EMCY(s)"), mon.node_lines()
        node.emcy(0x3210, 0x04)                      # over-voltage: durand leaves OPERATIONAL
        assert until(lambda: shown("1 EMCY(s), last EMCY 0x3210 register 0x04")), \
            mon.node_lines()
        # the node's heartbeat stops beyond its timeout, then comes back: one loss seen
        losses = count(" heartbeat loss(es)")
        node.write(0x1017, 0, 0)
        assert until(lambda: any(f"node {NODE}: no heartbeat" in f for f in mon.bus_flags()))
        assert count(" heartbeat loss(es)") == losses  # counted once heard again
        node.write(0x1017, 0, 20)
        assert until(lambda: count(" heartbeat loss(es)") >= losses + 1), mon.node_lines()
    finally:
        mon.close()
        master.stop()
        node.close()
