"""spec - what a device map says: buses and devices, as frozen records.

Loaded and validated by :mod:`chcos.devices.devmap`; consumed by the device manager
(:mod:`chcos.devices.devtab`)
and by the bus drivers (:mod:`drivers`). Values here are already checked; nothing in this module
raises.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal

Direction = Literal["sensor", "actuator"]

#: Machine (satellite) numbers are 0..MAX_MACHINE, in device maps and host commands alike.
MAX_MACHINE = 9999


@dataclass(frozen=True)
class BusSpec:
    """One field bus: its name (unique in the system), its kind (the driver registry key: ``can``,
    ``canopen``, ``modbus-tcp``, ``modbus-rtu``, ``serial``, ``memory``, ``signal``...), the
    kind-specific options as written in the file, and where it was declared (``file`` and the key
    path, e.g. ``bus[2]``) so later errors can point back at it."""

    name: str
    kind: str
    options: Mapping[str, Any] = field(default_factory=dict)
    file: str = "<memory>"
    key: str = "bus[?]"
    #: ``options`` parsed into the driver's option dataclass (:mod:`chcos.devices.options`) when
    #: the map was checked; None where the kind declares none or the spec was built in code
    #: (the driver then parses ``options`` itself, see
    #: :meth:`chcos.devices.driver.Driver.bus_options`)
    config: Any = field(default=None, compare=False, repr=False)

    def with_options(self, options: Mapping[str, Any]) -> BusSpec:
        """This bus with ``options`` instead of its own: the config parsed from the file goes
        with them (``dataclasses.replace(bus, options=...)`` would keep it, stale), so the driver
        parses the new ones."""
        return dataclasses.replace(self, options=options, config=None)


@dataclass(frozen=True)
class DeviceSpec:
    """One sensor (input) or actuator (output) of Devtab.

    ``address`` is bus-specific (CAN id + signal, CANopen node + index/subindex, Modbus table +
    address, serial field...). A sensor's engineering value is ``raw * scale + offset``; an
    actuator's raw bus value is ``(value - offset) / scale``. ``limits`` are engineering units, both
    ends inclusive, ``None`` for open. ``stale_after`` is seconds without fresh data before a sensor
    is marked stale (``None``: never). ``safe_value`` is written to an actuator on e-stop, on
    abnormal completion of its owning task, and on shutdown (``None``: nothing is written).
    ``priority`` is the interrupt priority 0..99 of the device's sensory link. ``round`` (actuators
    only) lets Devtab round the raw value to the nearest integer before the driver gets it; without
    it a value an integer address cannot carry exactly is refused at write.
    ``north_writable`` lets the north-side facades command the actuator.
    """

    name: str
    direction: Direction
    machine: int
    bus: str
    address: Mapping[str, Any] = field(default_factory=dict)
    priority: int = 8
    stale_after: float | None = None
    scale: float = 1.0
    offset: float = 0.0
    limits: tuple[float | None, float | None] = (None, None)
    safe_value: float | None = None
    units: str = ""
    file: str = "<memory>"
    key: str = "device[?]"
    round: bool = False
    #: the north side (Modbus facade, OPC UA) may command this actuator (limits and owner rules
    #: still apply); default False: read-only from above
    north_writable: bool = False
    #: why the actuator has no safe value (``safe_value = "none"`` in the map, e.g. a target
    #: position, where any value would move the machine); "" when it has one or none was said
    safe_reason: str = ""
    #: ``address`` parsed into the driver's address dataclass when the map was checked (see
    #: :attr:`BusSpec.config`); None where the kind declares none or the spec was built in code
    addr: Any = field(default=None, compare=False, repr=False)


@dataclass(frozen=True)
class DeviceMap:
    """Everything loaded from one or more device-map files, validated as a whole."""

    buses: tuple[BusSpec, ...] = ()
    devices: tuple[DeviceSpec, ...] = ()
    files: tuple[str, ...] = ()
    #: What ``chcos check`` warns about: legal, but bound to misbehave (``file:line: key: ...``).
    warnings: tuple[str, ...] = ()

    def bus(self, name: str) -> BusSpec:
        """Return the bus called ``name``; raises KeyError if there is none."""
        for b in self.buses:
            if b.name == name:
                return b
        raise KeyError(name)

    def devices_on(self, bus: str) -> tuple[DeviceSpec, ...]:
        """The devices attached to bus ``bus``, in file order."""
        return tuple(d for d in self.devices if d.bus == bus)

    def merged(self, other: DeviceMap) -> DeviceMap:
        """This map with ``other`` appended (no validation; see
        :func:`chcos.devices.devmap.load`)."""
        return DeviceMap(self.buses + other.buses, self.devices + other.devices,
                         self.files + other.files, self.warnings + other.warnings)
