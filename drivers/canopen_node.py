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
every ``poll_period``, paced by the polls as in :mod:`drivers.jobs` (the kernel timer only
enqueues; the SDOs run on the driver's I/O
thread, the sensors of one period in turn in one job). An actuator write goes in the RPDO that
maps the object, else by SDO download.

Failures: a node whose heartbeat is missing longer than its ``heartbeat_timeout`` fails all its
devices until a heartbeat returns. Every EMCY is reported through ``host.error(bus, "emcy", ...)``;
EMCY codes of the classes current (2xxx), voltage (3xxx), temperature (4xxx), device hardware (50xx)
and monitoring (8xxx) are fatal: they fail the node's devices until an error-reset EMCY (code 0000).
An SDO abort or timeout fails that device (with the abort code text) until its next good transfer.
Short PDO and EMCY frames, and heartbeats of nodes not in ``nodes``, are ``host.error`` reports.

This module holds the life cycle, the SDO polls (a poll's readings go to the host as one
interrupt) and the writes; the receive side (frames, TPDOs, the heartbeat watchdog, EMCY) and the
driver's state are :mod:`drivers.canopen_events`, the object dictionary :mod:`drivers.canopen_od`.
"""

from __future__ import annotations

import contextlib
import struct
import time
from typing import Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from chcos.devices import parsecache
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import BusError
from drivers.base import deliver_all
from drivers.canbus import read_frames
from drivers.canopen_events import Binding, CanopenEvents, FrameCheck, NodeState
from drivers.canopen_od import (
    DEFAULT_POLL,
    accepted,
    check_bus,
    check_device,
    coerce,
    encodable,
    load_od,
    value_error,
)
from drivers.jobs import Job
from drivers.threaded import ReaderThread

DEFAULT_SDO_TIMEOUT = 0.3
#: The reader's default receive timeout on interfaces without a file descriptor.
DEFAULT_RX_POLL = 0.005


class CanopenDriver(CanopenEvents):
    """The ``canopen`` bus: see the module doc for options, addresses and failure handling."""

    kind = "canopen"

    # -- validation (drivers.canopen_od) -----------------------------------------------------

    @classmethod
    def check_bus(cls, bus: BusSpec) -> list[str]:
        """Errors of the bus options (unknown keys, types, node ids, unreadable EDS files)."""
        return check_bus(bus)

    @classmethod
    def check_device(cls, bus: BusSpec, device: DeviceSpec) -> list[str]:
        """Errors of a device address: keys, node on this bus, object present in the node's EDS,
        readable for a sensor and writable for an actuator."""
        return check_device(bus, device)

    @classmethod
    def encodable(cls, bus: BusSpec, device: DeviceSpec) -> tuple[float, float] | None:
        """The range of the object's data type in the node's EDS: 0..1 for BOOLEAN, the
        INTEGERn/UNSIGNEDn ranges, the largest REAL32; None for REAL64 and other types."""
        return encodable(bus, device)

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
        network.listeners.append(FrameCheck(self))
        opts = self.bus.options
        for ncfg in opts["nodes"]:
            nid = int(ncfg["id"])
            node: Any = canopen.RemoteNode(nid, load_od(self.bus, nid, ncfg["eds"]))
            node.sdo.RESPONSE_TIMEOUT = float(opts.get("sdo_timeout", DEFAULT_SDO_TIMEOUT))
            network.add_node(node)
            hb = ncfg.get("heartbeat_timeout")
            self._nodes[nid] = NodeState(node, float(hb) if hb is not None else None,
                                          bool(ncfg.get("nmt_start", True)))
        self._network = network
        self._watched = any(s.heartbeat_timeout is not None for s in self._nodes.values())
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
            self._bindings[dev.name] = Binding(
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
        self._tell_frames()
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
        return value_error(b.od_var, b.index, b.subindex, value)

    def accepts(self, device: str) -> tuple[float, float, bool] | None:
        """The object's data type range (see :func:`drivers.canopen_od.accepted`)."""
        b = self._bindings.get(device)
        return None if b is None else accepted(b.od_var)

    # -- I/O thread ---------------------------------------------------------------------------

    def _run(self, job: Job) -> None:
        """A poll (SDO upload), a write (RPDO or SDO download), or an NMT start of a node."""
        op, name, arg = job
        try:
            if op == "poll":
                self._poll_taken(name)
                batch: list[tuple[str, Any]] = []
                try:
                    for b in self._poll_groups[name]:
                        try:
                            self._poll(b, batch)
                        except can.CanError as exc:   # this object's request; the next go out
                            self.host.error(self.bus.name, "can", f"poll {b.device.name}: CAN "
                                                                  f"send failed: {exc}")
                finally:   # the poll's readings as one interrupt
                    deliver_all(self.host, batch)
            elif op == "write":
                self._transfer(self._bindings[name], arg)
            elif op == "nmt":
                self._nodes[int(name)].node.nmt.state = "OPERATIONAL"
        except can.CanError as exc:
            self.host.error(self.bus.name, "can", f"{op} {name}: CAN send failed: {exc}")
            if op == "write":
                self.host.write_failed(name, arg, f"CAN send failed: {exc}")

    def _where(self, b: Binding) -> str:
        return f"canopen node {b.node} 0x{b.index:04X}:{b.subindex:02X} (device {b.device.name})"

    def _poll(self, b: Binding, batch: list[tuple[str, Any]]) -> None:
        """SDO-read ``b``'s object: the reading goes to ``batch`` (delivered at the end of the
        poll), a failure to the host at once."""
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
        if self._health.has_causes(b.device.name):
            self._health.clear(b.device.name, "sdo", f"SDO read of {self._where(b)} answered")
        batch.append((b.device.name, value))

    def _transfer(self, b: Binding, value: Any) -> None:
        try:
            raw = coerce(b.od_var, value)
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
            self.sent_frames[name] += 1
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

