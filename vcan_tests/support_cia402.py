"""support_cia402 - a CANopen master hosting a :class:`drivers.codecs.cia402.Axis` for the CiA 402
tests: the canopen library's network on a python-can virtual channel, RPDO frames composed from an
image of every object they map (so a mode write never sends a stale controlword), TPDOs decoded into
readings, reads answered by SDO. It is the shape the CANopen driver takes when it hosts an axis.

Time is virtual: :meth:`Cia402Host.cycle` steps the drive by ``dt``, waits until the drive's
TPDOs have arrived (a condition, no sleep), feeds the axis one reading and sends what it returns,
waiting after each frame until the drive applied it.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import canopen

from drivers.codecs.cia402 import Actions, Axis, AxisConfig, Fault, Obj, Op, Reading, Result

WAIT = 10.0  # seconds to wait for a frame's effect before a test fails


class Drive(Protocol):
    """What the host needs from a simulated drive under test."""

    def step(self, dt: float) -> None: ...
    def published(self) -> tuple[int, int, int, int, int]: ...
    def frames(self) -> int: ...
    def wait(self, predicate: Callable[[], bool], timeout: float = 10.0) -> bool: ...


#: RPDOs of a typical vendor drive: (COB-ID base, mapped objects with struct formats)
RPDOS: dict[Obj, tuple[int, tuple[tuple[Obj, str], ...]]] = {
    Obj.CONTROLWORD: (0x200, ((Obj.CONTROLWORD, "H"),)),
    Obj.MODES: (0x300, ((Obj.CONTROLWORD, "H"), (Obj.MODES, "b"))),
    Obj.TARGET_POSITION: (0x400, ((Obj.CONTROLWORD, "H"), (Obj.TARGET_POSITION, "i"))),
    Obj.TARGET_VELOCITY: (0x500, ((Obj.CONTROLWORD, "H"), (Obj.TARGET_VELOCITY, "i"))),
}
#: SDO data formats of the objects an axis reads
READ_FORMATS = {Obj.STATUSWORD: "<H", Obj.MODES_DISPLAY: "<b", Obj.ERROR_CODE: "<H",
                Obj.POSITION_ACTUAL: "<i", Obj.VELOCITY_ACTUAL: "<i"}


class Cia402Host:
    """One axis on node ``node_id`` of virtual channel ``channel``, hosted as a driver would."""

    def __init__(self, channel: str, node_id: int, drive: Drive, config: AxisConfig,
                 dt: float = 0.01, *, error_code_by_sdo: bool = False) -> None:
        self.node_id = node_id
        self.drive = drive
        self.axis = Axis(config)
        self.dt = dt
        #: leave 0x603F out of the TPDO readings, as for a drive that does not map it
        self.error_code_by_sdo = error_code_by_sdo
        self.now = 0.0
        self.image: dict[Obj, int] = {Obj.CONTROLWORD: 0, Obj.MODES: 0,
                                      Obj.TARGET_POSITION: 0, Obj.TARGET_VELOCITY: 0}
        self.results: list[Result] = []
        self.faults: list[Fault | None] = []
        self.emcys: list[int] = []
        self.sdo_reads: list[Obj] = []
        self._cond = threading.Condition()
        self._view: dict[str, int] = {}
        self.network: Any = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05  # bounds how long close() waits for the notifier
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.node: Any = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
        self.network.add_node(self.node)
        self.network.subscribe(0x180 + node_id, self._on_tpdo1)
        self.network.subscribe(0x280 + node_id, self._on_tpdo2)
        self.network.subscribe(0x80 + node_id, self._on_emcy)

    def close(self) -> None:
        """Disconnect the network."""
        self.network.disconnect()

    def start_node(self) -> None:
        """NMT start; returns when the drive's TPDOs show what it publishes."""
        self.network.send_message(0x000, bytes([0x01, self.node_id]))
        # an SDO answer comes from the thread that applied the NMT frame sent before it
        self.node.sdo.upload(int(Obj.STATUSWORD), 0)
        self.drive.step(0.2)          # the drive's self test and TPDO event timers
        self.settle()

    # -- receiving -----------------------------------------------------------------------------

    def _on_tpdo1(self, can_id: int, data: bytes, timestamp: float) -> None:
        sw, mode, err = struct.unpack("<HbH", bytes(data[:5]))
        with self._cond:
            self._view.update(statusword=sw, mode=mode, error=err)
            self._cond.notify_all()

    def _on_tpdo2(self, can_id: int, data: bytes, timestamp: float) -> None:
        pos, vel = struct.unpack("<ii", bytes(data[:8]))
        with self._cond:
            self._view.update(position=pos, velocity=vel)
            self._cond.notify_all()

    def _on_emcy(self, can_id: int, data: bytes, timestamp: float) -> None:
        (code,) = struct.unpack("<H", bytes(data[:2]))
        with self._cond:
            self.emcys.append(code)
            self._cond.notify_all()

    def _seen(self) -> tuple[int, ...] | None:
        v = self._view
        keys = ("statusword", "mode", "position", "velocity", "error")
        return tuple(v[k] for k in keys) if all(k in v for k in keys) else None

    def settle(self) -> None:
        """Wait until the TPDOs show what the drive publishes now."""
        with self._cond:
            if not self._cond.wait_for(lambda: self._seen() == self.drive.published(), WAIT):
                raise AssertionError(f"TPDOs show {self._seen()}, the drive "
                                     f"{self.drive.published()}")

    def reading(self) -> Reading:
        """The last TPDO values as one reading."""
        with self._cond:
            v = dict(self._view)
        return Reading(statusword=v.get("statusword"), mode_display=v.get("mode"),
                       position=v.get("position"), velocity=v.get("velocity"),
                       error_code=None if self.error_code_by_sdo else v.get("error"))

    # -- sending -------------------------------------------------------------------------------

    def perform(self, actions: Actions) -> None:
        """Send the writes (one RPDO frame each, composed from the image, waiting until the drive
        applied it), answer the reads by SDO, and keep results and faults."""
        for write in actions.writes:
            self.image[write.obj] = write.value
            cob, layout = RPDOS[write.obj]
            data = b"".join(struct.pack("<" + fmt, self.image[obj]) for obj, fmt in layout)
            before = self.drive.frames()
            self.network.send_message(cob + self.node_id, data)
            if not self.drive.wait(lambda b=before: self.drive.frames() > b, WAIT):
                raise AssertionError(f"the drive did not apply {write}")
        self.results.extend(actions.results)
        self.faults.extend(actions.faults)
        if actions.reads:
            values: dict[str, int] = {}
            for obj in actions.reads:
                self.sdo_reads.append(obj)
                raw = self.node.sdo.upload(int(obj), 0)
                (values[obj.name],) = struct.unpack(READ_FORMATS[obj], bytes(raw))
            reading = Reading(statusword=values.get("STATUSWORD"),
                              mode_display=values.get("MODES_DISPLAY"),
                              error_code=values.get("ERROR_CODE"))
            self.perform(self.axis.update(reading, self.now))

    def cycle(self) -> None:
        """One cycle: the drive steps, its TPDOs arrive, the axis takes them and answers."""
        self.now = round(self.now + self.dt, 9)
        self.drive.step(self.dt)
        self.settle()
        self.perform(self.axis.update(self.reading(), self.now))

    def run(self, start: Callable[[float], Actions], limit: float = 60.0) -> Result:
        """Start a command (e.g. ``host.axis.enable``) and cycle until it ends; its result."""
        count = len(self.results)
        self.perform(start(self.now))
        end = self.now + limit
        while True:
            for result in self.results[count:]:
                if not result.reason.startswith("superseded"):
                    return result
            if self.now > end:
                raise AssertionError(f"no result within {limit} s of virtual time")
            self.cycle()

    def idle(self, seconds: float) -> None:
        """Cycle ``seconds`` of virtual time with no command."""
        end = self.now + seconds
        while self.now < end:
            self.cycle()

    def op_results(self, op: Op) -> list[Result]:
        """The results of ``op`` so far."""
        return [r for r in self.results if r.op is op]


# -- EDS files of CiA 402 drives ----------------------------------------------------------------

#: (index, name, data type, access, default or None) of a one-axis CiA 402 drive
DRIVE_OBJECTS: tuple[tuple[int, str, int, str, int | None], ...] = (
    (0x603F, "Error code", 0x0006, "ro", 0),
    (0x6040, "Controlword", 0x0006, "rw", 0),
    (0x6041, "Statusword", 0x0006, "ro", 0),
    (0x605A, "Quick stop option code", 0x0003, "rw", 2),
    (0x6060, "Modes of operation", 0x0002, "rw", 0),
    (0x6061, "Modes of operation display", 0x0002, "ro", 0),
    (0x6064, "Position actual value", 0x0004, "ro", 0),
    (0x6065, "Following error window", 0x0007, "rw", 5000),
    (0x606C, "Velocity actual value", 0x0004, "ro", 0),
    (0x607A, "Target position", 0x0004, "rw", 0),
    (0x6081, "Profile velocity", 0x0007, "rw", 10000),
    (0x6085, "Quick stop deceleration", 0x0007, "rw", 50000),
    (0x60FF, "Target velocity", 0x0004, "rw", 0),
)
#: every RPDO carries the controlword, as vendor drives map them
VENDOR_RPDOS = ((0x6040,), (0x6040, 0x6060), (0x6040, 0x607A), (0x6040, 0x60FF))
VENDOR_TPDOS = ((0x6041, 0x6061, 0x603F), (0x6064, 0x606C))
SIZES = {0x0002: 8, 0x0003: 16, 0x0004: 32, 0x0005: 8, 0x0006: 16, 0x0007: 32}


def drive_eds(*, name: str = "CiA 402 drive", rpdos: tuple[tuple[int, ...], ...] = VENDOR_RPDOS,
              tpdos: tuple[tuple[int, ...], ...] = VENDOR_TPDOS, transmission: int = 255,
              event_timer: int = 100, defaults: bool = True,
              extra: tuple[tuple[int, str, int, str, int | None], ...] = (),
              without: tuple[int, ...] = (),
              records: tuple[tuple[int, str, tuple[tuple[str, int, str, object], ...]],
                             ...] = ()) -> str:
    """The text of an EDS for a one-axis CiA 402 drive: the objects of :data:`DRIVE_OBJECTS`
    (plus ``extra``), the RPDOs/TPDOs given, TPDOs of ``transmission`` type with
    ``event_timer`` ms; ``defaults=False`` leaves the application objects without DefaultValue,
    as some vendor files do; ``without`` leaves objects out; ``records`` adds records (index,
    name, entries from sub-index 1 as (name, data type, access, default))."""
    objects = tuple(o for o in DRIVE_OBJECTS + extra if o[0] not in without)
    kinds = {i: (n, t, a, d) for i, n, t, a, d in objects}
    sections: list[str] = []

    def var(key: str, pname: str, dtype: int, access: str, default: object | None,
            mapping: int = 0) -> None:
        lines = [f"[{key}]", f"ParameterName={pname}", "ObjectType=0x7",
                 f"DataType=0x{dtype:04X}", f"AccessType={access}"]
        if default is not None:
            lines.append(f"DefaultValue={default}")
        lines.append(f"PDOMapping={mapping}")
        sections.append("\n".join(lines))

    def record(index: int, pname: str, subs: list[tuple[str, int, str, object]]) -> None:
        sections.append(f"[{index:04X}]\nParameterName={pname}\nObjectType=0x9\n"
                        f"SubNumber={len(subs)}")
        for n, (sname, dtype, access, default) in enumerate(subs):
            var(f"{index:04X}sub{n}", sname, dtype, access, default)

    var("1000", "Device type", 0x0007, "ro", "0x00020192")
    var("1001", "Error register", 0x0005, "ro", 0)
    var("1017", "Producer heartbeat time", 0x0006, "rw", 0)
    record(0x1018, "Identity object", [("Highest sub-index supported", 0x0005, "ro", 2),
                                       ("Vendor-ID", 0x0007, "ro", "0x000000AB"),
                                       ("Product code", 0x0007, "ro", "0x00000402")])
    pdo_indices = []
    for n, mapped in enumerate(rpdos):
        record(0x1400 + n, f"RPDO{n + 1} communication parameter",
               [("Highest sub-index supported", 0x0005, "ro", 2),
                ("COB-ID used by RPDO", 0x0007, "rw", f"$NODEID+0x{0x200 + 0x100 * n:X}"),
                ("Transmission type", 0x0005, "rw", 255)])
        record(0x1600 + n, f"RPDO{n + 1} mapping parameter",
               [("Number of mapped objects", 0x0005, "rw", len(mapped))]
               + [(f"Mapped object {k + 1}", 0x0007, "rw",
                   f"0x{i:04X}00{SIZES[kinds[i][1]]:02X}") for k, i in enumerate(mapped)])
        pdo_indices += [0x1400 + n, 0x1600 + n]
    for n, mapped in enumerate(tpdos):
        record(0x1800 + n, f"TPDO{n + 1} communication parameter",
               [("Highest sub-index supported", 0x0005, "ro", 5),
                ("COB-ID used by TPDO", 0x0007, "rw", f"$NODEID+0x{0x180 + 0x100 * n:X}"),
                ("Transmission type", 0x0005, "rw", transmission),
                ("Inhibit time", 0x0006, "rw", 0),
                ("Compatibility entry", 0x0005, "rw", 0),
                ("Event timer", 0x0006, "rw", event_timer)])
        record(0x1A00 + n, f"TPDO{n + 1} mapping parameter",
               [("Number of mapped objects", 0x0005, "rw", len(mapped))]
               + [(f"Mapped object {k + 1}", 0x0007, "rw",
                   f"0x{i:04X}00{SIZES[kinds[i][1]]:02X}") for k, i in enumerate(mapped)])
        pdo_indices += [0x1800 + n, 0x1A00 + n]
    for index, pname, dtype, access, default in objects:
        var(f"{index:04X}", pname, dtype, access, default if defaults else None, 1)
    for index, pname, entries in records:
        record(index, pname, [("Highest sub-index supported", 0x0005, "ro", len(entries)),
                              *entries])
    optional = [0x1017] + pdo_indices + [i for i, *_ in objects if i < 0x2000 or i >= 0x6000] \
        + [i for i, *_ in records]
    manufacturer = [i for i, *_ in objects if 0x2000 <= i < 0x6000]
    head = [
        "[FileInfo]", f"FileName={name.replace(' ', '_')}.eds", "FileVersion=1",
        "FileRevision=1", "EDSVersion=4.0", f"Description={name}",
        "", "[DeviceInfo]", "VendorName=Example Motion", "VendorNumber=0x000000AB",
        f"ProductName={name}", "ProductNumber=0x00000402", "RevisionNumber=0x00010000",
        "BaudRate_500=1", "BaudRate_1000=1", "SimpleBootUpSlave=1", "Granularity=8",
        f"NrOfRXPDO={len(rpdos)}", f"NrOfTXPDO={len(tpdos)}", "LSS_Supported=0",
        "", "[MandatoryObjects]", "SupportedObjects=3", "1=0x1000", "2=0x1001", "3=0x1018",
        "", "[OptionalObjects]", f"SupportedObjects={len(optional)}",
        *[f"{k + 1}=0x{i:04X}" for k, i in enumerate(optional)],
        "", "[ManufacturerObjects]", f"SupportedObjects={len(manufacturer)}",
        *[f"{k + 1}=0x{i:04X}" for k, i in enumerate(manufacturer)], "",
    ]
    return "\n".join(head) + "\n" + "\n\n".join(sections) + "\n"


def remote_axis_map(channel: str, eds: object, node: int) -> str:
    """A device map with a CANopen bus on python-can channel ``channel`` (node ``node``, EDS
    ``eds``) and axis ``x`` on it, hosted by machine 1 (profile velocity, mm): the axis the
    two-satellite tests command from machine 0."""
    return f"""
[[bus]]
name = "drives"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
sdo_timeout = 0.2
nodes = [{{ id = {node}, eds = "{eds}" }}]

[[device]]
name = "x"
profile = "cia402"
machine = 1
bus = "drives"
units = "mm"
address = {{ node = {node} }}
mode = "PV"
quick_stop_option = 2
counts_per_unit = 1000.0
timeouts = {{ enable = 5.0, disable = 5.0, fault_reset = 5.0, set_mode = 2.0, velocity = 10.0 }}
"""


def imported_sync_drive(where: Path, node: int, name: str) -> Path:
    """``chcos import eds`` of a one-axis drive whose TPDOs are synchronous (transmission type 1,
    no event timer) as node ``node`` on bus ``drive``: writes ``drive.eds`` and ``drive.toml``
    in ``where`` and returns the map (the importer gives the bus a ``sync_period``)."""
    from chcos.cli import main as cli

    eds = where / "drive.eds"
    eds.write_text(drive_eds(name=name, transmission=1, event_timer=0), encoding="utf-8")
    devmap = where / "drive.toml"
    assert cli.main(["import", "eds", str(eds), "--node", str(node), "--bus", "drive",
                     "-o", str(devmap)]) == 0
    return devmap
