"""slaves - the welding cell's devices as bus slaves, for the simulator (:mod:`.plant`).

Each class is one side of one bus of ``chcos/apps/weld/maps/weld_cell.toml`` (the contract of
``chcos/apps/weld/DEVICES.md``), with the register, object and message layout it answers to:

* :class:`ServoDrives` - **CANopen**: five CiA 402 servo drives
  (:class:`chcos.apps.weld.servo.JointDrive`), node ids :data:`NODE_IDS` (canopen
  ``LocalNode``: SDO server, NMT, heartbeat); TPDO1 position and velocity actual (0x6064,
  0x606C, INTEGER32 microradians, :data:`POSITION_SCALE`), TPDO2 statusword, modes display and
  error code (0x6041, 0x6061, 0x603F; on change and every :data:`STATUS_EVERY` servo periods),
  RPDO1 target positions (0x607A), RPDO2 controlword and modes of operation (0x6040, 0x6060);
* :class:`SensorFrames` - **raw CAN**: the DBC-coded messages of
  ``chcos/apps/weld/maps/weld_cell.dbc`` (:data:`CAN_MESSAGES`), each at its cycle time or on
  change;
* :class:`PowerSource` (its :class:`WeldRegisterStore`) - **Modbus TCP**, unit :data:`UNIT`: the
  power source and the cell I/O (:data:`INPUT_REGISTERS`, holding registers
  :data:`HR_VOLTS_SET` / :data:`HR_WIRE_SET`, coils :data:`COIL_DRIVES_ENABLE` /
  :data:`COIL_GAS_VALVE`); a silent sensor answers exception 11;
* **serial**: the linear light sensor's lines (:data:`LINE_FORMAT`, :func:`format_line`) to the
  clients of a :class:`chcos.apps.weld.lineserver.LineServer`, opened by the serial driver as
  ``socket://127.0.0.1:port``.

They know nothing of time: :class:`chcos.apps.weld.plant.WeldSim` steps the model and tells them
what to send. Errors: :class:`chcos.errors.BusError` when a channel cannot be
opened or a port bound, :class:`chcos.errors.ConfigError` for an unreadable EDS or a message
the DBC lacks.
"""

from __future__ import annotations

import contextlib
import functools
import struct
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen

from chcos import resources
from chcos.apps.sim.modbus_slave import GATEWAY_NO_RESPONSE, RegisterStore
from chcos.apps.weld.model import Readings, WeldCell
from chcos.apps.weld.servo import POSITION_SCALE as POSITION_SCALE
from chcos.apps.weld.servo import JointDrive
from chcos.errors import BusError, ConfigError, DeviceError

BUSCONFIG = resources.path("chcos.apps.weld", "maps")
#: The EDS of the joint servo drives.
WELD_EDS = BUSCONFIG / "weld_servo.eds"
#: The raw-CAN messages of the cell.
WELD_DBC = BUSCONFIG / "weld_cell.dbc"


NODE_IDS: tuple[int, ...] = (1, 2, 3, 4, 5)
"""CANopen node id of joint ``j`` is ``NODE_IDS[j - 1]``."""
DRIVE_OBJECTS = (0x603F, 0x6040, 0x6041, 0x605A, 0x6060, 0x6061, 0x6064, 0x606C, 0x607A, 0x6085)
"""The CiA 402 objects the joint drives' EDS must have."""
STATUS_EVERY = 10
"""TPDO2 (the statusword) goes out on change and at least every this many servo periods."""
HEARTBEAT_PERIOD = 0.05
"""Heartbeat producer period (s of the simulator's clock), as 0x1017 of the EDS."""

SERVO_PERIOD = 0.01
"""TPDO1 period and Modbus input-register refresh period (s of simulated time)."""
CAN_SLOT = SERVO_PERIOD
"""The raw-CAN scheduler's slot (s): every DBC cycle time is a multiple of it."""

UNIT = 1
INPUT_REGISTERS: Mapping[str, tuple[int, float]] = {
    "arc_voltage": (0, 0.01),
    "arc_current": (10, 0.1),
    "wire_speed": (20, 0.01),
    "gas_bottle_pressure": (30, 0.01),
    "gas_flow": (40, 0.01),
}
"""Model sensor (a :class:`chcos.apps.weld.model.Readings` field) -> (input register, units per
bit):
arc V, arc A, wire mm/s, bottle bar, flow L/min. uint16, clamped to 0..65535."""
HR_VOLTS_SET = 100
HR_WIRE_SET = 110
SETPOINT_SCALE = 0.01
"""V per bit of :data:`HR_VOLTS_SET`, mm/s per bit of :data:`HR_WIRE_SET`."""
COIL_DRIVES_ENABLE = 0
COIL_GAS_VALVE = 1

CAN_MESSAGES: tuple[str, ...] = ("LightCurtain", "ArcTemperature", "GapMarkers", "WireFeed")
"""DBC messages sent by default: those ``weld_cell.toml`` binds (GasSupply would be an unknown
id to the raw-CAN driver; pass ``can_messages`` to send it too). WireFeed carries the electrode
supply (``wire_left``)."""

LINE_FORMAT = "L {pixels} R {range:.2f}"
"""One serial line: 64 pixels as '0'/'1' (1 = dark, pixel 0 on the tool -y side), range in mm
(-1.00: nothing within 0..100 mm)."""


def _where(kind: str, detail: str) -> str:
    return f"weld simulator {kind}: {detail}"


# --- the power source's registers --------------------------------------------------------------


class WeldRegisterStore(RegisterStore):
    """Unit 1's tables; reads of input registers in :attr:`silent_inputs` answer exception 11
    (a sensor of the power source that stopped reporting). Thread-safe."""

    def __init__(self) -> None:
        super().__init__((UNIT,), size=200)
        self.silent_inputs: frozenset[int] = frozenset()

    def refusal(self, unit: int, table: str, address: int, count: int, write: bool
                ) -> int | None:
        """Exception 11 for a read of a silent input (see :class:`RegisterStore`)."""
        silent = self.silent_inputs
        if table == "input" and any(address <= a < address + count for a in silent):
            return GATEWAY_NO_RESPONSE
        return None


class PowerSource:
    """The power source and the cell I/O as the model sees them through :attr:`store`: the
    coils and holding registers the controller writes are applied to the model when they
    change (:meth:`apply`), the model's readings are shown in the input registers
    (:meth:`publish`; a silent sensor's register answers exception 11)."""

    def __init__(self) -> None:
        self.store = WeldRegisterStore()
        self.drives_enabled = False
        self.gas_open = False
        self.volts_raw = 0
        self.wire_raw = 0

    def apply(self, model: WeldCell, refused: Callable[[str, str], None]) -> None:
        """Apply what changed in the coils and holding registers to ``model``; a set-point the
        model refuses is reported as ``refused(kind, text)``. Dropping ``drives_enable`` holds
        every joint where it is (safe torque off)."""
        store = self.store
        coils = store.read(UNIT, "coil", 0, 2)
        volts = store.read(UNIT, "holding", HR_VOLTS_SET)[0]
        wire = store.read(UNIT, "holding", HR_WIRE_SET)[0]
        drives, gas = bool(coils[COIL_DRIVES_ENABLE]), bool(coils[COIL_GAS_VALVE])
        if drives != self.drives_enabled:
            self.drives_enabled = drives
            if not drives:
                model.set_joint_targets(model.joints)
        if gas != self.gas_open:
            self.gas_open = gas
            model.set_gas_valve(gas)
        if volts != self.volts_raw:
            self.volts_raw = volts
            try:
                model.set_voltage(volts * SETPOINT_SCALE)
            except DeviceError as exc:
                refused("volts", f"holding {HR_VOLTS_SET} = {volts}: {exc}")
        if wire != self.wire_raw:
            self.wire_raw = wire
            try:
                model.set_wire_speed(wire * SETPOINT_SCALE)
            except DeviceError as exc:
                refused("wire", f"holding {HR_WIRE_SET} = {wire}: {exc}")

    def publish(self, r: Readings) -> None:
        """Show readings ``r`` in the input registers (:data:`INPUT_REGISTERS`)."""
        silent: set[int] = set()
        for name, (address, scale) in INPUT_REGISTERS.items():
            if name in r.silent:
                silent.add(address)
                continue
            raw = round(float(getattr(r, name)) / scale)
            self.store.write(UNIT, "input", address, [max(0, min(0xFFFF, raw))])
        self.store.silent_inputs = frozenset(silent)


# --- the servo drives --------------------------------------------------------------------------


@dataclass(frozen=True)
class TargetWrite:
    """RPDO1 of node ``node``: target position 0x607A in counts."""

    node: int
    counts: int


@dataclass(frozen=True)
class ControlWrite:
    """RPDO2 of node ``node`` (controlword 0x6040, modes of operation 0x6060), or an SDO
    download of one of them (the other None)."""

    node: int
    controlword: int | None
    mode: int | None


@dataclass(frozen=True)
class NodeReset:
    """An NMT reset node for ``node``: the drive reboots."""

    node: int


DriveCommand = TargetWrite | ControlWrite | NodeReset

NMT_PRE_OPERATIONAL = 0x7F
"""The NMT state code a heartbeat carries after boot-up (CiA 301)."""
_NMT_AFTER = {0x01: 0x05, 0x02: 0x04, 0x80: 0x7F, 0x81: 0x7F, 0x82: 0x7F}
"""NMT command -> the state code the node's heartbeat then carries (operational, stopped,
pre-operational; a reset boots into pre-operational)."""


class ServoDrives:
    """The five joint drives on one CAN channel, each a CiA 402 drive
    (:class:`chcos.apps.weld.servo.JointDrive`, in :attr:`drives` by node id).

    A canopen ``Network`` of ``LocalNode`` objects answers SDO and NMT (its own notifier
    thread); its object dictionaries hold what the drives show, so an SDO upload of 0x6041,
    0x6061, 0x6064, 0x606C or 0x603F answers the drive's present value. The heartbeats are not
    canopen's producer (a wall-clock thread, late on a loaded machine and far too slow for
    virtual time): :meth:`beat` sends them from the simulator's cycle, on its clock, every
    heartbeat period (0x1017) with the NMT state the drive is in as the NMT commands on the
    synchronous handle left it.
    A second python-can handle on the same channel is read only synchronously by :meth:`drain`
    (NMT, RPDO1 targets and RPDO2 controlwords, in arrival order) and sends the TPDOs, so the
    simulated-time side never depends on thread timing. SDO downloads of 0x6040, 0x6060 or
    0x605A (a master without the RPDO) are taken in at the next :meth:`drain`, after the
    frames. Raises :class:`BusError` if the channel cannot be opened, :class:`ConfigError` for
    an unreadable EDS or one without the CiA 402 objects.
    """

    def __init__(self, interface: str, channel: str, eds: Path = WELD_EDS,
                 heartbeat_period: float = HEARTBEAT_PERIOD) -> None:
        self._hb_ms = max(1, round(heartbeat_period * 1000))
        #: each node's heartbeat period (ms, 0x1017; 0: no heartbeat) and NMT state code as the
        #: NMT commands read by :meth:`drain` left it (what :meth:`beat` sends)
        self.hb_ms = dict.fromkeys(NODE_IDS, self._hb_ms)
        self.nmt_state = dict.fromkeys(NODE_IDS, NMT_PRE_OPERATIONAL)
        self._hb_due = dict.fromkeys(NODE_IDS, 0.0)
        self.nodes: dict[int, Any] = {}
        self.drives: dict[int, JointDrive] = {}
        self._sdo_writes: deque[DriveCommand] = deque()
        network: Any = canopen.Network()
        network.NOTIFIER_CYCLE = 0.05
        for nid in NODE_IDS:
            try:
                od = canopen.import_od(str(eds), nid)
            except Exception as exc:  # canopen raises assorted types for a bad EDS
                raise ConfigError(_where("canopen", f"cannot read EDS {eds}: {exc}")) from exc
            missing = [f"0x{i:04X}" for i in DRIVE_OBJECTS if i not in od]
            if missing:
                raise ConfigError(_where("canopen", f"EDS {eds} lacks the CiA 402 objects "
                                                    f"{', '.join(missing)}"))
            node: Any = canopen.LocalNode(nid, od)
            node.add_write_callback(functools.partial(self._on_sdo_write, nid))
            network.add_node(node)
            self.nodes[nid] = node
            self.drives[nid] = JointDrive(
                nid, quick_stop_option=_default(od, 0x605A),
                quick_stop_deceleration=_default(od, 0x6085))
        self._network = network
        try:
            network.connect(interface=interface, channel=channel)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(_where("canopen", f"cannot open {interface} channel {channel!r}: "
                                             f"{exc}")) from exc
        try:
            # only NMT (0x000), RPDO1 (0x200 + node) and RPDO2 (0x300 + node) are read here:
            # SocketCAN filters the rest (heartbeats, SDO) out in the kernel. Not elsewhere:
            # python-can filters in software, and recv(0) then stops at the first frame that
            # does not match
            filters = [{"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
                       {"can_id": 0x200, "can_mask": 0x7F8, "extended": False},
                       {"can_id": 0x300, "can_mask": 0x7F8, "extended": False}]
            self.pdo_bus = can.Bus(interface=interface, channel=channel,
                                   can_filters=filters if interface == "socketcan" else None)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            with contextlib.suppress(Exception):
                network.disconnect()
            raise BusError(_where("canopen", f"cannot open {interface} channel {channel!r}: "
                                             f"{exc}")) from exc
        self.operational = dict.fromkeys(NODE_IDS, False)
        self.beating = dict.fromkeys(NODE_IDS, True)
        self.tpdos_sent = 0
        self.send_errors = 0
        self._shown: dict[int, tuple[int, int, int] | None] = dict.fromkeys(NODE_IDS)
        self._slots = 0
        for nid, node in self.nodes.items():
            node.data_store.setdefault(0x1017, {})[0] = \
                node.object_dictionary[0x1017].encode_raw(self._hb_ms)
            self._store(nid)
            node.nmt.state = "INITIALISING"
            node.nmt.state = "PRE-OPERATIONAL"  # boot-up message (canopen's heartbeat starts)
            node.nmt.stop_heartbeat()           # ...and stops: beat() sends them on the clock

    def _on_sdo_write(self, nid: int, *, index: int, subindex: int, od: Any,
                      data: bytes) -> None:
        """An SDO download (canopen's notifier thread): queued for the next :meth:`drain`."""
        if subindex != 0:
            return
        if index == 0x1017:     # canopen restarted its wall-clock producer: beat() does it
            self.nodes[nid].nmt.stop_heartbeat()
            self.hb_ms[nid] = struct.unpack("<H", bytes(data[:2]))[0]
        elif index == 0x6040:
            self._sdo_writes.append(ControlWrite(nid, struct.unpack("<H", bytes(data[:2]))[0],
                                                 None))
        elif index == 0x6060:
            self._sdo_writes.append(ControlWrite(nid, None, struct.unpack("<b",
                                                                          bytes(data[:1]))[0]))
        elif index == 0x605A:
            self.drives[nid].quick_stop_option = struct.unpack("<h", bytes(data[:2]))[0]

    def drain(self) -> list[DriveCommand]:
        """Read every frame waiting on the synchronous handle: apply NMT start/stop to the PDO
        state, and return what the drives are to apply, in order: NMT resets, RPDO1 targets and
        RPDO2 controlwords of OPERATIONAL nodes, then SDO downloads received meanwhile."""
        out: list[DriveCommand] = []
        while True:
            try:
                msg = self.pdo_bus.recv(0)
            except (can.CanError, OSError):
                break
            if msg is None:
                break
            if msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame:
                continue
            cob = msg.arbitration_id
            data = bytes(msg.data)
            if cob == 0 and len(data) >= 2:
                cmd, target = data[0], data[1]
                for nid in NODE_IDS:
                    if target in (0, nid):
                        self.operational[nid] = cmd == 0x01
                        self.nmt_state[nid] = _NMT_AFTER.get(cmd, self.nmt_state[nid])
                        if cmd == 0x81:
                            out.append(NodeReset(nid))
            elif cob - 0x200 in self.nodes and len(data) >= 4:
                nid = cob - 0x200
                if self.operational[nid]:
                    counts = struct.unpack_from("<i", data)[0]
                    self.nodes[nid].data_store.setdefault(0x607A, {})[0] = data[:4]
                    out.append(TargetWrite(nid, counts))
            elif cob - 0x300 in self.nodes and len(data) >= 3:
                nid = cob - 0x300
                if self.operational[nid]:
                    cw, mode = struct.unpack_from("<Hb", data)
                    out.append(ControlWrite(nid, cw, mode))
        while self._sdo_writes:
            out.append(self._sdo_writes.popleft())
        return out

    def apply(self, command: DriveCommand) -> bool:
        """Apply one command of :meth:`drain` to its drive; for a target, True if the drive
        took it (OPERATION ENABLED in CSP)."""
        drive = self.drives[command.node]
        match command:
            case TargetWrite(_, counts):
                return drive.target(counts)
            case ControlWrite(_, cw, mode):
                if cw is not None:
                    drive.controlword(cw)
                if mode is not None:
                    drive.mode(mode)
            case NodeReset():
                drive.reboot()
        return True

    def step(self, dt: float, model: WeldCell, torque: bool) -> None:
        """Advance every drive ``dt`` s and command its joint of ``model`` (held where it
        stands unless OPERATION ENABLED with ``torque`` from the relay, or quick-stopping)."""
        for j, nid in enumerate(NODE_IDS):
            goal = self.drives[nid].step(dt, model.joints[j] / POSITION_SCALE, torque)
            if goal is None:
                model.targets[j] = model.joints[j]
                continue
            try:
                model.set_joint_target(j + 1, goal * POSITION_SCALE)
            except DeviceError:
                model.targets[j] = model.joints[j]

    def _store(self, nid: int, position: int | None = None) -> None:
        """Show drive ``nid``'s values in its object dictionary (what an SDO upload answers)."""
        drive, store = self.drives[nid], self.nodes[nid].data_store
        store.setdefault(0x6041, {})[0] = struct.pack("<H", drive.statusword)
        store.setdefault(0x6061, {})[0] = struct.pack("<b", drive.mode_display)
        store.setdefault(0x603F, {})[0] = struct.pack("<H", drive.error_code & 0xFFFF)
        store.setdefault(0x606C, {})[0] = struct.pack("<i", _int32(drive.velocity))
        if position is not None:
            store.setdefault(0x6064, {})[0] = struct.pack("<i", position)

    def send_tpdo(self, nid: int, counts: int) -> None:
        """Send TPDO1 of node ``nid`` (position actual ``counts``, velocity actual) and keep
        them in 0x6064/0x606C."""
        counts = _int32(counts)
        data = struct.pack("<ii", counts, _int32(self.drives[nid].velocity))
        self._store(nid, counts)
        self._send(0x180 + nid, data)

    def send_status(self, nid: int, force: bool = False) -> None:
        """Send TPDO2 of node ``nid`` (statusword, modes display, error code) if it changed
        since the last one, or ``force``."""
        drive = self.drives[nid]
        shown = (drive.statusword, drive.mode_display, drive.error_code & 0xFFFF)
        self._store(nid)
        if not force and shown == self._shown[nid]:
            return
        self._shown[nid] = shown
        self._send(0x280 + nid, struct.pack("<HbH", *shown))

    def _send(self, cob: int, data: bytes) -> None:
        try:
            self.pdo_bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))
            self.tpdos_sent += 1
        except (can.CanError, OSError):
            self.send_errors += 1

    def heartbeat(self, nid: int, on: bool) -> None:
        """Start or stop node ``nid``'s heartbeat (a servo timeout silences it)."""
        self.beating[nid] = on

    def beat(self, now: float) -> None:
        """Send the heartbeat of every beating node whose period (0x1017) is up at simulated
        time ``now`` (s): the first at once, then one a period apart."""
        for nid in NODE_IDS:
            period = self.hb_ms[nid] / 1000.0
            if not self.beating[nid] or period <= 0.0 or now + 1e-9 < self._hb_due[nid]:
                continue
            self._hb_due[nid] = max(self._hb_due[nid] + period, now)
            self._send(0x700 + nid, bytes([self.nmt_state[nid]]))

    def sync_heartbeats(self, ok: Sequence[bool]) -> None:
        """Joint ``j``'s drive beats while ``ok[j]`` (a servo timeout silences it)."""
        for j, nid in enumerate(NODE_IDS):
            self.heartbeat(nid, ok[j])

    def close(self) -> None:
        """Stop the heartbeats and close both handles. Never raises."""
        for node in self.nodes.values():
            with contextlib.suppress(Exception):
                node.nmt.stop_heartbeat()
        with contextlib.suppress(Exception):
            self._network.disconnect()
        with contextlib.suppress(Exception):
            self.pdo_bus.shutdown()


def _default(od: Any, index: int) -> int:
    """The EDS default of integer object ``index`` (0 if it has none)."""
    var: Any = od.get_variable(index, 0)
    default = None if var is None else var.default
    return int(default) if isinstance(default, int) else 0


def _int32(value: int) -> int:
    return max(-(2**31), min(2**31 - 1, int(value)))


# --- the raw CAN sensors -----------------------------------------------------------------------


class SensorFrames:
    """The DBC-coded raw CAN nodes: each message at its cycle time, on-change messages also when
    their signals (alive counter aside) change; a message missing from the signals (its sensor is
    silent) is not sent. ``db`` is the cantools database loaded from ``dbc`` (named in errors).
    Raises :class:`BusError` for an unusable channel, :class:`ConfigError` for a message the DBC
    lacks."""

    def __init__(self, interface: str, channel: str, db: Any, dbc: Path = WELD_DBC,
                 messages: Sequence[str] = CAN_MESSAGES) -> None:
        self.db = db
        self.messages: dict[str, Any] = {}
        self.slots: dict[str, int | None] = {}
        self.on_change: set[str] = set()
        for name in messages:
            try:
                msg = self.db.get_message_by_name(name)
            except KeyError:
                raise ConfigError(_where("can", f"message {name!r} is not in {dbc}; expected "
                                                f"one of {[m.name for m in self.db.messages]}")) \
                    from None
            self.messages[name] = msg
            cycle = msg.cycle_time
            self.slots[name] = max(1, round(cycle / 1000.0 / CAN_SLOT)) if cycle else None
            if "OnChange" in str(msg.send_type or ""):
                self.on_change.add(name)
        self.counters = dict.fromkeys(self.messages, 0)
        self._last: dict[str, dict[str, Any]] = {}
        self.frames_sent = 0
        self.send_errors = 0
        try:
            self.bus = can.Bus(interface=interface, channel=channel)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(_where("can", f"cannot open {interface} channel {channel!r}: {exc}")) \
                from exc

    def _due(self, name: str, slot: int, values: Mapping[str, Any]) -> bool:
        every = self.slots[name]
        if every is not None and slot % every == 0:
            return True
        key = {k: v for k, v in values.items() if k != "AliveCounter"}
        return name in self.on_change and key != self._last.get(name)

    def due(self, slot: int, signals: Mapping[str, Mapping[str, Any]]) -> bool:
        """True if :meth:`publish` would send anything in ``slot`` with ``signals``."""
        return any(name in signals and self._due(name, slot, signals[name])
                   for name in self.messages)

    def publish(self, slot: int, signals: Mapping[str, Mapping[str, Any]]) -> None:
        """Send what is due in slot number ``slot`` (slots are :data:`CAN_SLOT` apart)."""
        for name, msg in self.messages.items():
            values = signals.get(name)
            if values is None or not self._due(name, slot, values):
                continue
            key = {k: v for k, v in values.items() if k != "AliveCounter"}
            data = msg.encode({**values, "AliveCounter": self.counters[name] % 16})
            try:
                self.bus.send(can.Message(arbitration_id=msg.frame_id, data=data,
                                          is_extended_id=msg.is_extended_frame))
                self.frames_sent += 1
            except (can.CanError, OSError):
                self.send_errors += 1
            self.counters[name] += 1
            self._last[name] = key

    def close(self) -> None:
        """Close the bus. Never raises."""
        with contextlib.suppress(Exception):
            self.bus.shutdown()


def format_line(r: Readings) -> str:
    """The serial line of the linear light sensor for readings ``r`` (:data:`LINE_FORMAT`)."""
    pixels = "".join("1" if p else "0" for p in r.linear_pixels)
    return LINE_FORMAT.format(pixels=pixels, range=-1.0 if r.range_mm is None else r.range_mm)
