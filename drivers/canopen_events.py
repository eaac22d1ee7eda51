"""canopen_events - the receive side of the ``canopen`` driver (:mod:`drivers.canopen_node`):
the frames of its reader thread handed to canopen's listeners (SDO responses, PDOs, heartbeats,
EMCY), TPDO readings, the NMT state of each heartbeat driving the node's lifecycle (a boot-up is
a reboot), heartbeat supervision (on its own thread, :mod:`drivers.canopen_watchdog`), EMCY
failures and recoveries, and the frames canopen would drop quietly. :class:`NodeEvents` is an
object the driver composes (it holds the nodes, their health and the SYNC cycle, and queues jobs
through the callable it is given); the life cycle of the driver, the boot procedure of the nodes,
the SDO polls and the writes are :class:`drivers.canopen_node.CanopenDriver`.

Failure causes of a device (:class:`drivers.health.Health`, each with its reason): ``lifecycle``
(the node is not in the state the map requires: waiting for its boot-up, rebooted, identity
mismatch, configuration refused, held in PRE-OPERATIONAL), ``heartbeat`` (lost), ``emcy`` (a
fatal EMCY, or the error register 0x1001 set at boot), ``sdo`` (a transfer of this device
failed). A device recovers when its last cause clears.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

import can

from drivers.base import DriverHost, deliver_all, host_clock_virtual, host_peers_on_clock
from drivers.canopen_jobs import BootNode, CanopenJob, ReportHeld
from drivers.canopen_lifecycle import NmtState, NodeLifecycle, NodeStatus
from drivers.canopen_od import DEFAULT_MASTER_ID
from drivers.canopen_remote import ManagedNode
from drivers.canopen_sync import SYNC_COB_ID, SyncCycle, SyncStats
from drivers.canopen_watchdog import HeartbeatWatchdog
from drivers.codecs.canopen import (
    emcy_node,
    heartbeat_node,
    is_error_reset,
    is_fatal_emcy,
)
from drivers.health import Health
from drivers.threaded import ReaderThread

RETRY_SILENT = 2.0
"""Seconds between two boot procedures of a node that heartbeats but did not answer SDO."""

HEARTBEAT_SETTLE = 0.1
"""Bound (s) on handing over received frames before a heartbeat loss is declared (polling
interfaces; on SocketCAN the drain is immediate)."""


class NodeEvents:
    """The nodes of a ``canopen`` bus and everything that happens to them (see the module doc).
    ``submit`` queues a job on the driver's I/O thread (False when it is stopping)."""

    def __init__(self, bus: str, host: DriverHost, submit: Callable[[CanopenJob], bool]) -> None:
        self.bus = bus
        self.host = host
        self.health = Health(host)
        self.submit = submit
        self.nodes: dict[int, ManagedNode] = {}
        #: sensors delivered from TPDOs: (node, index, subindex) -> device names
        self.pdo_sensors: dict[tuple[int, int, int], list[str]] = {}
        #: canopen's Network whose listeners get the frames (set at start)
        self.network: Any = None
        #: the reader whose input a watchdog hands over before it declares a loss (set at start)
        self.rx: ReaderThread | None = None
        #: the node id of this master's heartbeat (bus option ``master_node_id``)
        self.master_id = DEFAULT_MASTER_ID
        self.sync: SyncCycle | None = None
        #: True when a producer process sends SYNC and the reader counts each one it sees
        self.observe_sync = False
        self._watchdog: HeartbeatWatchdog | None = None
        #: the clock heartbeats are supervised on: wall time, or the kernel's virtual clock when
        #: the nodes are simulated on it (then on kernel timers, not the watchdog thread: a
        #: virtual cell is deterministic; a real node's heartbeat keeps wall time)
        self.clock: Callable[[], float] = time.monotonic
        self._watching = False
        self._bus_failed = False
        #: frames handed to canopen's listeners, written by whoever receives (the reader, or a
        #: settle's drain: one at a time, under the reader's lock); of which reported to the
        #: host as ``frames`` (:meth:`tell_frames`, under ``_told_lock``)
        self._frames_in = 0
        self._frames_told = 0
        self._told_lock = threading.Lock()
        #: the SYNC counters last added to the host's statistics (cycles, missing, late)
        self._sync_told = (0, 0, 0)
        #: the TPDO values of a node hosting axes: ``axis_feed(node id, [(index, sub, raw)])``
        self.axis_feed: Callable[[int, list[tuple[int, int, int]]], None] | None = None
        #: a node hosting axes failed (lifecycle, heartbeat): ``node_down(node, reason)``;
        #: ``node_up(node)`` once it is ready again (the driver calls its axes' ``lost`` once)
        self.node_down: Callable[[ManagedNode, str], None] | None = None
        self.node_up: Callable[[ManagedNode], None] | None = None

    # -- what the driver shows ------------------------------------------------------------------

    def node_states(self) -> dict[int, NodeStatus]:
        """Each node's lifecycle status by node id (see :class:`NodeStatus`). Thread-safe."""
        out = {}
        for nid, node in self.nodes.items():
            with node.lock:
                out[nid] = node.lifecycle.status()
        return out

    def sync_stats(self) -> SyncStats | None:
        """The SYNC cycle's counters and jitter (None without ``sync_period``)."""
        sync = self.sync
        return None if sync is None else sync.stats()

    def wait_cycle(self, n: int, timeout: float) -> bool:
        """Wait until SYNC cycle ``n`` is complete: every synchronous TPDO due in it arrived
        (True), or SYNC n+1 went out first or ``timeout`` passed (False; also without SYNC)."""
        sync = self.sync
        return False if sync is None else sync.wait_cycle(n, timeout)

    # -- the node's readiness and its devices ----------------------------------------------------

    def where(self, node: ManagedNode) -> str:
        return node.where(self.bus)

    def judge(self, node: ManagedNode, why_ok: str) -> None:
        """Fail or recover ``node``'s devices (cause ``lifecycle``) by its lifecycle: OK only
        while it is ready; while the driver is first bringing it up, not failed yet."""
        with node.lock:
            ready = node.lifecycle.ready()
            if ready:
                node.starting = False
            hold = node.starting
            reason = f"{self.where(node)}: {node.lifecycle.state.value}: {node.lifecycle.reason}"
        if ready:
            for dev in node.devices:
                self.health.clear(dev, "lifecycle", f"{self.where(node)}: {why_ok}")
            if node.axes and self.node_up is not None:
                self.node_up(node)
        elif not hold:
            for dev in node.devices:
                self.health.fail(dev, "lifecycle", reason)
            if node.axes and self.node_down is not None:
                self.node_down(node, reason)

    def fail_node(self, node: ManagedNode, cause: str, reason: str) -> None:
        for dev in node.devices:
            self.health.fail(dev, cause, reason)
        if cause != "emcy" and node.axes and self.node_down is not None:
            self.node_down(node, reason)

    def clear_node(self, node: ManagedNode, cause: str, why: str) -> None:
        for dev in node.devices:
            self.health.clear(dev, cause, why)

    # -- statistics and the watchdog thread -------------------------------------------------

    def tell_frames(self) -> None:
        """Count the frames received since the last call in the host's ``frames`` statistic,
        as one addition (one per frame would cost the reader a locked call per frame)."""
        with self._told_lock:
            n = self._frames_in
            new, self._frames_told = n - self._frames_told, n
        if new:
            self.host.stat(self.bus, "frames", new)
        sync = self.sync
        if sync is not None:
            now = sync.counters()
            with self._told_lock:
                told, self._sync_told = self._sync_told, now
            for key, a, b in zip(("sync-cycles", "sync-missing", "sync-late"), told, now,
                                 strict=True):
                if b > a:
                    self.host.stat(self.bus, key, b - a)

    def check_heartbeats(self) -> float:
        """Fail the devices of nodes whose heartbeat is overdue; the time to the next deadline
        (the watchdog thread). Before it declares a node lost it has the reader hand over every
        frame the operating system already holds: after this process was stalled (a loaded
        machine, a virtual one) the watchdog may wake before the reader, and a heartbeat waiting
        in the socket is not a missing one."""
        now = self.clock()
        overdue = False
        for s in self.nodes.values():
            with s.lock:
                overdue |= (s.heartbeat_timeout is not None and not s.lost and not s.booting
                            and now - s.last_heartbeat > s.heartbeat_timeout)
        rx = self.rx
        if overdue and rx is not None:
            rx.settle(HEARTBEAT_SETTLE)
        wait = 0.5
        for s in self.nodes.values():
            with s.lock:
                if s.heartbeat_timeout is None or s.lost or s.booting:
                    continue
                late = now - s.last_heartbeat
                s.lost = late > s.heartbeat_timeout
                if s.lost:
                    s.starting = False
                    s.lifecycle.heartbeat_lost()
            if s.lost:
                self.host.stat(self.bus, "heartbeat-losses")
                self.fail_node(s, "heartbeat", f"{self.where(s)}: no heartbeat for more "
                                                f"than heartbeat_timeout {s.heartbeat_timeout} s")
            else:
                wait = min(wait, s.heartbeat_timeout - late + 0.001)
        return wait

    def start_watchdog(self) -> None:
        if not any(s.heartbeat_timeout is not None for s in self.nodes.values()):
            return
        if host_clock_virtual(self.host) and host_peers_on_clock(self.host):
            self.clock = self.host.now
            self._watching = True
            self._watch_virtual()
            return
        self._watchdog = HeartbeatWatchdog(self.check_heartbeats,
                                           f"canopen-{self.bus}-watchdog")
        self._watchdog.start()

    def _watch_virtual(self) -> None:
        """The watchdog on a virtual clock: a kernel timer at each deadline."""
        if self._watching:
            wait = max(0.001, self.check_heartbeats())
            self.host.at(round(self.host.now() + wait, 9), self._watch_virtual)

    def stop_watchdog(self) -> None:
        self._watching = False
        wd, self._watchdog = self._watchdog, None
        if wd is not None:
            wd.stop()

    # -- reader thread ------------------------------------------------------------------------

    def on_frame(self, frame: can.Message) -> None:
        """A received frame to canopen's listeners (what its notifier would do)."""
        self._bus_failed = False     # a receive error is reported again after a good frame
        self._frames_in += 1         # to the statistics in tell_frames
        if frame.arbitration_id == SYNC_COB_ID and self.observe_sync:
            sync = self.sync
            if sync is not None:
                sync.seen(frame.timestamp)
            return
        network = self.network
        if network is None:
            return
        for listener in network.listeners:
            try:
                listener.on_message_received(frame)
            except Exception as exc:  # the reader must survive any canopen/host surprise
                self.host.error(self.bus, "internal", f"frame handling failed: {exc!r}")

    def on_bus_error(self, reason: str) -> None:
        if not self._bus_failed:
            self._bus_failed = True
            self.host.error(self.bus, "bus-error",
                            f"canopen bus {self.bus}: receive failed: {reason}")

    def on_tpdo(self, pdo_map: Any) -> None:
        """A TPDO arrived (reader thread, or settle's drain: both under the reader's lock, so
        settle never returns while one is being delivered)."""
        nid = pdo_map.pdo_node.node.id
        sync = self.sync
        if sync is not None:
            sync.tpdo(pdo_map.cob_id)
        if len(pdo_map.data) * 8 < pdo_map.length:
            self.host.error(self.bus, "malformed",
                            f"{pdo_map.name} from canopen node {nid}: {len(pdo_map.data)} "
                            f"bytes, expected {(pdo_map.length + 7) // 8}")
            return
        deliver_all(self.host, [(dev, var.raw) for var in pdo_map.map
                                for dev in self.pdo_sensors.get((nid, var.index, var.subindex),
                                                                 ())])
        feed = self.axis_feed
        if feed is not None and self.nodes[nid].axes:
            feed(nid, [(var.index, var.subindex, var.raw) for var in pdo_map.map])

    def on_heartbeat(self, node: ManagedNode, code: int) -> None:
        """A heartbeat or boot-up of ``node`` (reader thread): supervision, then the lifecycle."""
        nmt = NmtState.of(code)
        if nmt is NmtState.BOOT_UP:     # failed for the reboot before the loss ends
            self.rebooted(node)
        with node.lock:
            node.last_heartbeat = self.clock()
            was_lost, node.lost = node.lost, False
        if was_lost:
            self.clear_node(node, "heartbeat", f"canopen node {node.id}: heartbeat back")
            if node.axes and self.node_up is not None:
                self.node_up(node)
        if nmt is NmtState.BOOT_UP:
            return
        if nmt is None:
            self.host.error(self.bus, "malformed", f"{self.where(node)}: heartbeat with "
                                                        f"unknown NMT state {code:#x}")
            return
        if self.retry_silent(node):
            return
        with node.lock:
            before = node.lifecycle.state
            node.lifecycle.heartbeat(nmt)
            after, generation = node.lifecycle.state, node.lifecycle.generation
            if after is NodeLifecycle.PREOP_HELD:
                node.starting = False
        if after is NodeLifecycle.PREOP_HELD and before is not NodeLifecycle.PREOP_HELD:
            self.submit(ReportHeld(node.id, generation))
        if after is not before or not node.lifecycle.ready():
            self.judge(node, f"heartbeat confirms {nmt.name}")

    def retry_silent(self, node: ManagedNode) -> bool:
        """A heartbeat of a node whose boot procedure found it silent (it was busy, or came up
        without a boot-up message we saw): run the procedure again, at most every
        :data:`RETRY_SILENT` s (each try may cost SDO timeouts on the I/O thread)."""
        now = time.monotonic()
        with node.lock:
            if (node.booting or node.lifecycle.state is not NodeLifecycle.WAITING_BOOT
                    or now < node.retry_at):
                return False
            node.retry_at = now + RETRY_SILENT
            node.booting = True
            generation = node.lifecycle.restart("heartbeat of a node that had not answered: "
                                                "identity, configuration and NMT start again")
        self.submit(BootNode(node.id, generation))
        return True

    def rebooted(self, node: ManagedNode) -> None:
        """A boot-up message: the node's devices fail, its boot procedure runs again (the safe
        values follow its recovery, through the host)."""
        with node.lock:
            generation = node.lifecycle.booted()
            node.starting = False
            node.booting = True
        reason = f"{self.where(node)}: rebooted (boot-up message): configuring it again"
        self.host.error(self.bus, "boot-up", reason)
        self.fail_node(node, "lifecycle", reason)
        self.submit(BootNode(node.id, generation))

    def on_emcy(self, node: ManagedNode, entry: Any) -> None:
        text = f"{self.where(node)}: EMCY {entry} register 0x{entry.register:02X}"
        with node.lock:
            node.lifecycle.emcy(f"{entry} register 0x{entry.register:02X}")
        self.host.error(self.bus, "emcy", text)
        if is_error_reset(entry.code):
            self.clear_node(node, "emcy", f"canopen node {node.id}: error-reset EMCY")
        elif is_fatal_emcy(entry.code) and not node.axes:
            # a drive's fault is its axes' failure, judged from the statusword (failing the
            # node would refuse the fault reset and the statusword: the deadlock of issue 37)
            self.fail_node(node, "emcy", text)

    def report_frame(self, kind: str, detail: str) -> None:
        """A frame-level problem seen by the bus listener (see :class:`FrameCheck`)."""
        self.host.error(self.bus, kind, detail)

    def knows_node(self, node_id: int) -> bool:
        """True if ``node_id`` is one of this bus's nodes or the master's own id (whose
        heartbeat other sockets of this host see on SocketCAN)."""
        return node_id in self.nodes or node_id == self.master_id


class FrameCheck(can.Listener):
    """Reports frames canopen would drop quietly: heartbeats of unknown nodes, short EMCYs."""

    def __init__(self, driver: NodeEvents) -> None:
        self._driver = driver

    def on_message_received(self, msg: can.Message) -> None:
        cob = msg.arbitration_id
        if cob > 0x77F or 0xFF < cob < 0x701 or cob < 0x81:
            return   # neither a heartbeat nor an EMCY COB-ID: most frames (SDO, PDO) end here
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        hb, emcy = heartbeat_node(cob), emcy_node(cob)
        if hb is not None and not self._driver.knows_node(hb):
            self._driver.report_frame("unknown-node",
                                      f"heartbeat of node {hb} (COB-ID 0x{cob:03X}), "
                                      f"which is not in the bus's nodes")
        elif emcy is not None and self._driver.knows_node(emcy) and msg.dlc < 8:
            self._driver.report_frame("malformed",
                                      f"EMCY from node {emcy} with {msg.dlc} bytes, "
                                      f"expected 8")

    def stop(self) -> None:
        """Nothing to release."""
