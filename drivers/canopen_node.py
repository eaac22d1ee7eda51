"""canopen_node - the ``canopen`` bus driver: remote CANopen nodes through the canopen library.

Bus options (``[[bus]] kind = "canopen"``):

* ``interface``, ``channel``, ``bitrate`` - the python-can bus; any left out comes from python-can's
  own configuration (``can.util.load_config``: ``CAN_INTERFACE``, ``CAN_CHANNEL``, config files).
  ``port``: the UDP port of interface ``udp_multicast`` (``channel`` is its multicast group; a bus
  shared by processes on any machine, e.g. ``chcos sim --from`` beside ``chcos run``).
* ``nodes = [{id, eds, heartbeat_timeout, nmt_start, identity, config, store_config,
  restart_limit, restart_backoff}]`` - node id 1..127, the node's EDS file (absolute, or
  relative to the device-map file), heartbeat timeout in seconds (optional: no heartbeat
  supervision), whether the driver puts the node OPERATIONAL (default true), the identity 0x1018
  it must have, the configuration downloaded at each boot and whether it is then stored in the
  node (0x1010; :mod:`drivers.canopen_config`), and its recovery policy (default 5 restarts,
  the first 1 s after it left OPERATIONAL, doubling:
  :class:`drivers.canopen_lifecycle.RestartPolicy`).
* ``sync_period`` (s, optional) - produce SYNC at this period (on SocketCAN from a producer
  process of the driver's own: :mod:`drivers.canopen_sync`); ``sync_priority`` (0..99, default
  80) - the SCHED_FIFO priority of the producer processes (0: SCHED_OTHER; without the right to
  set it, they stay SCHED_OTHER and the bus reports it once); ``poll_period`` (s, default 0.1)
  - default SDO polling period; ``sdo_timeout`` (s, default 0.3) - SDO response timeout.
* ``master_heartbeat_ms`` (optional) - produce the master's heartbeat (COB-ID 0x700 +
  ``master_node_id``, default 127, state OPERATIONAL) at this period, so that nodes with a
  heartbeat consumer (0x1016) notice a dead or frozen controller; ``liveness_ms`` (default
  1000; 0: off) - the master heartbeat and SYNC stop when the controller's kernel completed no
  scheduling round for this long (:mod:`drivers.canopen_heartbeat`).
* ``poll`` (s, default 0.005) - the receive timeout of the driver's reader on interfaces it cannot
  wait on without receiving; it bounds :meth:`CanopenDriver.settle` there. Not used on SocketCAN
  or python-can's ``virtual`` interface (see :func:`drivers.canbus.read_frames`).

Each node is a :class:`drivers.canopen_remote.ManagedNode` with a lifecycle
(:mod:`drivers.canopen_lifecycle`): at start and after every boot-up message the I/O thread checks
its identity, reads its error register 0x1001, downloads its configuration (every write read
back), sends one NMT start, and its devices are OK once its heartbeat confirms OPERATIONAL
(:meth:`CanopenDriver.node_states` shows where each node is). A node that leaves OPERATIONAL by
itself is started again by its recovery policy once its cause cleared (a :class:`RestartNode`
job reads 0x1001 first); :meth:`CanopenDriver.nmt` is the host's NMT command. A command queued
before a node's boot-up is not sent (its configuration, NMT start and safe value come first).
The kernel receives only the nodes' COB-IDs (``can_filters``: heartbeats, EMCY, SDO answers,
TPDOs).

Frames are received by the driver's own reader thread (:func:`drivers.canbus.read_frames`), not
by canopen's notifier, and handed to canopen's listeners (SDO responses, PDOs, heartbeats, EMCY),
so that :meth:`CanopenDriver.settle` can promise that every frame that arrived before it has been
handled: virtual-time runs are deterministic on CANopen too.

Device address: ``{node, index, subindex = 0, poll_period}``. A sensor whose object is mapped in an
enabled TPDO of the node (as configured, else as in its EDS) is delivered from the PDO callback;
any other sensor is read by SDO every ``poll_period``, paced by the polls as in
:mod:`drivers.jobs`. An actuator write goes in the RPDO that maps the object (composed from the
current value of every object it maps: :class:`drivers.canopen_remote.RpdoImages`), else by SDO
download. An SDO write that aborts or times out fails the actuator; the driver then probes the
object by SDO upload until the node answers and the failure clears (no latch).

CiA 402 axes (``profile = "cia402"`` device-map tables, :mod:`drivers.canopen_axis`): the driver
hosts one :class:`drivers.codecs.cia402.Axis` engine per axis on its I/O thread: the TPDO values of
the axis's objects are fed in as one reading, the engine is cycled every :data:`AXIS_CYCLE` s, each
write it asks for goes out as its own frame (the first RPDO mapping the object, composed from the
node's image, else an SDO download), its reads are SDO uploads, its results complete the task's call
(:meth:`CanopenDriver.axis_call`) or the Devtab write of a command code, and a drive fault fails the
axis's actuator alone (cause ``drive-fault``). On a node hosting an axis, EMCY and the error
register at boot do not fail the node's devices (the fault reset must get through). A node lost or
rebooted makes each of its axes forget the drive and start its safe stop.
:meth:`CanopenDriver.flush` keeps cycling the axes at shutdown until their safe stops ended.

Failures are listed in :mod:`drivers.canopen_events`. Every EMCY is reported through
``host.error(bus, "emcy", ...)``; EMCY codes of the classes current (2xxx), voltage (3xxx),
temperature (4xxx), device hardware (50xx) and monitoring (8xxx) are fatal: they fail the node's
devices (but a CiA 402 drive's controlword in a plain map: the fault reset must get through)
until an error-reset EMCY (code 0000) or a boot that reads 0x1001 clear. Other ``host.error``
kinds: ``boot-up`` (a node rebooted; not for the host's ``nmt reset``), ``identity``,
``config``, ``left-operational``, ``preop-held``, ``controller-stalled`` (the master heartbeat
or SYNC held: the controller made no progress), ``sdo-abort``, ``timeout``, ``malformed``,
``unknown-node`` (once per node per 10 s, with the count).
"""

from __future__ import annotations

import contextlib
import functools
import logging
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from chcos.devices import parsecache
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from drivers import canopen_config
from drivers.base import DriverHost, deliver_all, host_clock_virtual, host_peers_on_clock
from drivers.canbus import read_frames
from drivers.canopen_axis import (
    CODE_OPS,
    AxisCall,
    AxisCode,
    AxisHost,
    AxisStatus,
    Done,
    device_write,
)
from drivers.canopen_events import FrameCheck, NodeEvents
from drivers.canopen_heartbeat import (
    ClockedHeartbeat,
    HeartbeatThread,
    Liveness,
    LivenessFeed,
    is_hold,
    is_resume,
)
from drivers.canopen_jobs import (
    AxisCommand,
    AxisCycle,
    AxisFeed,
    AxisLost,
    AxisRefresh,
    BootNode,
    CanopenJob,
    Probe,
    ReportHeld,
    RestartNode,
)
from drivers.canopen_lifecycle import Lifecycle, NmtCommand, NodeLifecycle, NodeStatus
from drivers.canopen_nmt import NmtMaster
from drivers.canopen_od import (
    DEFAULT_MASTER_ID,
    DEFAULT_POLL,
    accepted,
    check_bus,
    check_device,
    check_warnings,
    coerce,
    encodable,
    is_controlword,
    liveness,
    load_od,
    restart_policy,
    value_error,
)
from drivers.canopen_remote import BootOutcome, ManagedNode, RpdoImages, use_object_sdo_client
from drivers.canopen_sync import (
    DEFAULT_SYNC_PRIORITY,
    SYNC_COB_ID,
    ClockedSyncProducer,
    HeartbeatProducerProcess,
    ProducerProcess,
    SyncCycle,
    SyncProducerProcess,
    SyncStats,
)
from drivers.codecs.canopen import EMCY_BASE, HEARTBEAT_BASE
from drivers.codecs.cia402 import Obj, Write, config_from_table, mode_of
from drivers.jobs import Job, JobOp, WorkerJobDriver
from drivers.threaded import ReaderThread

log = logging.getLogger(__name__)

DEFAULT_SDO_TIMEOUT = 0.3
#: The reader's default receive timeout on interfaces without a file descriptor.
DEFAULT_RX_POLL = 0.005
SDO_TX_BASE = 0x580   # SDO server -> client: COB-ID 0x580 + node id
#: lifecycle states in which a node is known not to be OPERATIONAL: an RPDO to it is sent (a
#: safe value goes out whatever the state) but not reported written
IGNORES_RPDOS = (NodeLifecycle.PREOP_HELD, NodeLifecycle.FAILED, NodeLifecycle.WAITING_BOOT,
                 NodeLifecycle.LEFT_OPERATIONAL, NodeLifecycle.HOST_HELD)
#: seconds between two cycles of the axes' engines (timeouts, the fault reset's edge, resends)
AXIS_CYCLE = 0.01


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


def node_filters(nodes: dict[int, ManagedNode]) -> list[dict[str, int]]:
    """python-can ``can_filters`` (kernel filters on SocketCAN) for the frames the driver needs:
    every heartbeat (0x700..0x77F: unknown nodes are reported), and each node's EMCY, SDO
    answers and enabled TPDOs."""
    out = [{"can_id": HEARTBEAT_BASE, "can_mask": 0x780}]
    for nid, node in nodes.items():
        ids = {EMCY_BASE + nid, SDO_TX_BASE + nid}
        ids.update(m.cob_id for m in node.remote.tpdo.map.values() if m.enabled and m.cob_id)
        out.extend({"can_id": cob, "can_mask": 0x7FF} for cob in sorted(ids))
    return out


def apply_pdo_config(remote: Any, cfg: canopen_config.NodeConfig) -> None:
    """The driver's view of the node's PDOs (canopen's PDO maps, read from the EDS) changed to
    what ``cfg`` downloads: COB-IDs, enabled, transmission types, mappings."""
    for p in cfg.pdos:
        maps = remote.rpdo.map if p.kind == "rpdo" else remote.tpdo.map
        pdo_map = maps[p.number]
        if p.kind == "tpdo" and pdo_map.enabled and pdo_map.cob_id:
            with contextlib.suppress(Exception):
                remote.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)
        pdo_map.cob_id = canopen_config.effective_cob_id(p, remote.object_dictionary, remote.id)
        pdo_map.enabled = p.enabled
        if p.transmission_type is not None:
            pdo_map.trans_type = p.transmission_type
        if p.mapping is not None:
            pdo_map.clear()
            for index, sub, bits in p.mapping:
                pdo_map.add_variable(index, sub, bits)
        if p.kind == "tpdo":
            pdo_map.subscribe()


class CanopenDriver(WorkerJobDriver):
    """The ``canopen`` bus: see the module doc for options, addresses and failure handling."""

    kind = "canopen"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        #: the nodes and what happens to them (the receive side, heartbeats, EMCY, SYNC)
        self._events = NodeEvents(bus.name, host, self._submit_job)
        self._nodes = self._events.nodes
        #: the NMT master's own commands: the recovery policy's restarts, the host's commands
        self._master = NmtMaster(self._events)
        self._bindings: dict[str, Binding] = {}
        self._poll_groups: dict[float, list[Binding]] = {}   # SDO-polled sensors by period
        self._master_task: HeartbeatProducerProcess | HeartbeatThread | ClockedHeartbeat | \
            None = None
        self._sync_task: SyncProducerProcess | ClockedSyncProducer | None = None
        #: the controller's liveness (:mod:`drivers.canopen_heartbeat`): what the master
        #: heartbeat and SYNC go out under, and the thread that feeds the producer processes
        self._liveness: Liveness | None = None
        self._feed: LivenessFeed | None = None
        #: the CiA 402 axes hosted, by actuator name (:mod:`drivers.canopen_axis`); their
        #: engines are used by the I/O thread only
        self._axes: dict[str, AxisHost] = {}
        #: nodes hosting axes that are down (their axes told once), under ``_down_lock``
        self._down: set[int] = set()
        self._down_lock = threading.Lock()
        #: the SYNC cycle the writing task answers (see :meth:`watch_cycles`), and per actuator
        #: the cycle each queued RPDO write answers (None: not an answer)
        self._responding: Callable[[], int | None] | None = None
        #: (the cycle it answers, the node's boot generation when it was queued)
        self._answers: dict[str, deque[tuple[int | None, int]]] = {}
        self._answers_lock = threading.Lock()
        self._late_writes = 0

    def _submit_job(self, job: CanopenJob) -> bool:
        return self._submit(JobOp.OWN, job)

    # -- what the driver shows ----------------------------------------------------------------

    def node_states(self) -> dict[int, NodeStatus]:
        """Each node's lifecycle status by node id (:class:`NodeStatus`). Thread-safe."""
        return self._events.node_states()

    def sync_stats(self) -> SyncStats | None:
        """The SYNC cycle's counters and jitter (None without ``sync_period``)."""
        return self._events.sync_stats()

    def wait_cycle(self, n: int, timeout: float) -> bool:
        """Wait until SYNC cycle ``n`` is complete: every synchronous TPDO due in it arrived
        (True), or SYNC n+1 went out first or ``timeout`` passed (False; also without SYNC)."""
        return self._events.wait_cycle(n, timeout)

    def status_doc(self) -> dict[str, Any]:
        """Each node's lifecycle (``nodes``: state name, ready, confirmed, NMT state of its
        last heartbeat, boot-ups seen, NMT starts sent, heartbeat losses, EMCYs received,
        configurations stored (``store_config``), 0x1001, last EMCY, the reason it is not
        ready, whether its heartbeat is lost now, restarts of its recovery policy since its
        last boot) and the SYNC cycle's counters and jitter
        (``sync``, while it runs; with ``late_writes``: RPDO answers to cycle n that went out
        after SYNC n+1). Thread-safe."""
        nodes = [{"node": st.node, "state": st.lifecycle.name, "ready": st.ready,
                  "confirmed": st.confirmed, "nmt": None if st.nmt is None else st.nmt.name,
                  "boots": st.boots, "nmt_starts": st.nmt_starts,
                  "heartbeat_losses": st.heartbeat_losses, "emcys": st.emcys,
                  "config_stores": st.stores,
                  "error_register": st.error_register, "last_emcy": st.last_emcy,
                  "reason": st.reason, "heartbeat_lost": st.heartbeat_lost,
                  "restarts": st.restarts}
                 for nid, st in sorted(self.node_states().items())]
        doc: dict[str, Any] = {"nodes": nodes}
        stats = self.sync_stats()
        if stats is not None:
            doc["sync"] = {**asdict(stats), "late_writes": self._late_writes}
        return doc

    def watch_cycles(self, fn: Callable[[int, bool], None],
                     responding: Callable[[], int | None]) -> Callable[[], None]:
        """Call ``fn(n, complete)`` once per SYNC cycle as soon as its outcome is known
        (:meth:`drivers.canopen_sync.SyncCycle.watch`; on a driver thread: ``fn`` must not
        block). ``responding()``, asked on the kernel thread when an actuator write is made,
        names the cycle the writing task answers (None: none): an RPDO carrying it that goes
        out after SYNC n+1 is counted late (``sync-late-writes``). Returns the function that
        ends the watch. Raises BusError if the bus has no SYNC cycle (no ``sync_period``, or
        the driver is not running)."""
        sync = self._events.sync
        if sync is None:
            raise BusError(f"canopen bus {self.bus.name} ({self.bus.file}): no SYNC cycle to "
                           f"wait for: the bus has no sync_period, or is not running")
        self._responding = responding
        return sync.watch(fn)

    def _write(self, device: str, value: Any) -> None:
        """Queue the write (as :meth:`drivers.jobs.JobDriver._write`), remembering the SYNC
        cycle it answers if it goes in an RPDO and a task waiting for cycles made it."""
        responding = self._responding
        b = self._bindings.get(device)
        tag = responding() if responding is not None and b is not None and b.pdo_var else None
        generation = self._nodes[b.node].lifecycle.generation if b is not None else 0
        with self._answers_lock:
            self._answers.setdefault(device, deque()).append((tag, generation))
        if not self._submit(JobOp.WRITE, device, value):
            with self._answers_lock:
                self._answers[device].pop()
            self._refuse(device, value, "stopped", f"{self.kind} bus {self.bus.name} is not "
                                                   f"running")

    def _answered(self, device: str) -> tuple[int | None, int | None]:
        """The cycle the write of ``device`` now taken by the I/O thread answers (None: none),
        and the boot generation of its node when it was queued (None: not known)."""
        with self._answers_lock:
            q = self._answers.get(device)
            return q.popleft() if q else (None, None)

    def _tick(self) -> float:
        """The worker's longest wait for a job; the frames received meanwhile go to the bus
        statistics before each job and at least every 0.5 s."""
        self._events.tell_frames()
        return 0.5

    def settle(self, timeout: float) -> bool:
        """As :meth:`drivers.jobs.JobDriver.settle`; the frames handed over are counted in the
        bus statistics before it returns."""
        try:
            return super().settle(timeout)
        finally:
            self._events.tell_frames()

    # -- validation (drivers.canopen_od) -----------------------------------------------------

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of the bus options (unknown keys, types, node ids, unreadable EDS files, the
        nodes' identity and configuration, PDO mappings against the EDS)."""
        return check_bus(bus)

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """Errors of a device address: keys, node on this bus, object present in the node's EDS,
        readable for a sensor and writable for an actuator."""
        return check_device(bus, device)

    @classmethod
    def check_warnings(cls, bus: BusSpec, devices: Sequence[DeviceSpec]) -> list[str]:
        """What is legal but bound to misbehave: the device's timing (synchronous RPDOs or
        TPDOs never sent without SYNC, consumer times shorter than the producer's period plus
        its jitter) and CiA 402 axes whose statusword no TPDO carries
        (:func:`drivers.canopen_od.check_warnings`)."""
        return check_warnings(bus, devices)

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of the object's data type in the node's EDS: 0..1 for BOOLEAN, the
        INTEGERn/UNSIGNEDn ranges, the largest REAL32; None for REAL64 and other types."""
        return encodable(bus, device)

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Validate, open the CAN bus, bind devices to PDOs or SDO polling, start the I/O,
        reader and watchdog threads and the master heartbeat, and queue each node's boot
        procedure. Raises :class:`BusError` (invalid options included)."""
        with parsecache.scope():   # each EDS parsed once for the checks, not once per device
            errs = self.check_bus(self.bus)
            for dev in self.devices.values():
                errs.extend(self.check_device(self.bus, dev))
        if errs:
            raise BusError(f"canopen bus {self.bus.name} ({self.bus.file}): " + "; ".join(errs))
        network: Any = canopen.Network()
        network.listeners.append(FrameCheck(self._events))
        opts = self.bus.options
        self._events.master_id = int(opts.get("master_node_id", DEFAULT_MASTER_ID))
        for ncfg in opts["nodes"]:
            nid = int(ncfg["id"])
            remote: Any = canopen.RemoteNode(nid, load_od(self.bus, nid, ncfg["eds"]))
            use_object_sdo_client(remote)
            remote.sdo.RESPONSE_TIMEOUT = float(opts.get("sdo_timeout", DEFAULT_SDO_TIMEOUT))
            network.add_node(remote)
            remote.tpdo.read(from_od=True)
            remote.rpdo.read(from_od=True)
            cfg = canopen_config.with_bits(canopen_config.parse(ncfg), remote.object_dictionary)
            apply_pdo_config(remote, cfg)
            for pdo_map in remote.tpdo.map.values():
                pdo_map.add_callback(self._events.on_tpdo)
            hb = ncfg.get("heartbeat_timeout")
            self._nodes[nid] = ManagedNode(
                remote, cfg, float(hb) if hb is not None else None,
                Lifecycle(nid, bool(ncfg.get("nmt_start", True)), hb is not None,
                          restart_policy(ncfg)),
                RpdoImages(remote))
        self._events.network = network
        self._bind_devices()
        if self._axes:
            self._events.axis_feed = self._axis_feed
            self._events.node_down = self._axis_node_down
            self._events.node_up = self._axis_node_up
        config = {k: opts[k] for k in ("interface", "channel", "bitrate", "port") if k in opts}
        try:
            cfg_bus = dict(can.util.load_config(config=config))
            if "bitrate" not in cfg_bus:   # as canopen's connect(): the first EDS naming one
                rates = [n.remote.object_dictionary.bitrate for n in self._nodes.values()]
                if any(rates):
                    cfg_bus["bitrate"] = next(r for r in rates if r)
            # on SocketCAN producer processes send SYNC and the master heartbeat; the reader
            # sees each SYNC
            self._events.observe = cfg_bus.get("interface") == "socketcan"
            self._events.observe_sync = "sync_period" in opts and self._events.observe
            filters = node_filters(self._nodes)
            if self._events.observe_sync:
                filters.append({"can_id": SYNC_COB_ID, "can_mask": 0x7FF})
            bus = can.Bus(**cfg_bus, can_filters=filters)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"canopen bus {self.bus.name} ({self.bus.file} {self.bus.key}): cannot "
                           f"open CAN bus {config or 'from python-can config'}: {exc}") from exc
        network.bus = bus
        poll = float(opts.get("poll", DEFAULT_RX_POLL))
        rx = self._rx = ReaderThread(
            lambda: read_frames(rx, bus, poll, self._events.on_frame, self._events.on_bus_error),
            f"canopen-{self.bus.name}-rx")
        rx.start()
        self._events.rx = rx
        for node in self._nodes.values():
            node.remote.nmt.add_heartbeat_callback(
                lambda code, n=node: self._events.on_heartbeat(n, code))
            node.remote.emcy.add_callback(lambda entry, n=node: self._events.on_emcy(n, entry))
        boots = []
        for node in self._nodes.values():      # before any write: they count from this boot
            with node.lock:
                boots.append(BootNode(node.id, node.lifecycle.restart(
                    "driver started: identity, configuration and NMT start under way")))
                node.booting = True
        self._running = True
        self._events.running = True
        self._start_worker()
        self._events.start_watchdog()
        for boot in boots:
            self._submit(JobOp.OWN, boot)
        self._liveness = Liveness(self.host, liveness(self.bus))
        if "master_heartbeat_ms" in opts:
            self._start_master_heartbeat(bus, int(opts["master_heartbeat_ms"]))
        if "sync_period" in opts:
            self._start_sync(bus, float(opts["sync_period"]))
        groups: dict[float, list[Binding]] = {}
        for b in self._bindings.values():
            if b.device.direction == "sensor" and b.pdo_var is None:
                groups.setdefault(b.poll_period, []).append(b)
        # one timer and one job per poll period (not per object): the objects of a period are
        # uploaded one after the other in one job, as the single SDO channel of a node would
        # anyway; each reports its own failure
        self._poll_groups = groups
        for period in groups:
            self._poll_every(period, period)
        if self._axes:
            self._poll_every(AxisCycle(), AXIS_CYCLE)

    def _on_clock(self) -> bool:
        """True in a virtual cell: a virtual clock, the nodes simulated on it."""
        return bool(host_clock_virtual(self.host)) and host_peers_on_clock(self.host)

    def _producer_report(self, text: str) -> None:
        """A report of a producer (master heartbeat, SYNC): a hold by the liveness gate is a
        ``controller-stalled`` error of the bus, its end a log line, anything else a ``can``
        error."""
        where = f"canopen bus {self.bus.name}: {text}"
        if is_hold(text):
            self.host.error(self.bus.name, "controller-stalled", where)
        elif is_resume(text):
            log.warning("%s", where)
        else:
            self.host.error(self.bus.name, "can", where)

    def _start_master_heartbeat(self, bus: can.BusABC, period_ms: int) -> None:
        """The master's heartbeat (state OPERATIONAL) every ``period_ms``, while the controller
        is alive (:mod:`drivers.canopen_heartbeat`): on SocketCAN from a producer process of
        its own (``SCHED_FIFO`` at ``sync_priority``, fed by the liveness thread); in a virtual
        cell on the kernel's timers; else from a thread of the driver."""
        node = self._events.master_id
        msg = can.Message(arbitration_id=HEARTBEAT_BASE + node, data=b"\x05",
                          is_extended_id=False)
        assert self._liveness is not None
        period = period_ms / 1000.0

        def send() -> None:
            bus.send(msg)

        task: HeartbeatProducerProcess | HeartbeatThread | ClockedHeartbeat
        if self._events.observe:
            task = HeartbeatProducerProcess(
                str(getattr(bus, "channel", "")), period, node, self._producer_report,
                f"canopen-{self.bus.name}-heartbeat",
                int(self.bus.options.get("sync_priority", DEFAULT_SYNC_PRIORITY)),
                self._liveness.bound)
            try:
                task.start()
            except OSError as exc:
                self.host.error(self.bus.name, "can", f"canopen bus {self.bus.name}: cannot "
                                                      f"start the master heartbeat: {exc}")
                return
            self._feed_producer(task)
        elif self._on_clock():
            task = ClockedHeartbeat(send, period, self.host, self._producer_report)
            task.start()
        else:
            task = HeartbeatThread(send, period, self._liveness, self._producer_report,
                                   f"canopen-{self.bus.name}-heartbeat")
            task.start()
        self._master_task = task

    def _feed_producer(self, producer: ProducerProcess) -> None:
        """Have the liveness thread feed ``producer`` (a process just started), the thread
        started with the first one (none with ``liveness_ms = 0``)."""
        live = self._liveness
        if live is None or live.bound <= 0:
            return
        if self._feed is None:
            self._feed = LivenessFeed(live, [], f"canopen-{self.bus.name}-liveness")
            self._feed.start()
        self._feed.add(producer.feed)

    def _start_sync(self, bus: can.BusABC, period: float) -> None:
        """The SYNC producer and the cycle's books (:mod:`drivers.canopen_sync`), expecting the
        nodes' synchronous TPDOs: on SocketCAN a producer process of its own (each SYNC
        observed by the reader, :class:`drivers.canopen_sync.SyncProducerProcess`); on a
        virtual clock with the nodes simulated on it, the kernel's timers
        (:class:`drivers.canopen_sync.ClockedSyncProducer`: deterministic); else a thread."""
        frame = can.Message(arbitration_id=SYNC_COB_ID, data=b"", is_extended_id=False)

        def send() -> None:
            bus.send(frame)

        error = self._producer_report
        live = self._liveness
        assert live is not None
        sync = SyncCycle(period, send, error, f"canopen-{self.bus.name}-sync",
                         live.alive if live.gated else None)
        sync.liveness = live.bound
        for node in self._nodes.values():
            for m in node.remote.tpdo.map.values():
                if m.enabled and m.cob_id and m.trans_type is not None:
                    sync.expect(m.cob_id, int(m.trans_type))
        self._events.sync = sync
        if self._events.observe_sync:
            producer = SyncProducerProcess(
                str(getattr(bus, "channel", "")), period, error, f"canopen-{self.bus.name}-sync",
                int(self.bus.options.get("sync_priority", DEFAULT_SYNC_PRIORITY)), live.bound,
                sync.gave_up)
            try:
                producer.start()
            except OSError as exc:
                error(f"cannot start the SYNC producer: {exc}")
            else:
                self._sync_task = producer
                self._feed_producer(producer)
            sync.start(produce=False)
        elif self._on_clock():
            clocked = ClockedSyncProducer(sync, self.host.now, self.host.at)
            clocked.start()
            self._sync_task = clocked
        else:
            sync.start()

    def _bind_devices(self) -> None:
        default_poll = float(self.bus.options.get("poll_period", DEFAULT_POLL))
        for dev in self.devices.values():
            a = dev.address
            if a.get("profile") == "cia402":
                self._bind_axis_device(dev)
                continue
            nid, index, sub = int(a["node"]), int(a["index"]), int(a.get("subindex", 0))
            node = self._nodes[nid].remote
            maps = node.tpdo.map if dev.direction == "sensor" else node.rpdo.map
            pdo_var = next((v for m in maps.values() if m.enabled for v in m.map
                            if v.index == index and v.subindex == sub), None)
            self._bindings[dev.name] = Binding(
                dev, nid, index, sub, node.object_dictionary.get_variable(index, sub), pdo_var,
                float(a.get("poll_period", default_poll)))
            self._nodes[nid].devices.append(dev.name)
            if dev.direction == "actuator" and is_controlword(node.object_dictionary, index,
                                                              sub):
                self._nodes[nid].controlwords += (dev.name,)
            if dev.direction == "sensor" and pdo_var is not None:
                self._events.pdo_sensors.setdefault((nid, index, sub), []).append(dev.name)

    def _bind_axis_device(self, dev: DeviceSpec) -> None:
        """A device of a CiA 402 axis table: the actuator gets its engine; every one of them
        fails with the node (lifecycle, heartbeat), not with the drive's faults."""
        a = dev.address
        node = self._nodes[int(a["node"])]
        node.devices.append(dev.name)
        if dev.direction != "actuator":
            return
        cfg = config_from_table(dev.name, {"axis": int(a.get("axis", 0)),
                                           **dict(a.get("config", {}))}, dev.key)
        name = dev.name
        self._axes[name] = AxisHost(
            name, node.id, cfg, mode_of(a.get("mode")),
            send=functools.partial(self._axis_send, node),
            read=functools.partial(self._axis_read, node),
            deliver=functools.partial(deliver_all, self.host),
            fail=self._axis_fault,
            recover=self._axis_fault_ended,
            report=functools.partial(self._axis_report, name))
        node.axes.append(name)

    # -- axes (drivers.canopen_axis) ----------------------------------------------------------

    def axis_call(self, device: str, call: AxisCall, done: Done) -> None:
        """Start ``call`` on axis ``device`` on the I/O thread; ``done`` gets the engine's
        :class:`drivers.codecs.cia402.Result` (from the I/O thread), or the exception that
        refused it (AxisBusy, AxisLimitError, ValueError; BusError when the driver is stopped).
        Never blocks."""
        if device not in self._axes:
            done(BusError(f"canopen bus {self.bus.name}: no axis {device!r}"))
            return
        if not self._submit(JobOp.OWN, AxisCommand(device, call, done)):
            done(BusError(f"canopen bus {self.bus.name} is not running: {call.op.value} of "
                          f"axis {device} not sent"))

    def axis_status(self, device: str) -> AxisStatus:
        """What axis ``device``'s drive last confirmed (any thread). Raises KeyError for a
        device that is no axis of this bus."""
        return self._axes[device].status()

    def _axis_feed(self, nid: int, values: list[tuple[int, int, int]]) -> None:
        """A TPDO of a node hosting axes (reader thread): each axis's objects in it, as one
        reading, to the I/O thread."""
        for host in self._nodes[nid].axes:
            objs = self._axes[host].objects()
            mine = tuple((objs[(i, s)], v) for i, s, v in values if (i, s) in objs)
            if mine:
                # marked on arrival: it may wait in the queue behind newer SDO answers
                mark = self._axes[host].pdo_received(tuple(o for o, _v in mine))
                self._submit(JobOp.OWN, AxisFeed(host, mine, mark))

    def _axis_node_down(self, node: ManagedNode, reason: str) -> None:
        with self._down_lock:
            if node.id in self._down:
                return
            self._down.add(node.id)
        for name in node.axes:
            self._submit(JobOp.OWN, AxisLost(name, reason))

    def _axis_node_up(self, node: ManagedNode) -> None:
        with self._down_lock:
            self._down.discard(node.id)
        for name in node.axes:
            self._submit(JobOp.OWN, AxisRefresh(name))

    def _axis_send(self, node: ManagedNode, w: Write) -> None:
        """One write of an axis as its own frame: the first RPDO mapping the object, composed
        from the node's image, else an SDO download. Raises on failure (the engine resends)."""
        var = node.remote.object_dictionary.get_variable(w.index, 0)
        if var is None:
            raise ValueError(f"node {node.id}'s EDS has no 0x{w.index:04X}")
        data = bytes(var.encode_raw(coerce(var, w.value)))
        pdos = node.images.pdos_of(w.index, 0)
        if pdos:
            node.images.set(w.index, 0, data)
            pdos[0].transmit()
            self.sent_frames[self._axis_device(node, w)] += 1
            return
        node.remote.sdo.download(w.index, 0, data)

    def _axis_device(self, node: ManagedNode, w: Write) -> str:
        for name in node.axes:
            if self._axes[name].config.index(w.obj) == w.index:
                return name
        return node.axes[0]

    def _axis_fault(self, device: str, reason: str) -> None:
        self._events.health.fail(device, "drive-fault", reason)

    def _axis_fault_ended(self, device: str, why: str) -> None:
        self._events.health.clear(device, "drive-fault", why)

    def _axis_report(self, device: str, text: str) -> None:
        self.host.error(self.bus.name, "axis", text, device)

    def _axis_read(self, node: ManagedNode, obj: Obj, index: int) -> int | None:
        """An axis object read by SDO; None if the drive does not answer or refuses."""
        var = node.remote.object_dictionary.get_variable(index, 0)
        try:
            data = node.remote.sdo.upload(index, 0)
            return int(var.decode_raw(data)) if var is not None else \
                int.from_bytes(data, "little")
        except (SdoAbortedError, SdoCommunicationError, struct.error, ValueError):
            return None

    def _axis_job(self, job: AxisFeed | AxisCommand | AxisLost | AxisRefresh) -> None:
        now = self.host.now()
        match job:
            case AxisFeed(device, values, received):
                self._axes[device].reading({Obj(o): v for o, v in values}, now, received)
            case AxisCommand(device, call, done):
                self._axes[device].command(call, done, now)
            case AxisRefresh(device):
                self._axes[device].refresh(now)
            case AxisLost(device, reason):
                axis = self._axes[device]
                axis.lost(reason, now)
                axis.command(AxisCall(CODE_OPS[AxisCode.SAFE_STOP]), None, now)

    def _guarded(self, fn: Callable[..., None], *args: Any) -> None:
        """Axis work on the I/O thread: a surprise is reported, and the thread goes on."""
        try:
            fn(*args)
        except can.CanError:
            raise
        except Exception as exc:
            self.host.error(self.bus.name, "internal", f"axis work failed: {exc!r}")

    def _axis_poll(self) -> None:
        now = self.host.now()
        for axis in self._axes.values():
            axis.poll(now)

    def _axis_write(self, device: str, value: Any) -> None:
        """A Devtab write to an axis's actuator (:func:`drivers.canopen_axis.device_write`)."""
        device_write(self._axes[device], self.host, device, value)

    def flush(self, timeout: float) -> bool:
        """As :meth:`drivers.jobs.JobDriver.flush`, and then, while an axis runs a command (the
        safe stop at shutdown), keep cycling its engine until it ended or ``timeout`` passed:
        the kernel's timers no longer run at shutdown, and Devtab's safe outcome of an axis is
        the drive's confirmation."""
        deadline = time.monotonic() + timeout
        ok = super().flush(timeout)
        while self._axes and any(a.status().busy is not None for a in self._axes.values()):
            if time.monotonic() >= deadline or not self._running:
                return False
            self._submit(JobOp.OWN, AxisCycle())
            super().flush(max(0.0, deadline - time.monotonic()))
            time.sleep(AXIS_CYCLE)      # the drive's next statusword (real time at shutdown)
        return ok

    def stop(self) -> None:
        """Put every queued write on the wire (safe values at shutdown), then stop the master
        heartbeat, SYNC, the threads and the bus. Idempotent; never raises."""
        self._running = False
        self._events.running = False
        self._stop_worker()     # runs every job queued before: they go out first
        self._events.stop_watchdog()
        self._events.unknown.flush()
        feed, self._feed = self._feed, None
        if feed is not None:
            feed.stop()
        sync_task, self._sync_task = self._sync_task, None
        if sync_task is not None:
            with contextlib.suppress(Exception):
                sync_task.stop()
        sync, self._events.sync = self._events.sync, None
        if sync is not None:
            sync.stop()
        task, self._master_task = self._master_task, None
        if task is not None:
            with contextlib.suppress(Exception):
                task.stop()
        rx, self._rx = self._rx, None
        if rx is not None:
            rx.stop()
        self._events.tell_frames()
        network, self._events.network = self._events.network, None
        if network is not None:
            with contextlib.suppress(Exception):
                network.disconnect()

    # -- kernel side --------------------------------------------------------------------------

    def check_value(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for ``device``'s object (None if it can): not a
        finite number, a fraction for an integer object, outside the data type's range."""
        if device in self._axes:
            if isinstance(value, bool) or not isinstance(value, int | float) \
                    or value not in set(AxisCode):
                return (f"expected a command code of the axis "
                        f"({', '.join(f'{c.value} {c.name.lower()}' for c in AxisCode)}), "
                        f"got {value!r}")
            return None
        b = self._bindings.get(device)
        if b is None:
            return None
        return value_error(b.od_var, b.index, b.subindex, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """The object's data type range (see :func:`drivers.canopen_od.accepted`)."""
        if device in self._axes:
            return float(min(AxisCode)), float(max(AxisCode)), True
        b = self._bindings.get(device)
        return None if b is None else accepted(b.od_var)

    # -- I/O thread ---------------------------------------------------------------------------

    def _run(self, job: Job) -> None:
        """One job: a poll (SDO uploads), a write (RPDO or SDO download), a node's boot
        procedure, the report of a node held in PRE-OPERATIONAL, a probe after a failed write."""
        try:
            match job:
                case Job(JobOp.POLL, AxisCycle() as cycle):
                    self._poll_taken(cycle)
                    self._guarded(self._axis_poll)
                case Job(JobOp.POLL, period):
                    self._poll_group(period)
                case Job(JobOp.WRITE, device, value) if device in self._axes:
                    self._answered(device)      # an axis command answers no SYNC cycle
                    self._axis_write(device, value)
                case Job(JobOp.WRITE, device, value):
                    self._transfer(self._bindings[device], value, *self._answered(device))
                case Job(JobOp.OWN, BootNode() as boot):
                    self._boot(boot)
                case Job(JobOp.OWN, ReportHeld() as held):
                    self._report_held(held)
                case Job(JobOp.OWN, RestartNode() as restart):
                    self._master.restart(restart)
                case Job(JobOp.OWN, Probe() as probe):
                    self._probe(probe)
                case Job(JobOp.OWN, AxisFeed() | AxisCommand() | AxisLost() | AxisRefresh()
                         as axis_job):
                    self._guarded(self._axis_job, axis_job)
                case Job(JobOp.OWN, AxisCycle()):
                    self._guarded(self._axis_poll)
                case _:
                    raise AssertionError(f"canopen driver: no such job {job!r}")
        except can.CanError as exc:
            self.host.error(self.bus.name, "can", f"{job.op} {job.what}: CAN send failed: {exc}")
            if job.op is JobOp.WRITE:
                self.host.write_failed(job.what, job.value, f"CAN send failed: {exc}")

    def _poll_group(self, period: float) -> None:
        self._poll_taken(period)
        batch: list[tuple[str, Any]] = []
        try:
            for b in self._poll_groups[period]:
                try:
                    self._poll(b, batch)
                except can.CanError as exc:   # this object's request; the next go out
                    self.host.error(self.bus.name, "can", f"poll {b.device.name}: CAN send "
                                                          f"failed: {exc}")
        finally:   # the poll's readings as one interrupt
            deliver_all(self.host, batch)

    def _boot(self, job: BootNode) -> None:
        """The boot procedure of a node (see :meth:`ManagedNode.boot`), then its NMT start."""
        node = self._nodes[job.node]
        with node.lock:
            if job.generation != node.lifecycle.generation:
                return      # the node booted again meanwhile: that boot's procedure follows
        result = node.boot(self._events.master_id)
        where = self._events.where(node)
        with node.lock:
            if job.generation != node.lifecycle.generation:
                return
            node.booting = False        # supervision counts from here
            node.last_heartbeat = self._events.clock()
            lc = node.lifecycle
            match result.outcome:
                case BootOutcome.SILENT:
                    lc.no_answer(f"{result.reason}")
                    node.starting = False
                case BootOutcome.IDENTITY_MISMATCH | BootOutcome.CONFIG_REFUSED:
                    lc.failed(result.reason)
                    node.starting = False
                case BootOutcome.CONFIGURED:
                    lc.error_register = result.error_register
                    if result.stored:
                        lc.stores += 1
                    lc.configured()
                    if lc.nmt_start:
                        lc.started(self.host.now())
        match result.outcome:
            case BootOutcome.IDENTITY_MISMATCH:
                self.host.error(self.bus.name, "identity", f"{where}: {result.reason}")
            case BootOutcome.CONFIG_REFUSED:
                self.host.error(self.bus.name, "config", f"{where}: {result.reason}")
            case BootOutcome.CONFIGURED:
                reg = result.error_register
                if reg and not node.axes:
                    self._events.fail_node(node, "emcy", f"{where}: error register 0x1001 = "
                                                  f"0x{reg:02X} at boot",
                                           keep=node.controlwords)
                else:
                    self._events.clear_node(node, "emcy",
                                            f"{where}: error register 0x1001 clear at boot")
                if node.lifecycle.nmt_start:
                    node.send_nmt_start()
        self._events.judge(node, "configured and started" if node.lifecycle.nmt_start
                    else "configured")

    def _report_held(self, job: ReportHeld) -> None:
        """A started node stays PRE-OPERATIONAL (or its restarts were used up): its error
        register and last EMCY into the reason; reported once, no NMT start again (the node
        refuses for a reason) until its cause clears (an error-reset EMCY) or the host's
        ``nmt start``."""
        node = self._nodes[job.node]
        try:
            reg: int | None = node.read_error_register()
            got = "" if reg is None else f"error register 0x1001 = 0x{reg:02X}"
        except SdoCommunicationError as exc:
            reg, got = None, f"error register 0x1001 not read: {exc}"
        with node.lock:
            lc = node.lifecycle
            if job.generation != lc.generation or lc.state is not NodeLifecycle.PREOP_HELD:
                return
            if reg is not None:
                lc.error_register = reg
            parts = [p for p in (got, f"last EMCY {lc.last_emcy}" if lc.last_emcy else
                                 "no EMCY seen") if p]
            if lc.left_at is not None:      # it ran, left, and its restarts were used up
                lc.reason = lc.recovery_reason("; ".join(parts))
            else:
                state = lc.nmt.text if lc.nmt is not None else "not OPERATIONAL"
                lc.reason = f"stays {state} after the NMT start ({'; '.join(parts)})"
            reason = lc.reason
        self.host.error(self.bus.name, "preop-held", f"{self._events.where(node)}: {reason}")
        self._events.judge(node, "operational")
        self._events.restate(node)

    def nmt(self, command: NmtCommand | str, node: int) -> str:
        """Send NMT ``command`` (an :class:`NmtCommand`, or its host word: ``start``,
        ``stop``, ``preop``, ``reset``, ``reset-comm``) to node ``node`` now (see
        :meth:`drivers.canopen_nmt.NmtMaster.command`). Returns the answer naming the node and
        the state it was in. Raises BusError for a node not on this bus, a driver not running,
        a command that is none, or a frame that cannot be sent."""
        return self._master.command(command, node, self._running)

    def _sdo_where(self, b: Binding) -> str:
        return f"canopen node {b.node} 0x{b.index:04X}:{b.subindex:02X} (device {b.device.name})"

    def _poll(self, b: Binding, batch: list[tuple[str, Any]]) -> None:
        """SDO-read ``b``'s object: the reading goes to ``batch`` (delivered at the end of the
        poll), a failure to the host at once."""
        node = self._nodes[b.node].remote
        try:
            data = node.sdo.upload(b.index, b.subindex)
            value = b.od_var.decode_raw(data)
        except SdoAbortedError as exc:
            self._events.health.fail(b.device.name, "sdo", f"SDO read of {self._sdo_where(b)} "
                                                    f"aborted: {exc}")
            return
        except (SdoCommunicationError, struct.error) as exc:
            self._events.health.fail(b.device.name, "sdo", f"SDO read of {self._sdo_where(b)} "
                                                    f"failed: {exc}")
            return
        if self._events.health.has_causes(b.device.name):
            self._events.health.clear(b.device.name, "sdo", f"SDO read of {self._sdo_where(b)} "
                                                     f"answered")
        batch.append((b.device.name, value))

    def _transfer(self, b: Binding, value: Any, answers: int | None = None,
                  generation: int | None = None) -> None:
        node = self._nodes[b.node]
        if generation is not None and generation != node.lifecycle.generation:
            # queued before the node rebooted: its configuration, NMT start and safe value
            # come first (Devtab writes the safe value when the node is ready again)
            self.host.write_failed(b.device.name, value, f"{self._events.where(node)}: not "
                                   f"sent: the node rebooted (boot-up) after this command was "
                                   f"queued; it gets its configuration, NMT start and safe "
                                   f"value first")
            return
        try:
            raw = coerce(b.od_var, value)
            data = b.od_var.encode_raw(raw)
        except (struct.error, TypeError, ValueError, OverflowError) as exc:
            text = (f"write {value!r} to {self._sdo_where(b)}: expected a value of data "
                    f"type {b.od_var.data_type:#x}: {exc}")
            self.host.error(self.bus.name, "range", text, b.device.name)
            self.host.write_failed(b.device.name, value, text)
            return
        name = b.device.name
        if b.pdo_var is not None:
            # every RPDO image mapping the object takes the value; the PDO bound first carries it
            node = self._nodes[b.node]
            node.images.set(b.index, b.subindex, bytes(data))
            b.pdo_var.pdo_parent.transmit()     # on the wire whatever the node's state
            self.sent_frames[name] += 1
            sync = self._events.sync
            if answers is not None and sync is not None and sync.cycle > answers:
                self._late_writes += 1          # SYNC n+1 went out before this answer to n
                self.host.stat(self.bus.name, "sync-late-writes", device=name)
            with node.lock:
                state, why = node.lifecycle.state, node.lifecycle.reason
            if state in IGNORES_RPDOS:
                self.host.write_failed(name, value, f"{self._events.where(node)}: RPDO sent, "
                                                    f"but the node ignores it: {state.value}: "
                                                    f"{why}")
            else:
                self.host.written(name, value)
            return
        self.host.stat(self.bus.name, "requests", device=name)
        try:
            self._nodes[b.node].remote.sdo.download(b.index, b.subindex, data)
        except SdoAbortedError as exc:
            self._write_refused(b, value, "sdo-abort", f"SDO write to {self._sdo_where(b)} "
                                                       f"aborted: {exc}")
            return
        except SdoCommunicationError as exc:
            self._write_refused(b, value, "timeout", f"SDO write to {self._sdo_where(b)} "
                                                     f"failed: {exc}")
            return
        self.host.written(name, value)
        self._events.health.clear(name, "sdo", f"SDO write to {self._sdo_where(b)} answered")

    def _write_refused(self, b: Binding, value: Any, kind: str, text: str) -> None:
        """An SDO write failed: reported, the actuator failed, and a probe armed that clears
        the failure once the node answers again (a failed actuator gets no writes to do it)."""
        name = b.device.name
        self.host.error(self.bus.name, kind, text, name)
        self.host.write_failed(name, value, text)
        self._events.health.fail(name, "sdo", text)
        self._arm_probe(b)

    def _arm_probe(self, b: Binding) -> None:
        if self._running:
            self.host.at(round(self.host.now() + b.poll_period, 9),
                         lambda: self._queue_probe(b.device.name))

    def _queue_probe(self, device: str) -> None:
        self._submit(JobOp.OWN, Probe(device))

    def _probe(self, job: Probe) -> None:
        """An SDO upload of the failed actuator's object (of 0x1000, the device type, if the
        object cannot be read): an answer clears the failure, none arms the next probe."""
        b = self._bindings[job.device]
        if not self._events.health.failed(job.device):
            return
        readable = b.od_var is not None and b.od_var.readable
        index, sub = (b.index, b.subindex) if readable else (0x1000, 0)
        try:
            self._nodes[b.node].remote.sdo.upload(index, sub)
        except (SdoAbortedError, SdoCommunicationError):
            self._arm_probe(b)
            return
        self._events.health.clear(job.device, "sdo", f"canopen node {b.node} answered a probe of "
                                              f"0x{index:04X}:{sub:02X}")
