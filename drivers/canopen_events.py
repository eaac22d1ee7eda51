"""canopen_events - the receive side of the ``canopen`` driver (:mod:`drivers.canopen_node`):
the frames of its reader thread handed to canopen's listeners (SDO responses, PDOs, heartbeats,
EMCY), TPDO readings, the heartbeat watchdog of the nodes, EMCY failures and recoveries, and the
frames canopen would drop quietly. :class:`CanopenEvents` holds the driver's state; the life
cycle, the SDO polls and the writes are :class:`drivers.canopen_node.CanopenDriver`.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import can

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.base import DriverHost, deliver_all
from drivers.canopen_od import DEFAULT_POLL
from drivers.codecs.canopen import (
    emcy_node,
    heartbeat_node,
    is_error_reset,
    is_fatal_emcy,
)
from drivers.health import Health
from drivers.jobs import WorkerJobDriver

HEARTBEAT_SETTLE = 0.1
"""Bound (s) on handing over received frames before a heartbeat loss is declared (polling
interfaces; on SocketCAN the drain is immediate)."""


@dataclass
class Binding:
    """A device of the bus bound to its object: the node, index, subindex, the object's
    variable, the PDO variable that carries it (if any) and its SDO poll period."""

    device: DeviceSpec
    node: int
    index: int
    subindex: int
    od_var: Any
    pdo_var: Any = None        # TPDO variable (sensor) or RPDO variable (actuator), or None
    poll_period: float = DEFAULT_POLL


@dataclass
class NodeState:
    """A node of the bus: its canopen RemoteNode, heartbeat supervision and devices."""

    node: Any
    heartbeat_timeout: float | None
    nmt_start: bool
    last_heartbeat: float = field(default_factory=time.monotonic)
    lost: bool = False
    devices: list[str] = field(default_factory=list)


class CanopenEvents(WorkerJobDriver):
    """The state of a ``canopen`` driver and its receive side (see the module doc)."""

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._health = Health(host)
        self._hb_lock = threading.Lock()      # guards NodeState.last_heartbeat and .lost
        self._network: Any = None
        self._nodes: dict[int, NodeState] = {}
        self._bindings: dict[str, Binding] = {}
        self._pdo_sensors: dict[tuple[int, int, int], list[str]] = {}
        self._poll_groups: dict[float, list[Binding]] = {}   # SDO-polled sensors by period
        self._bus_failed = False
        #: whether any node has heartbeat supervision (set at start; the watchdog's fast exit)
        self._watched = False
        #: frames handed to canopen's listeners, written by whoever receives (the reader, or a
        #: settle's drain: one at a time, under the reader's lock); of which reported to the
        #: host as ``frames`` (:meth:`_tell_frames`, under ``_told_lock``)
        self._frames_in = 0
        self._frames_told = 0
        self._told_lock = threading.Lock()

    # -- I/O thread: the heartbeat watchdog -------------------------------------------------

    def _tick(self) -> float:
        """The worker's longest wait for a job: until the next heartbeat deadline. Before each
        job and at least every 0.5 s: the frames received meanwhile go to the bus statistics."""
        self._tell_frames()
        return self._watchdog() if self._watched else 0.5

    def _tell_frames(self) -> None:
        """Count the frames received since the last call in the host's ``frames`` statistic,
        as one addition (one per frame would cost the reader a locked call per frame)."""
        with self._told_lock:
            n = self._frames_in
            new, self._frames_told = n - self._frames_told, n
        if new:
            self.host.stat(self.bus.name, "frames", new)

    def settle(self, timeout: float) -> bool:
        """As :meth:`drivers.jobs.JobDriver.settle`; the frames handed over are counted in the
        bus statistics before it returns."""
        try:
            return super().settle(timeout)
        finally:
            self._tell_frames()

    def _watchdog(self) -> float:
        """Fail the devices of nodes whose heartbeat is overdue; the time to the next deadline.
        Before it declares a node lost it has the reader hand over every frame the operating
        system already holds: after this process was stalled (a loaded machine, a virtual one)
        the I/O thread may wake before the reader, and a heartbeat waiting in the socket is not a
        missing one."""
        now = time.monotonic()
        with self._hb_lock:
            overdue = any(s.heartbeat_timeout is not None and not s.lost
                          and now - s.last_heartbeat > s.heartbeat_timeout
                          for s in self._nodes.values())
        rx = self._rx
        if overdue and rx is not None:
            # a late heartbeat is not a dead node: first hand over every frame the OS already
            # received (this thread or the reader may simply have been starved of CPU)
            rx.settle(HEARTBEAT_SETTLE)
        wait = 0.5
        for nid, s in self._nodes.items():
            with self._hb_lock:
                if s.heartbeat_timeout is None or s.lost:
                    continue
                late = now - s.last_heartbeat
                s.lost = late > s.heartbeat_timeout
            if s.lost:
                reason = (f"canopen node {nid} on bus {self.bus.name}: no heartbeat for more than "
                          f"heartbeat_timeout {s.heartbeat_timeout} s")
                for dev in s.devices:
                    self._health.fail(dev, "heartbeat", reason)
            else:
                wait = min(wait, s.heartbeat_timeout - late + 0.001)
        return wait

    # -- reader thread ------------------------------------------------------------------------

    def _on_frame(self, frame: can.Message) -> None:
        """A received frame to canopen's listeners (what its notifier would do)."""
        self._bus_failed = False     # a receive error is reported again after a good frame
        self._frames_in += 1         # to the statistics in _tell_frames
        network = self._network
        if network is None:
            return
        for listener in network.listeners:
            try:
                listener.on_message_received(frame)
            except Exception as exc:  # the reader must survive any canopen/host surprise
                self.host.error(self.bus.name, "internal", f"frame handling failed: {exc!r}")

    def _on_bus_error(self, reason: str) -> None:
        if not self._bus_failed:
            self._bus_failed = True
            self.host.error(self.bus.name, "bus-error",
                            f"canopen bus {self.bus.name}: receive failed: {reason}")

    def _on_tpdo(self, pdo_map: Any) -> None:
        """A TPDO arrived (reader thread, or settle's drain: both under the reader's lock, so
        settle never returns while one is being delivered)."""
        nid = pdo_map.pdo_node.node.id
        if len(pdo_map.data) * 8 < pdo_map.length:
            self.host.error(self.bus.name, "malformed",
                            f"{pdo_map.name} from canopen node {nid}: {len(pdo_map.data)} "
                            f"bytes, expected {(pdo_map.length + 7) // 8}")
            return
        deliver_all(self.host, [(dev, var.raw) for var in pdo_map.map
                                for dev in self._pdo_sensors.get((nid, var.index, var.subindex),
                                                                 ())])

    def _on_heartbeat(self, state: NodeState, nmt_state: int) -> None:
        with self._hb_lock:
            state.last_heartbeat = time.monotonic()
            was_lost, state.lost = state.lost, False
        if was_lost:
            for dev in state.devices:
                self._health.clear(dev, "heartbeat", f"canopen node {state.node.id}: heartbeat "
                                                     f"back")
        if state.nmt_start and nmt_state in (0, 127):  # boot-up or PRE-OPERATIONAL
            self._submit("nmt", str(state.node.id))

    def _on_emcy(self, state: NodeState, entry: Any) -> None:
        nid = state.node.id
        text = f"canopen node {nid} on bus {self.bus.name}: EMCY {entry} register " \
               f"0x{entry.register:02X}"
        self.host.error(self.bus.name, "emcy", text)
        if is_error_reset(entry.code):
            for dev in state.devices:
                self._health.clear(dev, "emcy", f"canopen node {nid}: error-reset EMCY")
        elif is_fatal_emcy(entry.code):
            for dev in state.devices:
                self._health.fail(dev, "emcy", text)

    def report_frame(self, kind: str, detail: str) -> None:
        """A frame-level problem seen by the bus listener (see :class:`FrameCheck`)."""
        self.host.error(self.bus.name, kind, detail)

    def knows_node(self, node_id: int) -> bool:
        """True if ``node_id`` is one of this bus's nodes."""
        return node_id in self._nodes


class FrameCheck(can.Listener):
    """Reports frames canopen would drop quietly: heartbeats of unknown nodes, short EMCYs."""

    def __init__(self, driver: CanopenEvents) -> None:
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
