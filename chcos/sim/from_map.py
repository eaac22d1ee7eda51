"""from_map - simulated slaves for any device map, so a user's own cell runs without its hardware.

:func:`simulate` takes a validated :class:`~chcos.devspec.DeviceMap` and starts, per bus, a peer
that answers the bus's devices on the real protocol, on loopback only:

* ``modbus-tcp`` - a pymodbus server (:class:`chcos.sim.modbus_server.ModbusSimServer`) on a free
  127.0.0.1 port holding every mapped register, coil and input;
* ``modbus-rtu`` - the same server speaking RTU framing over a TCP socket (the bus's ``port``
  becomes ``socket://127.0.0.1:PORT``);
* ``memory``, ``signal``, ``weld-direct`` - in-process already; kept as they are.

It returns the map rewritten to point at those peers (the user's files are not touched) and a
:class:`SimSlaves` handle: :meth:`SimSlaves.set` puts a sensor's value (engineering units, the
map's scale and offset applied backwards) into the peer, :meth:`SimSlaves.get` reads what the
system last wrote to an actuator, :meth:`SimSlaves.silence` and :meth:`SimSlaves.restore` make a
bus's peer stop and start answering (fault injection). Buses of other kinds (``can``,
``canopen``, ``serial``) raise :class:`chcos.errors.ConfigError` naming the bus: their peers from
a map are not built yet.
"""

from __future__ import annotations

import dataclasses
import socket
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from chcos.devspec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ConfigError, DeviceError
from chcos.sim.modbus_server import ModbusSimServer, RegisterStore

IN_PROCESS = ("memory", "signal", "weld-direct")
"""Bus kinds that need no simulated peer."""
SIMULATED = ("modbus-tcp", "modbus-rtu", *IN_PROCESS)
"""Bus kinds :func:`simulate` can stand in for."""


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@dataclass
class _ModbusPoint:
    store: RegisterStore
    unit: int
    table: str
    address: int
    type: str
    word_order: Any


@dataclass
class SimSlaves:
    """The simulated peers of one device map (see the module doc). Close with :meth:`close`."""

    devmap: DeviceMap
    specs: dict[str, DeviceSpec] = dataclasses.field(default_factory=dict)
    servers: dict[str, ModbusSimServer] = dataclasses.field(default_factory=dict)
    _points: dict[str, _ModbusPoint] = dataclasses.field(default_factory=dict)
    _closers: list[Callable[[], None]] = dataclasses.field(default_factory=list)

    def simulated(self, device: str) -> bool:
        """True if ``device`` has a simulated peer that :meth:`set`/:meth:`get` reach."""
        return device in self._points

    def _point(self, device: str) -> _ModbusPoint:
        if device not in self.specs:
            raise DeviceError(f"no device named {device!r} in the device map")
        try:
            return self._points[device]
        except KeyError:
            raise DeviceError(f"device {device!r} is on a {self._kind(device)} bus, which is "
                              "in-process: use inject instead") from None

    def _kind(self, device: str) -> str:
        return self.devmap.bus(self.specs[device].bus).kind

    def set(self, device: str, value: Any) -> None:
        """Put ``value`` (engineering units) where the peer serves ``device``; the system reads
        it at its next poll. Raises DeviceError for an unknown or in-process device and
        ConfigError if the raw value does not fit the register type."""
        p = self._point(device)
        spec = self.specs[device]
        raw = value
        if isinstance(value, int | float) and not isinstance(value, bool) and p.type != "bool":
            raw = (value - spec.offset) / spec.scale
            if not p.type.startswith("float"):
                raw = round(raw)
        p.store.set_value(p.unit, p.table, p.address, raw, p.type, p.word_order)

    def get(self, device: str) -> Any:
        """What the peer holds for ``device``, in engineering units (an actuator: the last value
        the system wrote). Raises DeviceError for an unknown or in-process device."""
        p = self._point(device)
        spec = self.specs[device]
        raw = p.store.get_value(p.unit, p.table, p.address, p.type, p.word_order)
        if isinstance(raw, bool) or p.type == "bool":
            return bool(raw)
        return raw * spec.scale + spec.offset

    def silence(self, bus: str) -> None:
        """Make the peer of ``bus`` stop answering (its port closes). Raises DeviceError if the
        bus has no simulated peer."""
        self._server(bus).stop()

    def restore(self, bus: str) -> None:
        """Make the peer of ``bus`` answer again, with the values it held."""
        self._server(bus).start()

    def _server(self, bus: str) -> ModbusSimServer:
        try:
            return self.servers[bus]
        except KeyError:
            raise DeviceError(f"bus {bus!r} has no simulated peer (simulated: "
                              f"{', '.join(sorted(self.servers)) or 'none'})") from None

    def close(self) -> None:
        """Stop every peer. Idempotent."""
        while self._closers:
            self._closers.pop()()


def _modbus(bus: BusSpec, devices: tuple[DeviceSpec, ...], slaves: SimSlaves) -> BusSpec:
    from drivers.modbus import point_of

    points = [point_of(d) for d in devices]
    units = sorted({p.unit for p in points}) or [1]
    size = max([p.address + p.size for p in points] + [16])
    store = RegisterStore(units, size=size)
    port = free_port()
    framer: Literal["tcp", "rtu"] = "tcp" if bus.kind == "modbus-tcp" else "rtu"
    server = ModbusSimServer(store, port, framer=framer)
    server.start()
    slaves._closers.append(server.stop)
    slaves.servers[bus.name] = server
    for d, p in zip(devices, points, strict=True):
        slaves._points[d.name] = _ModbusPoint(store, p.unit, p.table, p.address, p.type,
                                              p.word_order)
        if d.direction == "actuator" and d.safe_value is not None:
            slaves.set(d.name, d.safe_value)  # an idle output holds its safe value
    options = dict(bus.options)
    if framer == "tcp":
        options.update(host="127.0.0.1", port=port)
    else:
        options["port"] = f"socket://127.0.0.1:{port}"
    return dataclasses.replace(bus, options=options)


def simulate(devmap: DeviceMap) -> SimSlaves:
    """Start a simulated peer for every bus of ``devmap`` that has devices; returns the handle,
    whose ``devmap`` is the map pointed at the peers. Raises ConfigError naming the bus and its
    file for a bus kind without a simulated peer, BusError if a peer cannot listen."""
    for bus in devmap.buses:
        if bus.kind not in SIMULATED and devmap.devices_on(bus.name):
            raise ConfigError(f"{bus.file}: {bus.key} ({bus.name}): no simulated peer for a "
                              f"{bus.kind!r} bus yet (simulated kinds: {', '.join(SIMULATED)})")
    slaves = SimSlaves(devmap, {d.name: d for d in devmap.devices})
    buses: list[BusSpec] = []
    try:
        for bus in devmap.buses:
            devs = devmap.devices_on(bus.name)
            if bus.kind in ("modbus-tcp", "modbus-rtu") and devs:
                buses.append(_modbus(bus, devs, slaves))
            else:
                buses.append(bus)
    except BaseException:
        slaves.close()
        raise
    slaves.devmap = dataclasses.replace(devmap, buses=tuple(buses))
    return slaves
