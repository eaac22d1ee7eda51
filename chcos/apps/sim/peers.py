"""peers - the simulated peers of the bus kinds a device map can name (Modbus TCP/RTU, raw CAN,
CANopen; serial is :mod:`chcos.apps.sim.serial_peer`): each answers one bus's devices on the
real protocol, with the map's directions turned round (see :mod:`chcos.apps.sim.from_map`).
The CAN peer codes frames with the driver's own pure codec (:mod:`drivers.codecs.can`).
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import re
import threading
from typing import Any, Literal

from chcos.apps.sim.modbus_server import ModbusSimServer
from chcos.apps.sim.modbus_slave import ModbusSlave, RegisterStore
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import ConfigError, DeviceError
from chcos.helpers import free_port
from drivers.codecs.cia402 import is_axis_address
from drivers.codecs.modbus_direct import register, unregister

LOOPBACK = ("127.0.0.1", "localhost", "::1")
_channels = itertools.count()


# ---- peers ------------------------------------------------------------------------------------
class Peer:
    """One bus's simulated peer."""

    bus: BusSpec

    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        self.bus = bus

    def set(self, device: DeviceSpec, raw: Any) -> None:
        raise NotImplementedError

    def get(self, device: DeviceSpec) -> Any:
        raise NotImplementedError

    def serve(self) -> None:
        """Begin answering at the bus's address (a socket server listens); a peer that
        answers from its construction on has nothing to do."""

    def tick(self, now: float) -> None:
        """Clock time ``now`` (seconds since the slaves started): send what is due."""

    def settle(self, timeout: float) -> bool:
        """Wait (``timeout`` wall seconds at most) until everything the drivers sent to this
        peer so far has been handled on the peer's own threads; True when it has. A peer
        that handles what it receives only when asked (on the kernel thread) or whose driver
        waits for every answer has nothing to wait for."""
        return True

    def handled(self) -> int:
        """A count that grows whenever a driver sent something to the peer's own threads and
        whenever they are done with it (see
        :meth:`chcos.kernel.scheduler.Kernel.add_settle_activity`)."""
        return 0

    def silence(self) -> None:
        raise NotImplementedError

    def restore(self) -> None:
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError

    def close(self) -> None:
        raise NotImplementedError


class Mutable:
    """A peer that goes silent on request and speaks again: its ``muted`` flag, under its
    ``lock`` (the peer's sending thread reads both)."""

    muted: bool
    lock: threading.Lock

    def silence(self) -> None:
        with self.lock:
            self.muted = True

    def restore(self) -> None:
        with self.lock:
            self.muted = False


class ModbusPeer(Peer):
    """The slaves of a Modbus bus: a :class:`chcos.apps.sim.modbus_slave.ModbusSlave` over a
    store holding exactly the map's entries (and the scale-factor registers they name), as one
    TCP device or a gateway as the bus's ``server`` says. Reached in-process (``direct``,
    rewritten maps: no socket), or over a socket: a TCP server, or RTU frames over TCP (the
    bus's ``socket://127.0.0.1:PORT``), started by :meth:`serve`."""

    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool,
                 direct: bool = True) -> None:
        from chcos.devices.options import parsed
        from drivers.codecs.modbus import scale_factor_point
        from drivers.codecs.modbus_options import RtuOptions, TcpOptions, point_of

        self.points = {d.name: point_of(d) for d in devices}
        pts = list(self.points.values())
        pts += [scale_factor_point(p) for p in pts if p.scale_factor is not None]
        units = sorted({p.unit for p in pts if not p.broadcast}) or [1]
        spans: dict[int, dict[str, list[tuple[int, int]]]] = {u: {} for u in units}
        for p in pts:  # only the mapped addresses exist, per unit (64512 costs one entry)
            for u in (units if p.broadcast else [p.unit]):
                spans[u].setdefault(p.table, []).append((p.address, p.size))
        self.store = RegisterStore(unit_spans=spans)
        framer: Literal["tcp", "rtu"] = "tcp" if bus.kind == "modbus-tcp" else "rtu"
        kind = TcpOptions if framer == "tcp" else RtuOptions
        config = bus.config if isinstance(bus.config, kind) else parsed(
            kind, bus.options, bus.key, bus.file)
        role = config.server_kind(set(units)) if isinstance(config, TcpOptions) else "gateway"
        self.slave = ModbusSlave(self.store, framer, role)
        self.server: ModbusSimServer | None = None
        self.direct = ""
        if rewrite and direct:
            self.direct = f"chcos-sim-{bus.name}-{os.getpid()}-{next(_channels)}"
            register(self.direct, self.slave)
            self.bus = dataclasses.replace(bus, options={**bus.options, "direct": self.direct},
                                           config=dataclasses.replace(config,
                                                                      direct=self.direct))
            return
        host, port, options = self._address(bus, framer, rewrite)
        self.bus = dataclasses.replace(bus, options=options, config=None)
        self.server = ModbusSimServer(self.store, port, host=host, framer=framer,
                                      slave=self.slave)
        if rewrite:
            self.server.start()

    @staticmethod
    def _address(bus: BusSpec, framer: str, rewrite: bool) -> tuple[str, int, dict[str, Any]]:
        """Where a socket server listens, and the bus's options pointed there."""
        options = dict(bus.options)
        if rewrite:
            port = free_port()
            if framer == "tcp":
                options.update(host="127.0.0.1", port=port)
            else:
                options["port"] = f"socket://127.0.0.1:{port}"
            return "127.0.0.1", port, options
        if framer == "tcp":
            host, port = str(options["host"]), int(options.get("port", 502))
            if host not in LOOPBACK:
                raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): host {host!r}: a "
                                  "simulated slave listens on loopback only (expected "
                                  "127.0.0.1)")
            return host, port, options
        m = re.fullmatch(r"socket://(127\.0\.0\.1|localhost):(\d+)", str(options["port"]))
        if not m:
            raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): port "
                              f"{options['port']!r}: a simulated RTU slave needs "
                              "socket://127.0.0.1:PORT")
        return "127.0.0.1", int(m.group(2)), options

    def serve(self) -> None:
        if self.server is not None:
            self.server.start()

    def set(self, device: DeviceSpec, raw: Any) -> None:
        p = self.points[device.name]
        if p.scale_factor is not None:
            raw = raw / 10.0 ** self._factor(p)
        if p.type not in ("bool", "string") and not p.type.startswith("float"):
            raw = round(raw)
        for unit in self._units_of(p):      # a broadcast address: every unit's
            self.store.set_value(unit, p.table, p.address, raw, p.type, p.word_order, p.count)

    def _units_of(self, p: Any) -> list[int]:
        return list(self.store.units) if p.broadcast else [p.unit]

    def get(self, device: DeviceSpec) -> Any:
        p = self.points[device.name]
        value = self.store.get_value(self._units_of(p)[0], p.table, p.address, p.type,
                                     p.word_order, p.count)
        if p.scale_factor is not None:
            return value * 10.0 ** self._factor(p)
        return value

    def _factor(self, p: Any) -> int:
        return int(self.store.get_value(self._units_of(p)[0], p.table, p.scale_factor, "int16"))

    def silence(self) -> None:
        if self.server is not None:
            self.server.stop()
        self.slave.silence()

    def restore(self) -> None:
        self.slave.restore()
        if self.server is not None:
            self.server.start()

    def describe(self) -> str:
        kind = "Modbus TCP" if self.slave.framing == "tcp" else "Modbus RTU"
        if self.server is None:
            return f"{kind} {self.slave.role if kind == 'Modbus TCP' else 'line'} in-process " \
                   f"({self.direct})"
        over = "" if self.slave.framing == "tcp" else " over TCP"
        return f"{kind} server{over} on {self.server.host}:{self.server.port}"

    def close(self) -> None:
        if self.server is not None:
            self.server.stop()
        if self.direct:
            unregister(self.direct)


def can_args(options: Any, rewrite: bool, tag: str) -> dict[str, Any]:
    if rewrite:
        return {"interface": "virtual",
                "channel": f"chcos-sim-{tag}-{os.getpid()}-{next(_channels)}"}
    args = {k: options[k] for k in ("interface", "channel", "bitrate", "port") if k in options}
    if "interface" not in args or "channel" not in args:
        import can

        cfg = can.util.load_config()
        args.setdefault("interface", cfg.get("interface"))
        args.setdefault("channel", cfg.get("channel"))
    return args


def on_channel(options: Any, args: dict[str, Any]) -> dict[str, Any]:
    """A CAN or CANopen bus's options moved to the private channel ``args`` of
    :func:`can_args` (``rewrite``): the map's interface and channel replaced, its
    ``udp_multicast`` port dropped (it names the map's own group, not the private channel)."""
    return {**{k: v for k, v in options.items() if k != "port"}, **args}


def cia402_eds(eds: Any, node: int) -> bool:
    """True when the EDS at ``eds`` describes a CiA 402 drive (0x6040, 0x6041, 0x6060), read
    as the simulated node reads it; an unreadable EDS is left to the node to refuse."""
    from chcos.devices.eds_file import read_eds
    from chcos.devices.importers.cia402 import is_cia402

    try:
        return is_cia402(read_eds(eds, node).od)
    except ValueError:
        return False


class CanopenPeer(Peer):
    """Per node of the bus, on the tick clock (virtual time stays deterministic), a
    :class:`chcos.apps.sim.cia402_drive.Cia402Drive` when the node's EDS is a CiA 402 drive's
    (the state machine answers the controlword; 0x605A as the EDS says), else a
    :class:`chcos.apps.sim.canopen_slave.CanopenSlave` without a plant (values come from
    :meth:`set` and scripts). Both are as strict as CiA 301 devices (``docs/canopen-sim.md``)
    and send a heartbeat every third of the node's ``heartbeat_timeout`` (none without it),
    TPDOs on change, event timer and SYNC, every timer on the slaves' clock.
    :meth:`node` hands a node to fault scripts."""

    def __init__(self, bus: BusSpec, devices: tuple[DeviceSpec, ...], rewrite: bool) -> None:
        from chcos.apps.sim.canopen_slave import CanopenSlave, Clock
        from chcos.apps.sim.cia402_drive import Cia402Drive
        from drivers.codecs.canopen import eds_path

        self.args = can_args(bus.options, rewrite, bus.name)
        options = on_channel(bus.options, self.args) if rewrite else dict(bus.options)
        self.bus = dataclasses.replace(bus, options=options)
        self.slaves: dict[int, Any] = {}
        self.last = 0.0
        # what the map's axes say the drive holds in 0x605A: the simulated drive holds it
        held: dict[int, int] = {}
        for d in devices:
            config = d.address.get("config") if is_axis_address(d.address) else None
            if isinstance(config, dict) and "quick_stop_option" in config \
                    and int(d.address.get("axis", 0)) == 0:
                held[int(d.address["node"])] = int(config["quick_stop_option"])
        port = int(self.args["port"]) if "port" in self.args else None
        try:
            for node in bus.options.get("nodes", []):
                nid = int(node["id"])
                timeout = float(node.get("heartbeat_timeout") or 0)
                eds = eds_path(bus, str(node["eds"]))
                slave: CanopenSlave
                if cia402_eds(eds, nid):
                    slave = Cia402Drive(nid, eds, channel=str(self.args["channel"]),
                                        interface=str(self.args["interface"]),
                                        port=port, heartbeat_period=timeout / 3, clock=Clock.TICK,
                                        quick_stop_option=held.get(nid))
                else:
                    slave = CanopenSlave(nid, eds, channel=str(self.args["channel"]),
                                         interface=str(self.args["interface"]),
                                         port=port, heartbeat_period=timeout / 3, clock=Clock.TICK,
                                         servo=False)
                self.slaves[nid] = slave
                slave.start()
        except BaseException:
            self.close()
            raise

    def node(self, node_id: int) -> Any:
        """The simulated node ``node_id`` (a ``CanopenSlave``); raises ConfigError naming the
        bus's nodes for another id."""
        try:
            return self.slaves[node_id]
        except KeyError:
            raise ConfigError(f"bus {self.bus.name!r} has no simulated CANopen node "
                              f"{node_id} (nodes: {', '.join(map(str, self.slaves))})") from None

    def _slave(self, device: DeviceSpec) -> tuple[Any, int, int]:
        a = device.address
        return self.slaves[int(a["node"])], int(a["index"]), int(a.get("subindex", 0))

    def set(self, device: DeviceSpec, raw: Any) -> None:
        if is_axis_address(device.address):
            raise DeviceError(f"{device.name!r} is a CiA 402 axis: the simulated drive owns "
                              "its values; command the axis, or inject a fault on "
                              "slaves.canopen_node(bus, node)")
        slave, index, sub = self._slave(device)
        if slave.data_type(index, sub) not in float_types():
            raw = round(raw) if not isinstance(raw, bool) else raw
        slave.set(index, sub, raw)

    def get(self, device: DeviceSpec) -> Any:
        if is_axis_address(device.address):
            return self._axis_value(device)
        slave, index, sub = self._slave(device)
        return slave.get(index, sub)

    def _axis_value(self, device: DeviceSpec) -> Any:
        """What the simulated drive holds for an axis device, in drive units: the actuator and
        ``.state`` the state's name, ``.statusword``, ``.mode`` (0x6061), ``.position`` and
        ``.velocity`` (counts), ``.fault`` (0x603F)."""
        from chcos.apps.sim.cia402_drive import Cia402Drive
        from drivers.codecs.cia402 import AxisReading, decode_state

        slave = self.slaves[int(device.address["node"])]
        if not isinstance(slave, Cia402Drive):
            raise DeviceError(f"{device.name!r}: node {slave.node_id} is not simulated as a "
                              "CiA 402 drive (its EDS lacks 0x6040, 0x6041 or 0x6060)")
        base = 0x800 * int(device.address.get("axis", 0))
        statusword = slave.value(0x6041 + base)
        reading = device.address.get("reading", AxisReading.STATE.value)
        values = {AxisReading.STATE.value: decode_state(statusword).name,
                  AxisReading.STATUSWORD.value: statusword,
                  AxisReading.MODE.value: slave.value(0x6061 + base),
                  AxisReading.POSITION.value: slave.value(0x6064 + base),
                  AxisReading.VELOCITY.value: slave.value(0x606C + base),
                  AxisReading.FAULT.value: slave.value(0x603F + base)}
        return values[str(reading)]

    def tick(self, now: float) -> None:
        """Each node's time to ``now`` (its own time, not a sum of rounded steps: its timers
        are due at the kernel's times)."""
        self.last = now
        for slave in self.slaves.values():
            slave.tick(max(0.0, now - slave.now()))

    def settle(self, timeout: float) -> bool:
        """Every node has handled every frame sent to it so far (see
        :meth:`chcos.apps.sim.canopen_slave.CanopenSlave.settle`)."""
        return all([slave.settle(timeout) for slave in self.slaves.values()])

    def handled(self) -> int:
        return sum(slave.activity for slave in self.slaves.values())

    def silence(self) -> None:
        for slave in self.slaves.values():
            slave.silence()

    def restore(self) -> None:
        for slave in self.slaves.values():
            slave.restore()

    def describe(self) -> str:
        return (f"CANopen node(s) {', '.join(str(n) for n in self.slaves)} on "
                f"{self.args.get('interface')} channel {self.args.get('channel')}")

    def close(self) -> None:
        for slave in self.slaves.values():
            slave.stop()


def float_types() -> tuple[int, ...]:
    from canopen.objectdictionary import FLOAT_TYPES

    return tuple(FLOAT_TYPES)
