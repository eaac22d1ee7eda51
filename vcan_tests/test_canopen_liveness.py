"""A hung controller is seen by its nodes (issue 46): the master heartbeat and SYNC go out only
while the controller's kernel makes progress (:mod:`drivers.canopen_heartbeat`). Here a task
that never awaits holds the kernel thread, the chcos process and its threads running on: the
master heartbeat and SYNC stop on the wire, a durand node watching the master
(:class:`vcan_tests.support_canopen_node.Cia301Node`) declares it lost, leaves OPERATIONAL and
says so; once the task lets go the heartbeat is back, the node clears its error and the
driver's recovery policy starts it again. What is asserted is what the node did and what an
independent observer saw on the wire. The stopped process (SIGSTOP) is in
``test_canopen_liveness_process.py`` (host) and ``test_canopen_liveness_socketcan.py``
(the SocketCAN guest)."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

from durand.services.nmt import StateEnum

from chcos.kernel.clock import RealClock
from chcos.kernel.scheduler import Kernel
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from drivers.canopen_heartbeat import Liveness
from vcan_tests.netutil import unique_channel
from vcan_tests.peers.durand_node import Wire
from vcan_tests.support_canopen_node import EMCY_HEARTBEAT, Cia301Node
from vcan_tests.support_faults import wait_until
from vcan_tests.support_fb import WAIT, FakeHost

M = "vcan_tests.test_canopen_liveness"
NODE = 5
MASTER = 0x700 + 127


async def stuck(ctx: TaskContext, cmd: dict[str, Any]) -> None:
    """A task that holds the kernel thread (a step that never awaits) until released."""
    cmd["entered"].set()
    cmd["release"].wait(cmd["wall"])


class ResettingNode(Cia301Node):
    """A node whose heartbeat consumer, once the master is heard again, ends its error as
    CANopen stacks do: the error-reset EMCY and 0x1001 back to 0."""

    def _heartbeat(self, ms: int) -> None:
        super()._heartbeat(ms)
        if self.consumer_losses > getattr(self, "_resets", 0):
            self._resets = self.consumer_losses
            self.node.emcy.set(0x0000, 0x00)
            self.event("error reset")


MAP = """
[[bus]]
name = "co"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.5
master_heartbeat_ms = 30
sync_period = 0.01
liveness_ms = 300

[[bus.nodes]]
id = {node}
eds = "{eds}"
heartbeat_timeout = 1.0
restart_backoff = 0.2
[bus.nodes.config]
heartbeat_producer_ms = 30
master_consumer_ms = 400
error_behaviour = 0

[[device]]
name = "target"
direction = "actuator"
bus = "co"
address = {{ node = {node}, index = 0x607A }}
limits = [-100000, 100000]
"""


def test_a_stuck_kernel_stops_the_master_heartbeat_and_sync_and_the_node_notices(
        tmp_path: Path) -> None:
    channel = unique_channel("live")
    node = ResettingNode(channel, NODE)
    eds = node.write_eds(tmp_path / "node.eds")
    wire = Wire(channel)
    path = tmp_path / "co.toml"
    path.write_text(MAP.format(channel=channel, node=NODE, eds=eds), encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0])
    s.execute(f"install -m0 --code={M}:stuck T")
    release = threading.Event()
    s.start()
    try:
        drv = next(d for d in s.devtab.drivers if d.bus.name == "co")
        assert wait_until(lambda: drv.node_states()[NODE].ready  # type: ignore[attr-defined]
                          and node.seen("consumer armed"))
        assert node.consumer_losses == 0 and node.state == StateEnum.OPERATIONAL
        entered = threading.Event()
        s.call(s.invoke, "T", {"entered": entered, "release": release, "wall": 2 * WAIT})
        assert entered.wait(WAIT)
        # the kernel is held; the process, its reader and its heartbeat thread run on
        assert node.wait(lambda: node.consumer_losses == 1, WAIT)
        assert node.wait(lambda: node.state == StateEnum.PRE_OPERATIONAL)
        lost_at = time.monotonic()
        assert wire.wait_for(lambda w: bool(w.of(0x080 + NODE, lost_at - 1.0)))
        emcy = next(f for f in wire.of(0x080 + NODE)
                    if int.from_bytes(f.data[:2], "little") == EMCY_HEARTBEAT)
        # from the node's EMCY on, while the kernel is held: no heartbeat, no SYNC (the
        # node waited its consumer time after the last heartbeat; SYNC stopped with it)
        assert wire.wait_for(lambda w: len(w.of(0x700 + NODE, emcy.at)) >= 5)
        held = [f for f in wire.frames if f.at >= emcy.at and f.cob_id in (MASTER, 0x080)]
        assert held == [], held[:3]
        before = [f for f in wire.frames if f.at < emcy.at]
        assert any(f.cob_id == MASTER for f in before) and any(f.cob_id == 0x080
                                                              for f in before)
        released = time.monotonic()
        release.set()
        # the kernel goes on: the heartbeat and SYNC are back, the node clears its error,
        # the driver starts it again
        assert wire.wait_for(lambda w: bool(w.of(MASTER, released)) and bool(w.of(0x080,
                                                                                 released)))
        assert node.wait(lambda: node.seen("error reset"))
        assert node.wait(lambda: node.state == StateEnum.OPERATIONAL, WAIT)
        assert wait_until(lambda: drv.node_states()[NODE].ready)  # type: ignore[attr-defined]
        st = drv.node_states()[NODE]  # type: ignore[attr-defined]
        assert st.restarts == 1
        stats = drv.sync_stats()  # type: ignore[attr-defined]
        assert stats is not None and stats.given_up > 0
        errors = s.devtab.bus_errors
        assert errors[("co", "controller-stalled")] >= 2       # the heartbeat's and SYNC's
        doc = s.devtab.bus_status()["co"]
        assert doc["sync"]["given_up"] == stats.given_up or doc["sync"]["given_up"] > 0
    finally:
        release.set()
        s.shutdown()
        wire.close()
        node.close()


def test_kernel_progress_stands_still_while_a_step_holds_the_kernel() -> None:
    from vcan_tests.test_core_kernel import spawn

    k = Kernel(RealClock())
    entered, release = threading.Event(), threading.Event()

    async def hog() -> None:
        entered.set()
        release.wait(WAIT)

    runner = threading.Thread(target=k.run)
    runner.start()
    try:
        assert wait_until(lambda: k.running)
        assert k.progress <= k.clock.now()        # idle: progress is now
        k.interrupt(lambda: spawn(k, "hog", hog(), 10))
        assert entered.wait(WAIT)
        held = k.progress
        assert wait_until(lambda: k.clock.now() > held + 0.05)
        assert k.progress == held                 # no round completed meanwhile
        release.set()
        assert wait_until(lambda: k.progress > held)
    finally:
        release.set()
        k.stop()
        runner.join(WAIT)


def test_liveness_follows_the_hosts_progress_and_without_it_the_process() -> None:
    class Host(FakeHost):
        at_progress = 0.0

        def progress(self) -> float:
            return self.at_progress

    host = Host()
    live = Liveness(host, 0.3)
    assert live.gated and live.alive()
    host.tick(0.3)
    assert live.alive() and live.stalled_for() == 0.3
    host.tick(0.01)
    assert not live.alive()
    host.at_progress = host.now()
    assert live.alive()
    assert Liveness(host, 0.0).alive() and not Liveness(host, 0.0).gated
    plain = Liveness(FakeHost(), 0.3)            # a host that does not say: the process only
    assert not plain.gated and plain.alive()
