"""cia402 (importer) - recognise a CiA 402 drive in an EDS and choose what each axis needs.

A drive is recognised by 0x6040 (controlword), 0x6041 (statusword) and 0x6060 (modes of
operation), at 0x800 per axis for multi-axis drives. For each axis :func:`detect_axes` picks
the objects an axis uses - statusword, controlword, modes and modes display, position and
velocity actual, target position and velocity, error code 0x603F, quick stop option code
0x605A, profile velocity - with the PDOs that carry them, and says what a user must know:
an object mapped into several RPDOs (they must be sent from one image), synchronous TPDOs (the
bus needs ``sync_period``), objects read by SDO because no PDO maps them, set-points without a
safe value. The EDS importer (:mod:`.eds`, ``chcos import eds``) writes one
``profile = "cia402"`` device per axis the CANopen driver can host (:func:`hostable`,
:func:`axis_device`); :func:`axis_draft` writes an axis's objects as plain devices instead (the
set-points with ``safe_value = "none"`` and the reason, :func:`no_safe_value`).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any

from chcos.devices.importers.draft import Hex, MapDraft
from chcos.errors import ConfigError

#: Index offset between the axes of a multi-axis drive.
AXIS_OFFSET = 0x800
#: The objects that make an object dictionary a CiA 402 drive's (axis 0).
SIGNATURE = (0x6040, 0x6041, 0x6060)


class Role(Enum):
    """What an object is for in an axis: (index of axis 0, direction, required)."""

    STATUSWORD = (0x6041, "sensor", True)
    CONTROLWORD = (0x6040, "actuator", True)
    MODES = (0x6060, "actuator", True)
    MODES_DISPLAY = (0x6061, "sensor", True)
    POSITION_ACTUAL = (0x6064, "sensor", False)
    VELOCITY_ACTUAL = (0x606C, "sensor", False)
    ERROR_CODE = (0x603F, "sensor", False)
    TARGET_POSITION = (0x607A, "actuator", False)
    TARGET_VELOCITY = (0x60FF, "actuator", False)
    PROFILE_VELOCITY = (0x6081, "actuator", False)
    QUICK_STOP_OPTION = (0x605A, "actuator", False)

    @property
    def index(self) -> int:
        """The object's index for axis 0."""
        return int(self.value[0])

    @property
    def direction(self) -> str:
        """``sensor`` (read from the drive) or ``actuator`` (written to it)."""
        return str(self.value[1])

    @property
    def required(self) -> bool:
        """Whether an axis cannot work without it."""
        return bool(self.value[2])


#: Why a set-point has no safe value: the reason the map carries instead of one.
NO_SAFE_VALUE = {
    Role.TARGET_POSITION: "no safe value: writing 0 would send the axis to position 0; the "
                          "axis's safe action is its stop sequence",
    Role.TARGET_VELOCITY: "no safe value of its own: the axis's stop sequence stops it",
    Role.PROFILE_VELOCITY: "no safe value: a profile parameter, not a command",
    Role.MODES: "no safe value: the mode is kept; the stop sequence acts through the "
                "controlword",
    Role.QUICK_STOP_OPTION: "no safe value: a configuration written once",
}
def no_safe_value(index: int) -> str | None:
    """Why the CiA 402 object ``index`` (at any axis's offset) has no safe value, or None
    when it may have one: the set-points and configuration of :data:`NO_SAFE_VALUE`."""
    base = 0x6000 + (index - 0x6000) % AXIS_OFFSET if 0x6000 <= index < 0x6000 + 8 * \
        AXIS_OFFSET else index
    role = next((r for r in NO_SAFE_VALUE if r.index == base), None)
    return NO_SAFE_VALUE[role] if role is not None else None


#: CANopen integer data types -> the range they carry (limits for the actuators).
TYPE_RANGES = {0x0002: (-0x80, 0x7F), 0x0003: (-0x8000, 0x7FFF),
               0x0004: (-0x8000_0000, 0x7FFF_FFFF), 0x0005: (0, 0xFF), 0x0006: (0, 0xFFFF),
               0x0007: (0, 0xFFFF_FFFF)}
CONTROLWORD_SAFETY = ("safe action: the axis's sequence (quick stop 0x02, then disable voltage "
                      "0x00 once stopped), not a single value")


@dataclass(frozen=True)
class Pdo:
    """One PDO that maps an object."""

    kind: str            # "TPDO" or "RPDO"
    number: int          # 1-based
    cob_id: int
    transmission: int    # 0 acyclic sync, 1..240 every n-th SYNC, 254/255 event
    event_timer: int     # ms, 0: none

    @property
    def synchronous(self) -> bool:
        """Sent on SYNC (transmission types 0..240)."""
        return self.transmission <= 240

    def __str__(self) -> str:
        return f"{self.kind}{self.number} (COB-ID 0x{self.cob_id:03X})"


@dataclass(frozen=True)
class AxisObject:
    """An object an axis uses, as the EDS describes it."""

    role: Role
    index: int
    subindex: int
    name: str
    data_type: int
    access: str
    default: int | None
    pdos: tuple[Pdo, ...]


@dataclass(frozen=True)
class DriveAxis:
    """One axis of a CiA 402 drive found in an EDS: its objects and what a user must know."""

    node: int
    axis: int
    objects: dict[Role, AxisObject]
    notes: tuple[str, ...] = field(default=())
    quick_stop_option: int | None = None
    #: drive counts per user unit from the factor group (None: the EDS does not say)
    counts_per_unit: float | None = None

    @property
    def warnings(self) -> tuple[str, ...]:
        """The notes that need the user's action (starting with ``warning:``)."""
        return tuple(n for n in self.notes if n.startswith("warning:"))


def load(path: str | Path, node: int) -> Any:
    """The object dictionary of node ``node`` from the EDS at ``path`` (canopen's import).
    Raises :class:`ConfigError` naming the file if it cannot be read."""
    from chcos.devices.eds_file import read_eds

    if not 1 <= node <= 127:
        raise ConfigError(f"--node {node}: expected a CANopen node id 1..127")
    try:
        return read_eds(path, node).od   # tolerant: vendor files leave numeric fields empty
    except ValueError as exc:
        raise ConfigError(f"{path}: not a readable EDS: {exc}") from exc


def _variable(od: Any, index: int, sub: int = 0) -> Any:
    try:
        return od.get_variable(index, sub)
    except Exception:   # canopen raises KeyError or returns None for an absent object
        return None


def _int(od: Any, index: int, sub: int) -> int | None:
    var = _variable(od, index, sub)
    if var is None or var.default is None:
        return None
    try:
        return int(var.default)
    except (TypeError, ValueError):
        return None


def is_cia402(od: Any, axis: int = 0) -> bool:
    """True when ``od`` has the CiA 402 signature objects (0x6040, 0x6041, 0x6060) of
    ``axis``."""
    return all(_variable(od, i + AXIS_OFFSET * axis) is not None for i in SIGNATURE)


def pdos_of(od: Any) -> dict[tuple[int, int], list[Pdo]]:
    """Every enabled PDO of the EDS by the objects it maps: (index, sub) -> PDOs."""
    out: dict[tuple[int, int], list[Pdo]] = {}
    for kind, comm, mapping in (("TPDO", 0x1800, 0x1A00), ("RPDO", 0x1400, 0x1600)):
        for n in range(512):
            cob = _int(od, comm + n, 1)
            if cob is None or cob & 0x8000_0000 or _variable(od, mapping + n, 0) is None:
                continue
            kind_of_sending = _int(od, comm + n, 2)
            pdo = Pdo(kind, n + 1, cob & 0x1FFF_FFFF,
                      255 if kind_of_sending is None else kind_of_sending,
                      _int(od, comm + n, 5) or 0)
            for sub in range(1, min(_int(od, mapping + n, 0) or 0, 64) + 1):  # CiA 301: 64
                entry = _int(od, mapping + n, sub)
                if entry and entry >> 16 >= 0x1000:
                    out.setdefault((entry >> 16, (entry >> 8) & 0xFF), []).append(pdo)
    return out


def detect_axes(od: Any, node: int) -> list[DriveAxis]:
    """The CiA 402 axes of ``od`` (node ``node``), each with its objects and notes; empty when
    the dictionary is no CiA 402 drive's."""
    pdos = pdos_of(od)
    axes = []
    for axis in range(8):
        if not is_cia402(od, axis):
            continue
        objects: dict[Role, AxisObject] = {}
        notes: list[str] = []
        for role in Role:
            index = role.index + AXIS_OFFSET * axis
            var = _variable(od, index)
            if var is None:
                if role.required:
                    notes.append(f"warning: 0x{index:04X} ({role.name.lower()}) is missing: "
                                 + ("a mode cannot be confirmed" if role is Role.MODES_DISPLAY
                                    else "the axis cannot work"))
                continue
            mapped = tuple(pdos.get((index, 0), ()))
            objects[role] = AxisObject(role, index, 0, str(var.name), int(var.data_type),
                                       str(var.access_type), _int(od, index, 0), mapped)
            notes.extend(_object_notes(objects[role]))
        option = objects.get(Role.QUICK_STOP_OPTION)
        factor, note = factor_group(od, axis)
        notes.append(note)
        axes.append(DriveAxis(node, axis, objects, tuple(dict.fromkeys(notes)),
                              option.default if option else None, factor))
    return axes


def factor_group(od: Any, axis: int = 0) -> tuple[float | None, str]:
    """Drive counts per user unit from the EDS's factor group, and a note saying how: position
    encoder resolution 0x608F (increments per motor revolution) x gear ratio 0x6091 (motor per
    shaft revolutions) / feed constant 0x6092 (feed per shaft revolution). Without 0x6092 the
    unit is a shaft revolution. (None, why) when the EDS gives no usable defaults."""
    base = AXIS_OFFSET * axis

    def ratio(index: int) -> float | None:
        top, bottom = _int(od, index + base, 1), _int(od, index + base, 2)
        if top is None or bottom is None or top <= 0 or bottom <= 0:
            return None
        return top / bottom

    encoder = ratio(0x608F)
    if encoder is None:
        return None, (f"no position encoder resolution (0x{0x608F + base:04X}) with defaults in "
                      "the EDS: set counts_per_unit (drive counts per mm or per degree)")
    gear = ratio(0x6091)
    feed = ratio(0x6092)
    counts = encoder * (gear if gear is not None else 1.0)
    if feed is None:
        return counts, (f"counts_per_unit = {counts:g} counts per shaft revolution (0x608F"
                        + (", 0x6091" if gear is not None else "")
                        + "; no feed constant 0x6092): divide by 360 for degrees")
    return counts / feed, (f"counts_per_unit = {counts / feed:g} counts per feed unit (0x608F, "
                           + ("0x6091, " if gear is not None else "") + "0x6092)")


def _object_notes(obj: AxisObject) -> list[str]:
    notes = []
    where = f"0x{obj.index:04X} {obj.name}"
    rpdos = [p for p in obj.pdos if p.kind == "RPDO"]
    tpdos = [p for p in obj.pdos if p.kind == "TPDO"]
    if obj.role.direction == "actuator" and len(rpdos) > 1:
        notes.append(f"{where} is mapped in {', '.join(map(str, rpdos))}: every one of them is "
                     "sent from one image (its current value), never a stale copy")
    for pdo in tpdos:
        if pdo.synchronous:
            notes.append(f"warning: {pdo} is synchronous (transmission type {pdo.transmission}):"
                         " set sync_period on the bus, or it is never sent")
    if not obj.pdos and obj.role in (Role.STATUSWORD, Role.CONTROLWORD, Role.MODES_DISPLAY):
        notes.append(f"{where} is in no PDO: read or written by SDO, slower than a PDO")
    if obj.default is None and obj.role.direction == "actuator":
        notes.append(f"{where} has no DefaultValue in the EDS")
    return notes


#: the roles an axis device cannot be hosted without (the CANopen driver's axis checks them)
HOSTED = (Role.STATUSWORD, Role.CONTROLWORD, Role.MODES, Role.MODES_DISPLAY)


def hostable(axis: DriveAxis) -> bool:
    """True when the drive has every object the CANopen driver's axis needs
    (:data:`HOSTED`); without 0x6061 a mode cannot be confirmed, and the importer writes the
    axis's objects as plain devices instead."""
    return all(role in axis.objects for role in HOSTED)


def axis_device(axis: DriveAxis, draft: MapDraft, *, bus: str, machine: int = 0,
                prefix: str = "", several: bool = False) -> tuple[list[str], dict[str, Any]]:
    """One ``profile = "cia402"`` device table for ``axis`` (its comment lines first): node
    and axis, the mode (PP with a target position, else PV, else none), ``counts_per_unit``
    from the factor group (else 1 and a comment asking for it), 0x605A's default as
    ``quick_stop_option``, the safe stop sequence. The notes of :func:`detect_axes` become the
    comments."""
    name = draft.name(f"axis{axis.axis + 1}" if several else "axis", prefix)
    dev: dict[str, Any] = {"name": name, "profile": "cia402", "bus": bus}
    if machine:
        dev["machine"] = machine
    dev["address"] = {"node": axis.node, "axis": axis.axis}
    if Role.TARGET_POSITION in axis.objects:
        dev["mode"] = "PP"
    elif Role.TARGET_VELOCITY in axis.objects:
        dev["mode"] = "PV"
    dev["counts_per_unit"] = axis.counts_per_unit if axis.counts_per_unit else 1.0
    if axis.quick_stop_option is not None:
        dev["quick_stop_option"] = axis.quick_stop_option
    dev["safe_stop"] = "quick_stop_then_disable"
    objects = ", ".join(f"0x{o.index:04X} " + (f"({', '.join(map(str, o.pdos))})" if o.pdos
                                               else "(SDO)")
                        for o in axis.objects.values())
    comments = [f"CiA 402 axis {axis.axis} of node {axis.node}: {objects}",
                "its safe action is the stop sequence (quick stop, then disable voltage once "
                "stopped); tasks command it with ctx.axis(name)",
                *axis.notes]
    return comments, dev


def axis_table(axis: DriveAxis, name: str, *, counts_per_unit: float | None = None,
               mode: str = "PP") -> dict[str, Any]:
    """The ``profile = "cia402"`` axis table for a map: node, axis, mode, units (given, else
    from the factor group, else 1) and the objects it uses (by role)."""
    units = counts_per_unit if counts_per_unit is not None else axis.counts_per_unit
    table: dict[str, Any] = {
        "name": name, "profile": "cia402", "node": axis.node, "axis": axis.axis, "mode": mode,
        "counts_per_unit": units if units is not None else 1.0,
        "objects": {role.name.lower(): Hex(obj.index) for role, obj in axis.objects.items()},
    }
    if axis.quick_stop_option is not None:
        table["quick_stop_option"] = axis.quick_stop_option
    return table


def axis_draft(path: str | Path, node: int, *, bus: str = "canopen", machine: int = 0,
               prefix: str = "", extra: Iterable[int] = (), eds_ref: str | None = None,
               interface: str = "socketcan", channel: str = "can0") -> MapDraft:
    """A map draft with, for each axis of the CiA 402 drive at ``path``, only the objects it
    needs (plus the indices in ``extra``, e.g. from ``--objects``), each with its PDO, the
    notes of :func:`detect_axes` and, for set-points, the reason there is no safe value.
    Raises :class:`ConfigError` naming the file when it is no CiA 402 drive's EDS."""
    od = load(path, node)
    axes = detect_axes(od, node)
    if not axes:
        missing = [f"0x{i:04X}" for i in SIGNATURE if _variable(od, i) is None]
        raise ConfigError(f"{path}: not a CiA 402 drive (no {', '.join(missing)})")
    draft = MapDraft()
    draft.header = [f"CANopen node {node}: CiA 402 drive, {len(axes)} axis/axes, imported "
                    f"from {Path(path).name} by chcos import eds (axis objects only)."]
    bus_table: dict[str, Any] = {"name": bus, "kind": "canopen", "interface": interface,
                                 "channel": channel,
                                 "nodes": [{"id": node, "eds": eds_ref or str(path)}]}
    draft.buses.append(bus_table)
    for axis in axes:
        label = f"{prefix}axis{axis.axis + 1}" if len(axes) > 1 else f"{prefix}axis"
        draft.header += [f"{label}: {n}" for n in axis.notes]
        for role, obj in axis.objects.items():
            dev: dict[str, Any] = {
                "name": draft.name(f"{label}_{role.name.lower()}"),
                "direction": role.direction, "machine": machine, "bus": bus,
                "address": {"node": node, "index": Hex(obj.index), "subindex": obj.subindex}}
            if role.direction == "actuator" and obj.data_type in TYPE_RANGES:
                dev["limits"] = list(TYPE_RANGES[obj.data_type])
            notes = [f"0x{obj.index:04X} {obj.name}: "
                     + (", ".join(map(str, obj.pdos)) if obj.pdos else "SDO")]
            if role is Role.CONTROLWORD:
                notes.append(CONTROLWORD_SAFETY)
            elif role in NO_SAFE_VALUE:
                notes.append(NO_SAFE_VALUE[role])
                dev["safe_value"], dev["safe_reason"] = "none", NO_SAFE_VALUE[role]
            draft.add(notes, dev)
    for index in extra:
        var = _variable(od, index)
        if var is None:
            raise ConfigError(f"{path}: --objects 0x{index:04X}: no such object in the EDS")
        draft.add([f"0x{index:04X} {var.name}: asked for with --objects"],
                  {"name": draft.name(f"{prefix}{var.name}"), "direction": "sensor",
                   "machine": machine, "bus": bus,
                   "address": {"node": node, "index": Hex(index), "subindex": 0}})
    return draft
