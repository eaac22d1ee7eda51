"""plant - the arc-welding cell simulator on real field buses: :class:`WeldSim`.

The stand-in for the physical cell of the thesis (sections 5.1, 5.4, appendix 2): it steps the
pure physics model :class:`chcos.apps.weld.model.WeldCell` and presents its devices (the contract of
``chcos/apps/weld/DEVICES.md``) on the buses a real cell uses, as laid down in
``chcos/apps/weld/maps/weld_cell.toml``:

* **CANopen** on python-can channel A: five servo drives, node ids 1..5 (canopen ``LocalNode``:
  SDO server, NMT, heartbeat every 50 ms of wall time). TPDO1 (0x180+node) carries position
  actual (0x6064, INTEGER32 microradians) every 10 ms of simulated time while the node is
  OPERATIONAL; RPDO1 (0x200+node) target positions (0x607A) are applied to the model.
* **raw CAN** on channel B: the messages of ``chcos/apps/weld/maps/weld_cell.dbc`` bound by the
device map
  (LightCurtain, ArcTemperature every 20 ms, GapMarkers every 50 ms, the curtain and the markers
  also on change; :data:`CAN_MESSAGES`), coded with cantools from
  :func:`chcos.apps.weld.model.dbc_signals`. Two channels, so the raw-CAN driver never sees CANopen.
* **Modbus TCP** on ``127.0.0.1:port``, unit 1: the power source and the cell I/O
  (:data:`INPUT_REGISTERS`, holding registers :data:`HR_VOLTS_SET` / :data:`HR_WIRE_SET`, coils
  :data:`COIL_DRIVES_ENABLE` / :data:`COIL_GAS_VALVE`), refreshed every 10 ms.
* **serial**: the linear light sensor, 50 lines a second (:data:`LINE_FORMAT`) to the clients
  of a TCP server on ``127.0.0.1:port``, which the serial driver opens as
  ``socket://127.0.0.1:port``.

Time. Physics advances in steps of ``tick`` seconds, lazily: whenever the simulator publishes or
takes a command it first steps the model up to the last tick boundary at or before now. Every
publication happens at its own instant, a fraction of a millisecond after the boundary
(:data:`PHASES`: CANopen and Modbus, raw CAN, serial), so that the kernel settles one bus at a
time and no two buses deliver in the same virtual instant (the order of their interrupts would
depend on thread timing), and never on a millisecond grid where driver polls and task timers lie.

:meth:`WeldSim.attach` runs it on a kernel's clock (virtual time in tests and fast runs) through
kernel timers, and registers :meth:`WeldSim.settle`, which takes in every command already sent to
the simulator (RPDO and NMT frames are read synchronously from a second bus handle on the CANopen
channel; Modbus writes are in the register store once the Modbus driver has its answer) and
applies it to the model before virtual time moves on. The kernel settles in registration order
and the drivers must have sent before the simulator looks, so the settler is registered at the
first publication, once the kernel runs: start the drivers that talk to the simulator (boot the
machine) before the kernel runs, whether before or after :meth:`WeldSim.attach` (a driver
started later settles after the simulator, and a command on its bus may then be taken in one
instant late, depending on thread timing).
:meth:`WeldSim.start_realtime` instead runs it from a thread on wall-clock time (``chcos sim
weld``, :func:`main`).

Faults (:mod:`chcos.apps.weld.faults`): a scenario at construction, :meth:`WeldSim.inject` at run
time.
A silent sensor stops being sent: no TPDO of that joint, no frame of its DBC message, no serial
line; its Modbus input register answers exception 11 (gateway target failed to respond), so the
driver fails that device alone. A servo timeout also stops that node's heartbeat. While the coil
``drives_enable`` is 0 every joint is held where it is and RPDO targets are ignored.

Errors: :class:`chcos.errors.ConfigError` for bad arguments, scenarios or device-map templates;
:class:`chcos.errors.BusError` when a CAN channel cannot be opened or a TCP port bound.
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import math
import re
import select
import socket
import struct
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import can
import canopen
from pymodbus.constants import ExcCodes

from chcos import resources
from chcos.apps.sim.modbus_server import ModbusSimServer, RegisterStore
from chcos.apps.weld.faults import Fault, Scenario, parse_fault, parse_scenario, parse_scenario_toml
from chcos.apps.weld.model import CellConfig, Readings, WeldCell, dbc_signals
from chcos.apps.weld.seam import Seam
from chcos.errors import BusError, ConfigError, DeviceError
from chcos.kernel.scheduler import Kernel, Timer
from drivers.codecs.can import load_dbc

BUSCONFIG = resources.path("chcos.apps.weld", "maps")
#: The cell's device map (fixed default channels and ports).
CELL_TOML = BUSCONFIG / "weld_cell.toml"
#: The EDS of the joint servo drives.
WELD_EDS = BUSCONFIG / "weld_servo.eds"
#: The raw-CAN messages of the cell.
WELD_DBC = BUSCONFIG / "weld_cell.dbc"

DEFAULT_CANOPEN_CHANNEL = "weld-canopen"
DEFAULT_SENSOR_CHANNEL = "weld-sensors"
DEFAULT_MODBUS_PORT = 15020
DEFAULT_SERIAL_PORT = 15021

NODE_IDS: tuple[int, ...] = (1, 2, 3, 4, 5)
"""CANopen node id of joint ``j`` is ``NODE_IDS[j - 1]``."""
POSITION_SCALE = 1e-6
"""rad per count of 0x6064 / 0x607A."""
HEARTBEAT_PERIOD = 0.05
"""Heartbeat producer period (s of wall time), as 0x1017 of the EDS."""

SERVO_PERIOD = 0.01
"""TPDO1 period and Modbus input-register refresh period (s of simulated time)."""
CAN_SLOT = SERVO_PERIOD
"""The raw-CAN scheduler's slot (s): every DBC cycle time is a multiple of it."""
LINE_SLOTS = 2
"""Linear light sensor: one line every second slot, 20 ms (50 Hz)."""
PHASES: Mapping[str, float] = {"servo": 0.00025, "can": 0.0005, "line": 0.00075}
"""Offset (s) of each publication after its 10 ms slot boundary (see the module doc); raw CAN
and serial instants exist only in slots where something is due."""

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

    def mirror(self, unit: int, function_code: int, start: int, address: int, count: int,
               image: list[int], values: list[Any] | None) -> ExcCodes | None:
        """The server hook of :class:`RegisterStore`, refusing reads of silent inputs."""
        silent = self.silent_inputs
        if function_code == 4 and any(address <= a < address + count for a in silent):
            with self._cond:
                self.requests += 1
            return ExcCodes.GATEWAY_NO_RESPONSE
        return super().mirror(unit, function_code, start, address, count, image, values)


# --- the linear sensor's line server -----------------------------------------------------------


class LineServer:
    """A TCP server on ``host:port`` writing text lines to every connected client (the far end of
    pyserial's ``socket://`` URL). Connections are accepted, and closed peers dropped, when a
    line is sent, on the sender's thread. Raises :class:`BusError` if the port cannot be bound."""

    def __init__(self, port: int, host: str = "127.0.0.1") -> None:
        self.host = host
        self.port = port
        listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            listener.bind((host, port))
            listener.listen(4)
            listener.setblocking(False)
        except OSError as exc:
            listener.close()
            raise BusError(_where("serial", f"cannot listen on {host}:{port}: {exc}")) from exc
        self._listener = listener
        self._clients: list[socket.socket] = []
        self._lock = threading.Lock()
        self.lines_sent = 0
        self.connects = 0

    @property
    def url(self) -> str:
        """The pyserial URL a driver opens."""
        return f"socket://{self.host}:{self.port}"

    @property
    def clients(self) -> int:
        """Connected clients (as of the last line sent)."""
        with self._lock:
            return len(self._clients)

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._listener.accept()
            except OSError:  # BlockingIOError: nobody waiting
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            conn.settimeout(1.0)
            self._clients.append(conn)
            self.connects += 1

    def send_line(self, text: str) -> None:
        """Write ``text`` + newline to every client; never raises (a broken client is dropped)."""
        data = (text + "\n").encode("ascii")
        with self._lock:
            self._accept()
            for conn in list(self._clients):
                try:  # discard anything the client wrote; readable with b"" is a closed peer
                    while select.select([conn], [], [], 0)[0]:
                        if not conn.recv(4096):
                            raise ConnectionResetError("peer closed")
                except (OSError, ValueError):
                    self._drop(conn)
                    continue
                try:
                    conn.sendall(data)
                except OSError:
                    self._drop(conn)
            self.lines_sent += 1

    def _drop(self, conn: socket.socket) -> None:
        self._clients.remove(conn)
        with contextlib.suppress(OSError):
            conn.close()

    def close(self) -> None:
        """Close the listener and every client. Idempotent."""
        with self._lock:
            for conn in self._clients:
                with contextlib.suppress(OSError):
                    conn.close()
            self._clients.clear()
            with contextlib.suppress(OSError):
                self._listener.close()


# --- the servo drives --------------------------------------------------------------------------


class ServoDrives:
    """The five joint drives on one CAN channel.

    A canopen ``Network`` of ``LocalNode`` objects answers SDO and NMT and produces heartbeats on
    wall time (its own notifier thread). A second python-can handle on the same channel is read
    only synchronously by :meth:`drain` (NMT and RPDO frames, in arrival order) and sends the
    TPDOs, so the simulated-time side never depends on thread timing. Raises :class:`BusError`
    if the channel cannot be opened, :class:`ConfigError` for an unreadable EDS.
    """

    def __init__(self, interface: str, channel: str, eds: Path = WELD_EDS,
                 heartbeat_period: float = HEARTBEAT_PERIOD) -> None:
        self._hb_ms = max(1, round(heartbeat_period * 1000))
        self.nodes: dict[int, Any] = {}
        network: Any = canopen.Network()
        network.NOTIFIER_CYCLE = 0.05
        for nid in NODE_IDS:
            try:
                od = canopen.import_od(str(eds), nid)
            except Exception as exc:  # canopen raises assorted types for a bad EDS
                raise ConfigError(_where("canopen", f"cannot read EDS {eds}: {exc}")) from exc
            node: Any = canopen.LocalNode(nid, od)
            network.add_node(node)
            self.nodes[nid] = node
        self._network = network
        try:
            network.connect(interface=interface, channel=channel)
        except (can.CanError, OSError, ValueError, ImportError) as exc:
            raise BusError(_where("canopen", f"cannot open {interface} channel {channel!r}: "
                                             f"{exc}")) from exc
        try:
            # only NMT (0x000) and RPDO1 (0x200 + node) are read here: SocketCAN filters the
            # rest (heartbeats, SDO) out in the kernel. Not elsewhere: python-can filters in
            # software, and recv(0) then stops at the first frame that does not match
            filters = [{"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
                       {"can_id": 0x200, "can_mask": 0x7F8, "extended": False}]
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
        for node in self.nodes.values():
            node.data_store.setdefault(0x1017, {})[0] = \
                node.object_dictionary[0x1017].encode_raw(self._hb_ms)
            node.nmt.state = "INITIALISING"
            node.nmt.state = "PRE-OPERATIONAL"  # boot-up message, heartbeat starts

    def drain(self) -> list[tuple[int, int]]:
        """Read every frame waiting on the synchronous handle: apply NMT commands to the PDO
        state, and return the RPDO1 targets ``(node, counts)`` of OPERATIONAL nodes in order."""
        targets: list[tuple[int, int]] = []
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
            elif cob - 0x200 in self.nodes and len(data) >= 4:
                nid = cob - 0x200
                if self.operational[nid]:
                    counts = struct.unpack_from("<i", data)[0]
                    self.nodes[nid].data_store.setdefault(0x607A, {})[0] = data[:4]
                    targets.append((nid, counts))
        return targets

    def send_tpdo(self, nid: int, counts: int) -> None:
        """Send TPDO1 of node ``nid`` (position actual ``counts``) and keep it in 0x6064."""
        counts = max(-(2**31), min(2**31 - 1, counts))
        data = struct.pack("<i", counts)
        self.nodes[nid].data_store.setdefault(0x6064, {})[0] = data
        try:
            self.pdo_bus.send(can.Message(arbitration_id=0x180 + nid, data=data,
                                          is_extended_id=False))
            self.tpdos_sent += 1
        except (can.CanError, OSError):
            self.send_errors += 1

    def heartbeat(self, nid: int, on: bool) -> None:
        """Start or stop node ``nid``'s heartbeat producer (a servo timeout silences it)."""
        if self.beating[nid] == on:
            return
        self.beating[nid] = on
        nmt = self.nodes[nid].nmt
        if on:
            nmt.start_heartbeat(self._hb_ms)
        else:
            nmt.stop_heartbeat()

    def close(self) -> None:
        """Stop the heartbeats and close both handles. Never raises."""
        for node in self.nodes.values():
            with contextlib.suppress(Exception):
                node.nmt.stop_heartbeat()
        with contextlib.suppress(Exception):
            self._network.disconnect()
        with contextlib.suppress(Exception):
            self.pdo_bus.shutdown()


# --- the raw CAN sensors -----------------------------------------------------------------------


class SensorFrames:
    """The DBC-coded raw CAN nodes: each message at its cycle time, on-change messages also when
    their signals (alive counter aside) change; a message missing from the signals (its sensor is
    silent) is not sent. Raises :class:`BusError` for an unusable DBC or channel,
    :class:`ConfigError` for a message the DBC lacks."""

    def __init__(self, interface: str, channel: str, dbc: Path = WELD_DBC,
                 messages: Sequence[str] = CAN_MESSAGES) -> None:
        self.db: Any = load_dbc(str(dbc))
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


# --- the simulator -----------------------------------------------------------------------------


def load_scenario(scenario: Scenario | str | Path | None) -> Scenario:
    """A scenario from a :class:`Scenario`, a scenario string (``"tip-stuck@s=120mm"``), or a
    TOML file (a :class:`Path`, or a string ending in ``.toml``). Raises ConfigError."""
    if scenario is None:
        return Scenario()
    if isinstance(scenario, Scenario):
        return scenario
    if isinstance(scenario, Path) or scenario.strip().endswith(".toml"):
        path = Path(scenario)
        try:
            text = path.read_text(encoding="utf-8")
        except OSError as exc:
            raise ConfigError(f"scenario file {path}: cannot be read: {exc}") from exc
        return parse_scenario_toml(text, str(path))
    return parse_scenario(scenario)


class WeldSim:
    """The simulated welding cell on CANopen, raw CAN, Modbus TCP and a serial line (see the
    module doc). ``tick`` is the physics step (s, 0 < tick <= 0.01); ``seed`` the noise seed;
    ``scenario`` faults to inject (see :func:`load_scenario`); ``config``/``seam`` the model's.

    Everything is opened at construction: build the simulator before the System whose drivers
    connect to it. Raises :class:`ConfigError` (bad arguments, scenario, EDS or DBC) and
    :class:`BusError` (a channel that cannot be opened, a port that cannot be bound); whatever
    was opened is closed again.
    """

    def __init__(self, *, canopen_channel: str = DEFAULT_CANOPEN_CHANNEL,
                 sensor_channel: str = DEFAULT_SENSOR_CHANNEL,
                 modbus_port: int = DEFAULT_MODBUS_PORT, serial_port: int = DEFAULT_SERIAL_PORT,
                 interface: str = "virtual", scenario: Scenario | str | Path | None = None,
                 seed: int = 0, tick: float = 0.005, config: CellConfig | None = None,
                 seam: Seam | None = None, can_messages: Sequence[str] = CAN_MESSAGES,
                 heartbeat_period: float = HEARTBEAT_PERIOD) -> None:
        if not (isinstance(tick, int | float) and math.isfinite(tick) and 0 < tick <= SERVO_PERIOD):
            raise ConfigError(f"weld simulator tick={tick!r} s: expected 0 < tick <= "
                              f"{SERVO_PERIOD} s")
        if canopen_channel == sensor_channel:
            raise ConfigError(f"weld simulator: canopen_channel and sensor_channel are both "
                              f"{canopen_channel!r}; expected two channels")
        for what, port in (("modbus_port", modbus_port), ("serial_port", serial_port)):
            if not (isinstance(port, int) and 1 <= port <= 65535):
                raise ConfigError(f"weld simulator {what}={port!r}: expected a TCP port 1..65535")
        if not heartbeat_period > 0:
            raise ConfigError(f"weld simulator heartbeat_period={heartbeat_period!r} s: "
                              f"expected > 0")
        self.tick = float(tick)
        self.scenario = load_scenario(scenario)
        self.model = WeldCell(config, seam, self.scenario, seed)
        self.interface = interface
        self.canopen_channel = canopen_channel
        self.sensor_channel = sensor_channel
        self.modbus_port = modbus_port
        self.serial_port = serial_port
        #: Commands the model refused or ignored, counted by kind.
        self.stats: Counter[str] = Counter()
        #: The latest refused commands (text), newest last.
        self.errors: list[str] = []
        self._lock = threading.RLock()
        self._closed = False
        self._steps = 0
        self._origin: float | None = None
        self._clock: Callable[[], float] = time.monotonic
        self._kernel: Kernel | None = None
        self._timers: list[Timer] = []
        self._rt_thread: threading.Thread | None = None
        self._rt_stop = threading.Event()
        self._slot = 0
        self._settler_due = False
        self._later: Callable[[float, Callable[[], None]], None] = lambda _delay, fn: fn()
        self._drives_enabled = False
        self._gas_open = False
        self._volts_raw = 0
        self._wire_raw = 0
        self.store = WeldRegisterStore()
        self.servo: ServoDrives | None = None
        self.sensors: SensorFrames | None = None
        self.modbus: ModbusSimServer | None = None
        self.line: LineServer | None = None
        try:
            self.servo = ServoDrives(interface, canopen_channel, heartbeat_period=heartbeat_period)
            self.sensors = SensorFrames(interface, sensor_channel, messages=can_messages)
            self.modbus = ModbusSimServer(self.store, modbus_port)
            self.modbus.start()
            self.line = LineServer(serial_port)
        except BaseException:
            self.close()
            raise
        self._publish_registers(self.model.readings())

    # -- running ------------------------------------------------------------------------------

    def attach(self, kernel: Kernel) -> None:
        """Run on ``kernel``'s clock from now: publications as kernel timers, commands taken in
        by a settler registered at the first publication (see the module doc: boot before the
        kernel runs). Raises ConfigError if already running or closed."""
        with self._lock:
            self._check_idle()
            now = kernel.clock.now()
            self._kernel = kernel
            self._clock = kernel.clock.now
            self._origin = now
            self._timers = [kernel.call_at(now + PHASES["servo"], self._on_servo, SERVO_PERIOD)]

            def later(delay: float, fn: Callable[[], None]) -> None:
                kernel.call_at(kernel.clock.now() + delay, fn)

            self._later = later
            self._settler_due = True  # registered at the first slot, after the drivers' own

    def settle(self, timeout: float) -> bool:
        """Take in every command sent to the simulator so far and apply it to the model (the
        kernel calls this before virtual time moves on). Always True: nothing waits."""
        with self._lock:
            if self._origin is not None and not self._closed:
                self._advance(self._clock())
        return True

    def start_realtime(self) -> None:
        """Run from a thread on wall-clock time (for ``chcos sim weld``). Raises ConfigError if
        already running or closed."""
        with self._lock:
            self._check_idle()
            self._clock = time.monotonic
            self._origin = origin = time.monotonic()
            self._rt_stop.clear()

            def loop() -> None:  # raw CAN and serial go out right after the servo slot
                n = 0
                while not self._rt_stop.wait(
                        max(0.0, origin + PHASES["servo"] + n * SERVO_PERIOD - time.monotonic())):
                    n += 1
                    self._on_servo()

            self._rt_thread = threading.Thread(target=loop, name="weld-sim", daemon=True)
            self._rt_thread.start()

    def _check_idle(self) -> None:
        if self._closed:
            raise ConfigError("weld simulator: closed; create a new one")
        if self._origin is not None:
            raise ConfigError("weld simulator: already running (attach/start_realtime once)")

    def close(self) -> None:
        """Stop the timers or the thread and close every bus and server. Idempotent; never
        raises."""
        with self._lock:
            self._closed = True
            for timer in self._timers:
                timer.cancel()
            self._timers = []
        self._rt_stop.set()
        if self._rt_thread is not None:
            self._rt_thread.join(timeout=5.0)
            self._rt_thread = None
        for part in (self.line, self.servo, self.sensors):
            if part is not None:
                with contextlib.suppress(Exception):
                    part.close()
        if self.modbus is not None:
            with contextlib.suppress(Exception):
                self.modbus.stop()

    def __enter__(self) -> WeldSim:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- faults -------------------------------------------------------------------------------

    def inject(self, fault: Fault | str) -> None:
        """Inject a fault (a :class:`Fault` or one scenario item such as
        ``"sensor-dropout(arc_temperature)"``) at the present simulated time. Raises ConfigError
        for a bad fault string."""
        if isinstance(fault, str):
            fault = parse_fault(fault)
        with self._lock:
            self.model.inject(fault)
            self._sync_heartbeats()

    @property
    def drives_enabled(self) -> bool:
        """The state of the safe-torque-off relay as the simulator applied it last."""
        with self._lock:
            return self._drives_enabled

    @property
    def sim_time(self) -> float:
        """Simulated time (s) the model has been stepped to."""
        with self._lock:
            return self._steps * self.tick

    # -- the cycle ----------------------------------------------------------------------------

    def _advance(self, now: float) -> None:
        """Take in commands, then step the model to the last tick boundary at or before ``now``
        and apply them from there."""
        assert self._origin is not None and self.servo is not None
        targets = self.servo.drain()
        n = math.floor((now - self._origin) / self.tick + 1e-6)
        model = self.model
        while self._steps < n:
            model.step(self.tick)
            self._steps += 1
        self._apply_power()
        for nid, counts in targets:
            if not self._drives_enabled:
                self.stats["target-ignored-disabled"] += 1
                continue
            try:
                model.set_joint_target(nid, counts * POSITION_SCALE)
            except DeviceError as exc:
                self._refused("target", f"node {nid} RPDO1 target {counts} counts: {exc}")
        self._sync_heartbeats()

    def _refused(self, kind: str, text: str) -> None:
        self.stats[f"{kind}-refused"] += 1
        self.errors.append(text)
        del self.errors[:-50]

    def _apply_power(self) -> None:
        store, model = self.store, self.model
        coils = store.read(UNIT, "coil", 0, 2)
        volts = store.read(UNIT, "holding", HR_VOLTS_SET)[0]
        wire = store.read(UNIT, "holding", HR_WIRE_SET)[0]
        drives, gas = bool(coils[COIL_DRIVES_ENABLE]), bool(coils[COIL_GAS_VALVE])
        if drives != self._drives_enabled:
            self._drives_enabled = drives
            if not drives:  # safe torque off: hold every joint where it is
                model.set_joint_targets(model.joints)
        if gas != self._gas_open:
            self._gas_open = gas
            model.set_gas_valve(gas)
        if volts != self._volts_raw:
            self._volts_raw = volts
            try:
                model.set_voltage(volts * SETPOINT_SCALE)
            except DeviceError as exc:
                self._refused("volts", f"holding {HR_VOLTS_SET} = {volts}: {exc}")
        if wire != self._wire_raw:
            self._wire_raw = wire
            try:
                model.set_wire_speed(wire * SETPOINT_SCALE)
            except DeviceError as exc:
                self._refused("wire", f"holding {HR_WIRE_SET} = {wire}: {exc}")

    def _sync_heartbeats(self) -> None:
        if self.servo is None:
            return
        ok = self.model.readings().servo_ok
        for j, nid in enumerate(NODE_IDS):
            self.servo.heartbeat(nid, ok[j])

    def _on_servo(self) -> None:
        """Every 10 ms slot: TPDO1 of every live, OPERATIONAL drive and the power source's
        registers; then the raw-CAN instant (if a message is due) and the serial instant (every
        second slot) are scheduled."""
        with self._lock:
            if self._closed or self.servo is None:
                return
            if self._settler_due and self._kernel is not None:
                self._settler_due = False
                self._kernel.add_settler(self.settle)
            self._advance(self._clock())
            slot = self._slot
            self._slot += 1
            r = self.model.readings()
            for j, nid in enumerate(NODE_IDS):
                if f"joint{j + 1}" in r.silent or not self.servo.operational[nid]:
                    continue
                self.servo.send_tpdo(nid, round(r.joints[j] / POSITION_SCALE))
            self._publish_registers(r)
            if self.sensors is not None and self.sensors.due(slot, dbc_signals(r, 0)):
                self._later(PHASES["can"] - PHASES["servo"], functools.partial(self._on_can, slot))
            if slot % LINE_SLOTS == 0:
                self._later(PHASES["line"] - PHASES["servo"], self._on_line)

    def _publish_registers(self, r: Readings) -> None:
        silent: set[int] = set()
        for name, (address, scale) in INPUT_REGISTERS.items():
            if name in r.silent:
                silent.add(address)
                continue
            raw = round(float(getattr(r, name)) / scale)
            self.store.write(UNIT, "input", address, [max(0, min(0xFFFF, raw))])
        self.store.silent_inputs = frozenset(silent)

    def _on_can(self, slot: int) -> None:
        """The raw-CAN messages due or changed in ``slot``."""
        with self._lock:
            if self._closed or self.sensors is None:
                return
            self._advance(self._clock())
            self.sensors.publish(slot, dbc_signals(self.model.readings(), 0))

    def _on_line(self) -> None:
        """One line of the linear light sensor."""
        with self._lock:
            if self._closed or self.line is None:
                return
            self._advance(self._clock())
            r = self.model.readings()
            if "linear_sensor" not in r.silent:
                self.line.send_line(format_line(r))


def format_line(r: Readings) -> str:
    """The serial line of the linear light sensor for readings ``r`` (:data:`LINE_FORMAT`)."""
    pixels = "".join("1" if p else "0" for p in r.linear_pixels)
    return LINE_FORMAT.format(pixels=pixels, range=-1.0 if r.range_mm is None else r.range_mm)


# --- the device map ----------------------------------------------------------------------------


def cell_devmap(dest_dir: str | Path, *, canopen_channel: str, sensor_channel: str,
                modbus_port: int, serial_port: int, interface: str = "virtual") -> Path:
    """Write ``weld_cell.toml`` into ``dest_dir`` bound to these CAN channels (python-can
    ``interface``), Modbus port and serial port on 127.0.0.1, with the EDS and DBC paths made
    absolute; returns the new file's path. Raises ConfigError for bad arguments or a template
    that no longer has the lines to rebind (naming the file and the line expected)."""
    for what, chan in (("canopen_channel", canopen_channel), ("sensor_channel", sensor_channel),
                       ("interface", interface)):
        if not (isinstance(chan, str) and chan and '"' not in chan and "\\" not in chan):
            raise ConfigError(f"cell_devmap {what}={chan!r}: expected a non-empty name without "
                              f"quotes or backslashes")
    for what, port in (("modbus_port", modbus_port), ("serial_port", serial_port)):
        if not (isinstance(port, int) and not isinstance(port, bool) and 1 <= port <= 65535):
            raise ConfigError(f"cell_devmap {what}={port!r}: expected a TCP port 1..65535")
    text = CELL_TOML.read_text(encoding="utf-8")
    rebind = [
        ('interface = "virtual"', f'interface = "{interface}"', 2),
        (f'channel = "{DEFAULT_CANOPEN_CHANNEL}"', f'channel = "{canopen_channel}"', 1),
        (f'channel = "{DEFAULT_SENSOR_CHANNEL}"', f'channel = "{sensor_channel}"', 1),
        (f"port = {DEFAULT_MODBUS_PORT}", f"port = {modbus_port}", 1),
        (f'url = "socket://127.0.0.1:{DEFAULT_SERIAL_PORT}"',
         f'url = "socket://127.0.0.1:{serial_port}"', 1),
        ('eds = "weld_servo.eds"', f'eds = "{WELD_EDS.as_posix()}"', len(NODE_IDS)),
        ('dbc = "weld_cell.dbc"', f'dbc = "{WELD_DBC.as_posix()}"', 1),
    ]
    for old, new, count in rebind:
        pattern = re.compile(r"(?<![\w.])" + re.escape(old) + r"(?![\w.])")
        text, found = pattern.subn(new, text)
        if found != count:
            raise ConfigError(f"{CELL_TOML}: expected {count} line(s) with {old!r} to rebind, "
                              f"found {found}")
    dest = Path(dest_dir)
    try:
        dest.mkdir(parents=True, exist_ok=True)
        out = dest / CELL_TOML.name
        out.write_text(text, encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cell_devmap: cannot write into {dest}: {exc}") from exc
    return out


# --- chcos sim weld ----------------------------------------------------------------------------


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos sim weld``: run the simulated cell on wall-clock time until interrupted or
    ``--duration`` elapses, printing a status line every ``--status`` seconds. Returns the exit
    status (0 ok, 2 bad arguments, scenario, channel or port)."""
    p = argparse.ArgumentParser(prog="chcos sim weld",
                                description="The simulated arc-welding cell on CANopen, raw CAN, "
                                            "Modbus TCP and a serial line (busconfig/"
                                            "weld_cell.toml).")
    p.add_argument("--scenario", default="",
                   help='faults, e.g. "tip-stuck@s=120mm,intruder(for=2s)@t=8s", or a .toml file')
    p.add_argument("--seed", type=int, default=0, help="noise seed (0)")
    p.add_argument("--tick", type=float, default=0.005, help="physics step, s (0.005)")
    p.add_argument("--interface", default="virtual", help="python-can interface (virtual)")
    p.add_argument("--canopen-channel", default=DEFAULT_CANOPEN_CHANNEL)
    p.add_argument("--sensor-channel", default=DEFAULT_SENSOR_CHANNEL)
    p.add_argument("--modbus-port", type=int, default=DEFAULT_MODBUS_PORT)
    p.add_argument("--serial-port", type=int, default=DEFAULT_SERIAL_PORT)
    p.add_argument("--duration", type=float, default=None, help="run this long, s")
    p.add_argument("--status", type=float, default=1.0, help="status line period, s (1)")
    args = p.parse_args(list(argv) if argv is not None else None)
    try:
        sim = WeldSim(canopen_channel=args.canopen_channel, sensor_channel=args.sensor_channel,
                      modbus_port=args.modbus_port, serial_port=args.serial_port,
                      interface=args.interface, scenario=args.scenario, seed=args.seed,
                      tick=args.tick)
    except (ConfigError, BusError) as exc:
        print(f"chcos sim weld: {exc}", file=sys.stderr)
        return 2
    with sim:
        sim.start_realtime()
        print(f"weld cell: canopen {args.interface}:{args.canopen_channel} nodes "
              f"{','.join(map(str, NODE_IDS))}, raw CAN {args.interface}:{args.sensor_channel}, "
              f"modbus 127.0.0.1:{args.modbus_port} unit {UNIT}, serial "
              f"socket://127.0.0.1:{args.serial_port}; scenario "
              f"{sim.scenario.describe() or 'none'}", flush=True)
        deadline = None if args.duration is None else time.monotonic() + args.duration
        stop = threading.Event()
        try:
            while deadline is None or time.monotonic() < deadline:
                left = args.status if deadline is None else min(args.status,
                                                                deadline - time.monotonic())
                stop.wait(max(0.0, left))
                print(status_line(sim), flush=True)
        except KeyboardInterrupt:
            pass
    return 0


def status_line(sim: WeldSim) -> str:
    """One line on the simulated cell: time, tip, arc, drives, weld progress."""
    with sim._lock:
        m = sim.model
        x, y, z = m.pose.position
        prog = m.progress()
        return (f"t={sim.sim_time:7.2f}s tip=({x:6.1f},{y:6.1f},{z:6.1f})mm "
                f"s={m.seam_point.s:6.1f}mm V={m.voltage_setpoint:4.1f} "
                f"T={m.temperature:6.0f}C drives={'on' if sim.drives_enabled else 'off'} "
                f"welded={prog.welded:5.1f}/{prog.length:.0f}mm flawed={prog.flawed:.1f}mm")
