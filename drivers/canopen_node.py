"""canopen_node - the ``canopen`` bus driver: remote CANopen nodes through the canopen library.

Bus options (``[[bus]] kind = "canopen"``):

* ``interface``, ``channel``, ``bitrate`` - the python-can bus; any left out comes from python-can's
  own configuration (``can.util.load_config``: ``CAN_INTERFACE``, ``CAN_CHANNEL``, config files).
* ``nodes = [{id, eds, heartbeat_timeout, nmt_start}]`` - node id 1..127, the node's EDS file
  (absolute, or relative to the device-map file), heartbeat timeout in seconds (optional: no
  heartbeat supervision), and whether the driver puts the node OPERATIONAL (default true).
* ``sync_period`` (s, optional) - produce SYNC at this period; ``poll_period`` (s, default 0.1) -
  default SDO polling period; ``sdo_timeout`` (s, default 0.3) - SDO response timeout.
* ``poll`` (s, default 0.005) - the receive timeout of the driver's reader on interfaces it cannot
  wait on without receiving; it bounds :meth:`CanopenDriver.settle` there. Not used on SocketCAN
  or python-can's ``virtual`` interface (see :func:`drivers.canbus.read_frames`).

Frames are received by the driver's own reader thread (:func:`drivers.canbus.read_frames`), not
by canopen's notifier, and handed to canopen's listeners (SDO responses, PDOs, heartbeats, EMCY),
so that :meth:`CanopenDriver.settle` can promise that every frame that arrived before it has been
handled: virtual-time runs are deterministic on CANopen too.

Device address: ``{node, index, subindex = 0, poll_period}``. A sensor whose object is mapped in an
enabled TPDO of the node's EDS is delivered from the PDO callback; any other sensor is read by SDO
every ``poll_period`` (the ``host.every`` callback only enqueues; the SDO runs on the driver's I/O
thread). An actuator write goes in the RPDO that maps the object, else by SDO download.

Failures: a node whose heartbeat is missing longer than its ``heartbeat_timeout`` fails all its
devices until a heartbeat returns. Every EMCY is reported through ``host.error(bus, "emcy", ...)``;
EMCY codes of the classes current (2xxx), voltage (3xxx), temperature (4xxx), device hardware (50xx)
and monitoring (8xxx) are fatal: they fail the node's devices until an error-reset EMCY (code 0000).
An SDO abort or timeout fails that device (with the abort code text) until its next good transfer.
Short PDO and EMCY frames, and heartbeats of nodes not in ``nodes``, are ``host.error`` reports.
"""

from __future__ import annotations

import contextlib
import functools
import struct
import threading
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, TypeGuard

import can
import canopen
from canopen.objectdictionary import BOOLEAN, FLOAT_TYPES, INTEGER_TYPES
from canopen.objectdictionary.datatypes import REAL32, SIGNED_TYPES
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from chcos.devices import parsecache
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from drivers.base import DriverHost, not_finite
from drivers.canbus import read_frames
from drivers.codecs.canopen import (
    eds_path,
    emcy_node,
    heartbeat_node,
    is_error_reset,
    is_fatal_emcy,
)
from drivers.health import Health
from drivers.jobs import Job, WorkerJobDriver
from drivers.threaded import ReaderThread

BUS_OPTIONS = ("interface", "channel", "bitrate", "nodes", "sync_period", "poll_period",
               "sdo_timeout", "poll")
NODE_KEYS = ("id", "eds", "heartbeat_timeout", "nmt_start")
HEARTBEAT_SETTLE = 0.1
"""Bound (s) on handing over received frames before a heartbeat loss is declared (polling
interfaces; on SocketCAN the drain is immediate)."""
ADDRESS_KEYS = ("node", "index", "subindex", "poll_period")
DEFAULT_POLL = 0.1
DEFAULT_SDO_TIMEOUT = 0.3
#: The reader's default receive timeout on interfaces without a file descriptor.
DEFAULT_RX_POLL = 0.005


def _is_number(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _is_int(v: object) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def load_od(bus: BusSpec, node_id: int, eds: str) -> Any:
    """canopen's object dictionary of node ``node_id`` from ``eds``; raises ``ValueError`` naming
    the file when canopen cannot read it."""
    path = eds_path(bus, eds)
    if not path.is_file():
        raise ValueError(f"EDS file {path} does not exist")
    try:
        return parsecache.cached("eds", path, node_id,
                                 lambda: canopen.import_od(str(path), node_id))
    except Exception as exc:  # canopen raises assorted types for a malformed EDS
        raise ValueError(f"canopen cannot read EDS {path}: {exc}") from exc


def checked_od(bus: BusSpec, node_id: int, eds: str) -> Any:
    """:func:`load_od` for the map checks (``check_device``, ``encodable``): inside a
    :func:`chcos.devices.parsecache.scope` one parse per node and file, however many devices use it.
    The result may be shared: read it, never change it (a running node gets its own).
    Raises ``ValueError`` like :func:`load_od`."""
    return load_od(bus, node_id, eds)


@dataclass
class _Binding:
    device: DeviceSpec
    node: int
    index: int
    subindex: int
    od_var: Any
    pdo_var: Any = None        # TPDO variable (sensor) or RPDO variable (actuator), or None
    poll_period: float = DEFAULT_POLL


@dataclass
class _NodeState:
    node: Any
    heartbeat_timeout: float | None
    nmt_start: bool
    last_heartbeat: float = field(default_factory=time.monotonic)
    lost: bool = False
    devices: list[str] = field(default_factory=list)


class CanopenDriver(WorkerJobDriver):
    """The ``canopen`` bus: see the module doc for options, addresses and failure handling."""

    kind = "canopen"

    def __init__(self, bus: BusSpec, devices: Sequence[DeviceSpec], host: DriverHost) -> None:
        super().__init__(bus, devices, host)
        self._health = Health(host)
        self._hb_lock = threading.Lock()      # guards _NodeState.last_heartbeat and .lost
        self._network: Any = None
        self._nodes: dict[int, _NodeState] = {}
        self._bindings: dict[str, _Binding] = {}
        self._pdo_sensors: dict[tuple[int, int, int], list[str]] = {}
        self._bus_failed = False

    # -- validation ---------------------------------------------------------------------------

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of the bus options (unknown keys, types, node ids, unreadable EDS files)."""
        errs: list[str] = []
        k = bus.key
        opts = bus.options
        for key in opts:
            if key not in BUS_OPTIONS:
                errs.append(f"{k}.{key}: unknown option for a canopen bus; valid options: "
                            f"{', '.join(BUS_OPTIONS)}")
        for key in ("interface", "channel"):
            if key in opts and (not isinstance(opts[key], str | int) or opts[key] == ""):
                errs.append(f"{k}.{key}: expected a python-can {key} name, got {opts[key]!r}")
        if "bitrate" in opts and not (_is_int(opts["bitrate"]) and opts["bitrate"] > 0):
            errs.append(f"{k}.bitrate: expected an integer > 0 (bit/s), got {opts['bitrate']!r}")
        if "poll" in opts and not (_is_number(opts["poll"]) and 0 < opts["poll"] <= 1):
            errs.append(f"{k}.poll: expected seconds in (0, 1], got {opts['poll']!r}")
        for key in ("sync_period", "poll_period", "sdo_timeout"):
            if key in opts and not (_is_number(opts[key]) and opts[key] > 0):
                errs.append(f"{k}.{key}: expected a number of seconds > 0, got {opts[key]!r}")
        nodes = opts.get("nodes")
        if not isinstance(nodes, list) or not nodes:
            return [*errs, f"{k}.nodes: expected a non-empty array of {{id, eds}} tables, "
                           f"got {nodes!r}"]
        seen: set[int] = set()
        for i, node in enumerate(nodes):
            errs.extend(cls._check_node(bus, f"{k}.nodes[{i}]", node, seen))
        return errs

    @classmethod
    def _check_node(cls, bus: BusSpec, k: str, node: object, seen: set[int]) -> list[str]:
        if not isinstance(node, Mapping):
            return [f"{k}: expected a table {{id, eds}}, got {node!r}"]
        errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(NODE_KEYS)}"
                for key in node if key not in NODE_KEYS]
        nid = node.get("id")
        if not (_is_int(nid) and 1 <= nid <= 127):
            errs.append(f"{k}.id: expected a CANopen node id 1..127, got {nid!r}")
        elif nid in seen:
            errs.append(f"{k}.id: node id {nid} appears twice on bus {bus.name}")
        else:
            seen.add(nid)
        eds = node.get("eds")
        if not isinstance(eds, str) or not eds:
            errs.append(f"{k}.eds: expected the path of the node's EDS file, got {eds!r}")
        elif _is_int(nid):
            try:
                load_od(bus, nid, eds)
            except ValueError as exc:
                errs.append(f"{k}.eds: expected a readable EDS file; {exc}")
        hb = node.get("heartbeat_timeout")
        if hb is not None and not (_is_number(hb) and hb > 0):
            errs.append(f"{k}.heartbeat_timeout: expected a number of seconds > 0, got {hb!r}")
        if "nmt_start" in node and not isinstance(node["nmt_start"], bool):
            errs.append(f"{k}.nmt_start: expected true or false, got {node['nmt_start']!r}")
        return errs

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """Errors of a device address: keys, node on this bus, object present in the node's EDS,
        readable for a sensor and writable for an actuator."""
        k = f"{device.key}.address"
        a = device.address
        errs = [f"{k}.{key}: unknown key; valid keys: {', '.join(ADDRESS_KEYS)}"
                for key in a if key not in ADDRESS_KEYS]
        nodes = {n.get("id"): n for n in bus.options.get("nodes", []) if isinstance(n, Mapping)}
        nid, index, sub = a.get("node"), a.get("index"), a.get("subindex", 0)
        if not _is_int(nid) or nid not in nodes:
            errs.append(f"{k}.node: expected the id of a node of bus {bus.name} "
                        f"({', '.join(str(n) for n in nodes) or 'none'}), got {nid!r}")
        if not (_is_int(index) and 0 <= index <= 0xFFFF):
            errs.append(f"{k}.index: expected an object index 0..0xFFFF, got {index!r}")
        if not (_is_int(sub) and 0 <= sub <= 0xFF):
            errs.append(f"{k}.subindex: expected a subindex 0..255, got {sub!r}")
        pp = a.get("poll_period")
        if pp is not None and not (_is_number(pp) and pp > 0):
            errs.append(f"{k}.poll_period: expected a number of seconds > 0, got {pp!r}")
        if errs or not _is_int(nid):
            return errs
        eds = nodes[nid].get("eds")
        try:
            od = checked_od(bus, nid, eds) if isinstance(eds, str) else None
        except ValueError:
            return []  # reported by check_bus
        var = od.get_variable(index, sub) if od is not None else None
        if od is not None and var is None:
            errs.append(f"{k}: expected an object of node {nid}'s EDS, no 0x{index:04X}:{sub:02X}")
        elif var is not None and device.direction == "sensor" and not var.readable:
            errs.append(f"{k}: 0x{index:04X}:{sub:02X} is not readable; a sensor needs a readable "
                        f"object")
        elif var is not None and device.direction == "actuator" and not var.writable:
            errs.append(f"{k}: 0x{index:04X}:{sub:02X} is read-only; an actuator needs a writable "
                        f"object")
        return errs

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of the object's data type in the node's EDS: 0..1 for BOOLEAN, the
        INTEGERn/UNSIGNEDn ranges, the largest REAL32; None for REAL64 and other types."""
        a = device.address
        nodes = {n.get("id"): n for n in bus.options.get("nodes", []) if isinstance(n, Mapping)}
        var = checked_od(bus, a["node"], str(nodes[a["node"]]["eds"])).get_variable(
            a["index"], a.get("subindex", 0))
        dt = var.data_type
        if dt == BOOLEAN:
            return 0.0, 1.0
        if dt == REAL32:
            return -3.4028234663852886e38, 3.4028234663852886e38
        if dt not in INTEGER_TYPES:
            return None
        bits = 8 * var.STRUCT_TYPES[dt].size
        if dt in SIGNED_TYPES:
            return float(-(1 << (bits - 1))), float((1 << (bits - 1)) - 1)
        return 0.0, float((1 << bits) - 1)

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Validate, open the CAN bus, bind devices to PDOs or SDO polling, start the I/O thread
        and put the nodes OPERATIONAL. Raises :class:`BusError` (invalid options included)."""
        with parsecache.scope():   # each EDS parsed once for the checks, not once per device
            errs = self.check_bus(self.bus)
            for dev in self.devices.values():
                errs.extend(self.check_device(self.bus, dev))
        if errs:
            raise BusError(f"canopen bus {self.bus.name} ({self.bus.file}): " + "; ".join(errs))
        network: Any = canopen.Network()
        network.listeners.append(_FrameCheck(self))
        opts = self.bus.options
        for ncfg in opts["nodes"]:
            nid = int(ncfg["id"])
            node: Any = canopen.RemoteNode(nid, load_od(self.bus, nid, ncfg["eds"]))
            node.sdo.RESPONSE_TIMEOUT = float(opts.get("sdo_timeout", DEFAULT_SDO_TIMEOUT))
            network.add_node(node)
            hb = ncfg.get("heartbeat_timeout")
            self._nodes[nid] = _NodeState(node, float(hb) if hb is not None else None,
                                          bool(ncfg.get("nmt_start", True)))
        self._network = network
        self._bind_devices()
        config = {k: opts[k] for k in ("interface", "channel", "bitrate") if k in opts}
        try:
            cfg = dict(can.util.load_config(config=config))
            if "bitrate" not in cfg:   # as canopen's connect(): the first EDS that names one
                rates = [s.node.object_dictionary.bitrate for s in self._nodes.values()]
                if any(rates):
                    cfg["bitrate"] = next(r for r in rates if r)
            bus = can.Bus(**cfg)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(f"canopen bus {self.bus.name} ({self.bus.file} {self.bus.key}): cannot "
                           f"open CAN bus {config or 'from python-can config'}: {exc}") from exc
        network.bus = bus
        poll = float(opts.get("poll", DEFAULT_RX_POLL))
        rx = self._rx = ReaderThread(
            lambda: read_frames(rx, bus, poll, self._on_frame, self._on_bus_error),
            f"canopen-{self.bus.name}-rx")
        rx.start()
        for state in self._nodes.values():
            state.node.nmt.add_heartbeat_callback(
                lambda nmt_state, s=state: self._on_heartbeat(s, nmt_state))
            state.node.emcy.add_callback(lambda entry, s=state: self._on_emcy(s, entry))
            state.last_heartbeat = time.monotonic()
        self._running = True
        self._start_worker()
        for nid, state in self._nodes.items():
            if state.nmt_start:
                self._submit("nmt", str(nid))
        if "sync_period" in opts:
            network.sync.start(float(opts["sync_period"]))
        for name, b in self._bindings.items():
            if b.device.direction == "sensor" and b.pdo_var is None:
                self.host.every(b.poll_period, functools.partial(self._submit_poll, name))

    def _bind_devices(self) -> None:
        default_poll = float(self.bus.options.get("poll_period", DEFAULT_POLL))
        for state in self._nodes.values():
            state.node.tpdo.read(from_od=True)
            state.node.rpdo.read(from_od=True)
            for pdo_map in state.node.tpdo.map.values():
                pdo_map.add_callback(self._on_tpdo)
        for dev in self.devices.values():
            a = dev.address
            nid, index, sub = int(a["node"]), int(a["index"]), int(a.get("subindex", 0))
            node = self._nodes[nid].node
            maps = node.tpdo.map if dev.direction == "sensor" else node.rpdo.map
            pdo_var = next((v for m in maps.values() if m.enabled for v in m.map
                            if v.index == index and v.subindex == sub), None)
            self._bindings[dev.name] = _Binding(
                dev, nid, index, sub, node.object_dictionary.get_variable(index, sub), pdo_var,
                float(a.get("poll_period", default_poll)))
            self._nodes[nid].devices.append(dev.name)
            if dev.direction == "sensor" and pdo_var is not None:
                self._pdo_sensors.setdefault((nid, index, sub), []).append(dev.name)

    def stop(self) -> None:
        """Put every queued write on the wire (safe values at shutdown), then stop SYNC, the I/O
        thread and the bus. Idempotent; never raises."""
        self._running = False
        self._stop_worker()     # runs every job queued before: they go out first
        rx, self._rx = self._rx, None
        if rx is not None:
            rx.stop()
        network, self._network = self._network, None
        if network is not None:
            with contextlib.suppress(Exception):
                network.sync.stop()
            with contextlib.suppress(Exception):
                network.disconnect()

    # -- kernel side --------------------------------------------------------------------------

    def check_value(self, device: str, value: Any) -> str | None:
        """Why ``value`` cannot be encoded for ``device``'s object (None if it can): not a
        finite number, a fraction for an integer object, outside the data type's range."""
        b = self._bindings.get(device)
        if b is None:
            return None
        if (why := not_finite(value)) is not None:
            return why
        if isinstance(value, bool):
            value = int(value)
        if (b.od_var.data_type in INTEGER_TYPES and isinstance(value, float)
                and not value.is_integer()):
            return f"expected an integer for object 0x{b.index:04X}:{b.subindex:02X}, got {value!r}"
        try:
            b.od_var.encode_raw(_coerce(b.od_var, value))
        except (struct.error, TypeError, ValueError, OverflowError) as exc:
            return (f"expected a value of data type {b.od_var.data_type:#x} for object "
                    f"0x{b.index:04X}:{b.subindex:02X}: {exc}")
        return None

    # -- I/O thread ---------------------------------------------------------------------------

    def _tick(self) -> float:
        """The worker's longest wait for a job: until the next heartbeat deadline."""
        return self._watchdog()

    def _run(self, job: Job) -> None:
        """A poll (SDO upload), a write (RPDO or SDO download), or an NMT start of a node."""
        op, name, arg = job
        try:
            if op == "poll":
                self._poll_taken(name)
                self._poll(self._bindings[name])
            elif op == "write":
                self._transfer(self._bindings[name], arg)
            elif op == "nmt":
                self._nodes[int(name)].node.nmt.state = "OPERATIONAL"
        except can.CanError as exc:
            self.host.error(self.bus.name, "can", f"{op} {name}: CAN send failed: {exc}")
            if op == "write":
                self.host.write_failed(name, arg, f"CAN send failed: {exc}")

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

    def _where(self, b: _Binding) -> str:
        return f"canopen node {b.node} 0x{b.index:04X}:{b.subindex:02X} (device {b.device.name})"

    def _poll(self, b: _Binding) -> None:
        node = self._nodes[b.node].node
        try:
            data = node.sdo.upload(b.index, b.subindex)
            value = b.od_var.decode_raw(data)
        except SdoAbortedError as exc:
            self._health.fail(b.device.name, "sdo", f"SDO read of {self._where(b)} aborted: {exc}")
            return
        except (SdoCommunicationError, struct.error) as exc:
            self._health.fail(b.device.name, "sdo", f"SDO read of {self._where(b)} failed: {exc}")
            return
        self._health.clear(b.device.name, "sdo", f"SDO read of {self._where(b)} answered")
        self.host.deliver(b.device.name, value)

    def _transfer(self, b: _Binding, value: Any) -> None:
        try:
            raw = _coerce(b.od_var, value)
            data = b.od_var.encode_raw(raw)
        except (struct.error, TypeError, ValueError, OverflowError) as exc:
            text = (f"write {value!r} to {self._where(b)}: expected a value of data "
                    f"type {b.od_var.data_type:#x}: {exc}")
            self.host.error(self.bus.name, "range", text, b.device.name)
            self.host.write_failed(b.device.name, value, text)
            return
        name = b.device.name
        if b.pdo_var is not None:
            b.pdo_var.set_data(data)
            b.pdo_var.pdo_parent.transmit()
            self.host.stat(self.bus.name, "frames-sent", device=name)
            self.host.written(name, value)
            return
        self.host.stat(self.bus.name, "requests", device=name)
        try:
            self._nodes[b.node].node.sdo.download(b.index, b.subindex, data)
        except SdoAbortedError as exc:
            text = f"SDO write to {self._where(b)} aborted: {exc}"
            self.host.error(self.bus.name, "sdo-abort", text, name)
            self.host.write_failed(name, value, text)
            self._health.fail(name, "sdo", text)
            return
        except SdoCommunicationError as exc:
            text = f"SDO write to {self._where(b)} failed: {exc}"
            self.host.error(self.bus.name, "timeout", text, name)
            self.host.write_failed(name, value, text)
            self._health.fail(name, "sdo", text)
            return
        self.host.written(name, value)
        self._health.clear(name, "sdo", f"SDO write to {self._where(b)} answered")

    # -- reader thread ------------------------------------------------------------------------

    def _on_frame(self, frame: can.Message) -> None:
        """A received frame to canopen's listeners (what its notifier would do)."""
        self._bus_failed = False     # a receive error is reported again after a good frame
        self.host.stat(self.bus.name, "frames")
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
        for var in pdo_map.map:
            for dev in self._pdo_sensors.get((nid, var.index, var.subindex), ()):
                self.host.deliver(dev, var.raw)

    def _on_heartbeat(self, state: _NodeState, nmt_state: int) -> None:
        with self._hb_lock:
            state.last_heartbeat = time.monotonic()
            was_lost, state.lost = state.lost, False
        if was_lost:
            for dev in state.devices:
                self._health.clear(dev, "heartbeat", f"canopen node {state.node.id}: heartbeat "
                                                     f"back")
        if state.nmt_start and nmt_state in (0, 127):  # boot-up or PRE-OPERATIONAL
            self._submit("nmt", str(state.node.id))

    def _on_emcy(self, state: _NodeState, entry: Any) -> None:
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
        """A frame-level problem seen by the bus listener (see :class:`_FrameCheck`)."""
        self.host.error(self.bus.name, kind, detail)

    def knows_node(self, node_id: int) -> bool:
        """True if ``node_id`` is one of this bus's nodes."""
        return node_id in self._nodes


def _coerce(od_var: Any, value: Any) -> Any:
    """``value`` as the Python type canopen encodes for ``od_var``'s data type."""
    if od_var.data_type == BOOLEAN:
        return bool(value)
    if od_var.data_type in INTEGER_TYPES:
        if isinstance(value, float):
            if value != value or value in (float("inf"), float("-inf")):
                raise ValueError("not a finite number")
            return round(value)
        return int(value)
    if od_var.data_type in FLOAT_TYPES:
        return float(value)
    return value


class _FrameCheck(can.Listener):
    """Reports frames canopen would drop quietly: heartbeats of unknown nodes, short EMCYs."""

    def __init__(self, driver: CanopenDriver) -> None:
        self._driver = driver

    def on_message_received(self, msg: can.Message) -> None:
        cob = msg.arbitration_id
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
