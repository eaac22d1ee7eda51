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
from drivers.canbus import Tally
from drivers.canopen_jobs import AxisRefresh, BootNode, CanopenJob, ReportHeld, RestartNode
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

REPORT_PERIOD = 10.0
"""Seconds between two reports of the same recurring frame problem (a node not in the map
heartbeating): the first at once, then one line per period with the count
(:class:`drivers.canbus.Tally`)."""


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
        #: True on SocketCAN: producer processes send the master heartbeat and SYNC
        self.observe = False
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
        #: the SYNC counters last added to the host's statistics (cycles, missing, late,
        #: given up)
        self._sync_told = (0, 0, 0, 0)
        #: the TPDO values of a node hosting axes: ``axis_feed(node id, [(index, sub, raw)])``
        self.axis_feed: Callable[[int, list[tuple[int, int, int]]], None] | None = None
        #: a node hosting axes failed (lifecycle, heartbeat): ``node_down(node, reason)``;
        #: ``node_up(node)`` once it is ready again (the driver calls its axes' ``lost`` once)
        self.node_down: Callable[[ManagedNode, str], None] | None = None
        self.node_up: Callable[[ManagedNode], None] | None = None
        #: heartbeats of nodes not in the map, reported once per :data:`REPORT_PERIOD` per
        #: node with their count (a node heartbeats 10 times a second, forever)
        self.unknown = Tally(self._report_unknown, REPORT_PERIOD, examples=1)
        #: False once the driver stops: no restart is armed any more
        self.running = True

    # -- what the driver shows ------------------------------------------------------------------

    def node_states(self) -> dict[int, NodeStatus]:
        """Each node's lifecycle status by node id (see :class:`NodeStatus`). Thread-safe."""
        out = {}
        for nid, node in self.nodes.items():
            with node.lock:
                out[nid] = node.lifecycle.status(self.lost_reason(node))
        return out

    @staticmethod
    def lost_reason(node: ManagedNode) -> str:
        """Why a node whose heartbeat is lost is not ready."""
        return f"no heartbeat for more than heartbeat_timeout {node.heartbeat_timeout} s"

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

    def reason(self, node: ManagedNode) -> str:
        """Why ``node``'s devices fail for its lifecycle: the node, its state (unless its
        reason says it already) and the reason (call with the node's lock held)."""
        lc = node.lifecycle
        state = "" if lc.reason.startswith(lc.state.value) else f"{lc.state.value}: "
        return f"{self.where(node)}: {state}{lc.reason}"

    def judge(self, node: ManagedNode, why_ok: str) -> None:
        """Fail or recover ``node``'s devices (cause ``lifecycle``) by its lifecycle: OK only
        while it is ready; while the driver is first bringing it up, not failed yet."""
        with node.lock:
            ready = node.lifecycle.ready()
            if ready:
                node.starting = False
            hold = node.starting
            reason = self.reason(node)
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

    def restate(self, node: ManagedNode) -> None:
        """The reason of a node that is not ready changed while it stays so (its recovery
        moved on: a restart sent, its next one planned): its devices show the new one."""
        with node.lock:
            if node.lifecycle.ready() or node.starting:
                return
            reason = self.reason(node)
        for dev in node.devices:
            self.health.restate(dev, "lifecycle", reason)

    # -- the recovery policy -----------------------------------------------------------------

    def arm_restart(self, node: ManagedNode, at_once: bool = False) -> None:
        """Queue the node's next restart (a :class:`RestartNode` job) at the time its policy
        says (its backoff, from when it left or its last restart was not taken; ``at_once``:
        its cause cleared, so as soon as the backoff allows). Nothing when the policy is used
        up or the driver stops. On the host's clock (``host.at``)."""
        now = self.host.now()
        with node.lock:
            lc = node.lifecycle
            nxt = lc.next_restart()
            if nxt is None or lc.state is not NodeLifecycle.LEFT_OPERATIONAL \
                    or not self.running:
                return
            if at_once:                     # no sooner than its backoff allows
                when = max(now, node.retry_at_host or now)
            else:
                when = node.retry_at_host = now + nxt[1]
            episode, nid = lc.episode, node.id
        def due() -> None:
            self.submit(RestartNode(nid, episode))
        self.host.at(round(when, 9), due)

    def left(self, node: ManagedNode) -> None:
        """The node left OPERATIONAL by itself (its heartbeat said so): reported once, its
        devices failed with the reason, its axes told (their drive is read at once), and its
        first restart armed."""
        with node.lock:
            reason = node.lifecycle.reason
        self.host.error(self.bus, "left-operational", f"{self.where(node)}: {reason}")
        self.arm_restart(node)

    def fail_node(self, node: ManagedNode, cause: str, reason: str,
                  keep: tuple[str, ...] = ()) -> None:
        """Fail ``node``'s devices (but those in ``keep``) for ``cause``."""
        for dev in node.devices:
            if dev not in keep:
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
            for key, a, b in zip(("sync-cycles", "sync-missing", "sync-late",
                                  "sync-given-up"), told, now, strict=True):
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
            node.lifecycle.lost = False
            seen_before, node.last_nmt = node.last_nmt, nmt
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
        if seen_before is not None and nmt is not seen_before and node.axes:
            self.refresh_axes(node)         # a drive that changed state may have faulted
        if self.retry_silent(node):
            return
        with node.lock:
            before, episode = node.lifecycle.state, node.lifecycle.episode
            node.lifecycle.heartbeat(nmt, self.host.now())
            after, generation = node.lifecycle.state, node.lifecycle.generation
            moved = node.lifecycle.episode != episode
            if after in (NodeLifecycle.PREOP_HELD, NodeLifecycle.LEFT_OPERATIONAL):
                node.starting = False
        if after is not before or not node.lifecycle.ready():
            self.judge(node, f"heartbeat confirms {nmt.name}")
        recovering = (NodeLifecycle.PREOP_HELD, NodeLifecycle.LEFT_OPERATIONAL)
        if moved and before is NodeLifecycle.OPERATIONAL and after in recovering:
            self.left(node)                 # it ran, and left by itself
        elif moved and after is NodeLifecycle.LEFT_OPERATIONAL:
            self.restate(node)              # a restart not taken: the next one
            self.arm_restart(node)
        elif was_lost and after is NodeLifecycle.LEFT_OPERATIONAL:
            self.arm_restart(node, at_once=True)    # the heartbeat is back: its cause cleared
        if after is NodeLifecycle.PREOP_HELD and (before is not after or moved):
            self.submit(ReportHeld(node.id, generation))

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
            expected = node.lifecycle.host_reset
            generation = node.lifecycle.booted()
            node.starting = False
            node.booting = True
            node.retry_at_host = None
        if expected:        # the host's nmt reset: a reboot asked for, not a fault
            reason = (f"{self.where(node)}: rebooted by the host's nmt reset (boot-up "
                      f"message): configuring it again")
            self.host.stat(self.bus, "host-resets")
        else:
            reason = f"{self.where(node)}: rebooted (boot-up message): configuring it again"
            self.host.error(self.bus, "boot-up", reason)
        self.fail_node(node, "lifecycle", reason)
        self.submit(BootNode(node.id, generation))

    def on_emcy(self, node: ManagedNode, entry: Any) -> None:
        text = f"{self.where(node)}: EMCY {entry} register 0x{entry.register:02X}"
        with node.lock:
            node.lifecycle.emcy(f"{entry} register 0x{entry.register:02X}")
        self.host.error(self.bus, "emcy", text)
        if node.axes:
            # a drive's fault is its axes' failure, judged from the statusword (failing the
            # node would refuse the fault reset and the statusword: the deadlock of issue 37);
            # a drive without the statusword in a TPDO tells it only this way: read it now
            self.refresh_axes(node)
        if is_error_reset(entry.code):
            self.clear_node(node, "emcy", f"canopen node {node.id}: error-reset EMCY")
            with node.lock:
                retry = node.lifecycle.cause_cleared()
            if retry:
                self.restate(node)
                self.arm_restart(node, at_once=True)
        elif is_fatal_emcy(entry.code) and not node.axes:
            # the drive's controlword stays writable: its fault reset is how it recovers
            self.fail_node(node, "emcy", text, keep=node.controlwords)

    def refresh_axes(self, node: ManagedNode) -> None:
        """Have every axis of ``node`` read its drive's objects by SDO now (statusword 0x6041,
        error code 0x603F...): an EMCY or a change of NMT state may be a fault that no TPDO
        brings."""
        for name in node.axes:
            self.submit(AxisRefresh(name))

    def report_frame(self, kind: str, detail: str) -> None:
        """A frame-level problem seen by the bus listener (see :class:`FrameCheck`)."""
        self.host.error(self.bus, kind, detail)

    def unknown_heartbeat(self, node_id: int, cob: int) -> None:
        """A heartbeat of node ``node_id``, which is not in the map: counted (``unknown-node``
        in the bus statistics, each frame), reported at once the first time and then once per
        :data:`REPORT_PERIOD` with the count."""
        self.host.stat(self.bus, "unknown-node-frames")
        self.unknown.add(f"{node_id}", f"0x{cob:03X}")

    def _report_unknown(self, node: str, n: int, examples: list[str]) -> None:
        cob = examples[0] if examples else "?"
        self.host.error(self.bus, "unknown-node",
                        f"{n} heartbeat(s) of node {node} (COB-ID {cob}) since the last "
                        f"report; the node is not in the bus's nodes")

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
            self._driver.unknown_heartbeat(hb, cob)
        elif emcy is not None and self._driver.knows_node(emcy) and msg.dlc < 8:
            self._driver.report_frame("malformed",
                                      f"EMCY from node {emcy} with {msg.dlc} bytes, "
                                      f"expected 8")

    def stop(self) -> None:
        """Nothing to release."""
