"""canopen_slave - a simulated CANopen node that lives like a real one, over a python-can bus.

canopen's ``LocalNode`` supplies the object dictionary and the SDO server; everything a node does
on its own is :class:`CanopenSlave`'s (CiA 301):

* **NMT** - boot-up message (``0x700+id``, ``0x00``) at start and after every reset, the state
  machine INITIALISING -> PRE-OPERATIONAL <-> OPERATIONAL / STOPPED driven by NMT commands
  (start, stop, enter pre-operational, reset node, reset communication). No PDO before
  OPERATIONAL, no SDO or EMCY while STOPPED. A reset reloads the power-on values (the EDS
  defaults) unless the area was stored by writing ``'save'`` (0x65766173) to 0x1010.
* **PDOs** - read from the communication and mapping parameters (0x1400/0x1600, 0x1800/0x1A00)
  as they stand in the object dictionary, re-read after an SDO write to them and after a reset.
  Event-driven TPDOs (transmission type 254/255) go out on change and on their event timer;
  synchronous ones (1..240) on every n-th SYNC, acyclic synchronous (0) on the SYNC after a
  change. Synchronous RPDOs (0..240) take effect at the next SYNC, the others at once.
* **Errors** - :meth:`CanopenSlave.inject_fault` sets the error register 0x1001 and sends an EMCY;
  :meth:`CanopenSlave.clear_fault` sends the error-reset EMCY when nothing is left.
* **Heartbeat** - a producer at 0x1017 and a consumer (0x1016) that, when the node it watches
  (the master) falls silent, sends EMCY 0x8130, applies the 0x1029 error behaviour (enter
  PRE-OPERATIONAL by default) and calls the master-lost hooks (the 0x6007 abort-connection
  option code is handed to them; the servo plant holds its position for codes 1..3).
* **SDO** - objects without a DefaultValue read as the zero of their type, not as an abort.

Time: the heartbeat producer runs on real time (a python-can periodic task, ``clock=REAL``) or on
:meth:`CanopenSlave.tick` (``clock=TICK``, for virtual time); event timers, the heartbeat
consumer and the plant always follow :meth:`~CanopenSlave.tick` (from
:meth:`~CanopenSlave.run_realtime`, a kernel's clock or a test). The default plant is a servo
position loop (:class:`ServoAxis`) when the EDS has its objects; ``plant`` adds any callable.

canopen's own objects are held as ``Any``: the library is only partly typed.
"""

from __future__ import annotations

import argparse
import contextlib
import enum
import logging
import struct
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import canopen
from canopen.objectdictionary import BOOLEAN, FLOAT_TYPES, INTEGER_TYPES
from canopen.sdo.exceptions import SdoAbortedError

from chcos import resources
from chcos.devices.eds_file import read_eds
from chcos.errors import BusError, ConfigError

log = logging.getLogger("chcos.apps.sim.canopen_slave")

#: The EDS shipped for the simulated servo drive.
SERVO_EDS = resources.path("chcos.apps.sim", "eds", "servo_drive.eds")

POSITION_ACTUAL = (0x6064, 0)
VELOCITY_ACTUAL = (0x606C, 0)
TARGET_POSITION = (0x607A, 0)
PROFILE_VELOCITY = (0x6081, 0)
STATUSWORD = (0x6041, 0)
HEARTBEAT_TIME = (0x1017, 0)
SERVO_OBJECTS = (POSITION_ACTUAL, VELOCITY_ACTUAL, TARGET_POSITION, PROFILE_VELOCITY, STATUSWORD)

#: Statusword: ready to switch on, switched on, operation enabled, voltage enabled, quick stop off.
STATUS_ENABLED = 0x0037
#: Statusword bit 10: target reached.
STATUS_TARGET_REACHED = 0x0400

SAVE_SIGNATURE = 0x65766173   # 'save' little-endian, written to 0x1010:n
LOAD_SIGNATURE = 0x64616F6C   # 'load' little-endian, written to 0x1011:n
EMCY_HEARTBEAT_LOST = 0x8130  # life guard / heartbeat consumer error
SYNC_COB = 0x080
ABORT_NOT_STORED = 0x08000020     # data cannot be transferred or stored (wrong signature)
ABORT_STATE = 0x08000022          # data cannot be transferred: present device state
ABORT_NO_DATA = 0x08000024        # no data available
ABORT_NOT_MAPPABLE = 0x06040041   # object cannot be mapped to the PDO
ABORT_PDO_LENGTH = 0x06040042     # number and length of the objects would exceed the PDO
ABORT_INVALID_VALUE = 0x06090030  # value range of parameter exceeded
ABORT_NO_OBJECT = 0x06020000      # object does not exist in the object dictionary


class NmtState(enum.IntEnum):
    """The NMT states, valued as a heartbeat carries them."""

    INITIALISING = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F

    @property
    def label(self) -> str:
        """The name canopen and CiA 301 use (``'PRE-OPERATIONAL'``)."""
        return self.name.replace("_", "-")


class NmtCommand(enum.IntEnum):
    """NMT command specifiers (first byte of a COB-ID 0 frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class Clock(enum.Enum):
    """What times the heartbeat producer: wall time, or :meth:`CanopenSlave.tick`."""

    REAL = "real"
    TICK = "tick"


class ErrorBits(enum.IntFlag):
    """Bits of the error register 0x1001."""

    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08
    COMMUNICATION = 0x10
    PROFILE = 0x20
    MANUFACTURER = 0x80


class ErrorBehaviour(enum.IntEnum):
    """0x1029:01, what a communication error (a lost master) does to the NMT state."""

    PRE_OPERATIONAL = 0
    NO_CHANGE = 1
    STOPPED = 2


def error_bits(code: int) -> ErrorBits:
    """The error-register bits an EMCY error code sets (its class, plus generic)."""
    bits = ErrorBits.GENERIC
    bits |= {0x2: ErrorBits.CURRENT, 0x3: ErrorBits.VOLTAGE, 0x4: ErrorBits.TEMPERATURE,
             0x8: ErrorBits.COMMUNICATION, 0xF: ErrorBits.PROFILE}.get(code >> 12, ErrorBits(0))
    if code >> 8 == 0xFF:
        bits |= ErrorBits.MANUFACTURER
    return bits


@dataclass(frozen=True)
class Fault:
    """An active error of the node: its EMCY code, error-register bits and manufacturer data."""

    code: int
    register: ErrorBits
    data: bytes = b""


@dataclass(frozen=True)
class MasterLost:
    """What a master-lost hook is told: the silent node, its consumer time and the node's
    0x6007 abort-connection option code (None when the EDS has no 0x6007)."""

    master: int
    timeout: float
    abort_option: int | None


@dataclass(frozen=True)
class PdoConfig:
    """One PDO as the node's communication and mapping parameters define it."""

    number: int
    cob_id: int
    enabled: bool
    trans_type: int
    event_timer_ms: int
    entries: tuple[tuple[int, int, int], ...]   # (index, subindex, bits)

    @property
    def synchronous(self) -> bool:
        """Transmission types 0..240 follow SYNC."""
        return self.trans_type <= 240

    @property
    def event_driven(self) -> bool:
        """Transmission types 254/255: on change and on the event timer."""
        return self.trans_type >= 254

    def maps(self, index: int, subindex: int) -> bool:
        """True if object ``index:subindex`` is in this PDO."""
        return any(i == index and s == subindex for i, s, _ in self.entries)


@dataclass
class _TpdoTimer:
    since: float = 0.0
    syncs: int = 0
    changed: bool = False


@dataclass
class _Consumer:
    node: int
    timeout: float
    last: float = 0.0
    armed: bool = False   # supervision starts with the first heartbeat received
    lost: bool = False


@dataclass
class SlaveStats:
    """What the node did, for tests and ``chcos sim`` scripts."""

    boots: int = 0
    syncs: int = 0
    tpdos: int = 0
    rpdos: int = 0
    rpdos_ignored: int = 0
    emcys: int = 0
    masters_lost: int = 0


Plant = Callable[["CanopenSlave", float], None]
"""A plant model stepped by :meth:`CanopenSlave.tick`: ``plant(slave, dt)``."""


@dataclass
class ServoAxis:
    """The position loop of the simulated drive: position moves toward target at most ``max_speed``
    counts per second. Pure arithmetic; :meth:`step` never raises."""

    position: float = 0.0
    velocity: float = 0.0

    def step(self, target: int, max_speed: float, dt: float) -> None:
        """Advance ``dt`` seconds toward ``target``."""
        if dt <= 0:
            self.velocity = 0.0
            return
        error = target - self.position
        reach = max(0.0, max_speed) * dt
        move = max(-reach, min(reach, error))
        self.position += move
        self.velocity = move / dt


class ServoPlant:
    """The servo drive's plant: a :class:`ServoAxis` following 0x607A at 0x6081 counts/s, writing
    0x6064, 0x606C and the statusword. On a lost master with an abort-connection option code
    1..3 (fault, disable voltage, quick stop) the axis holds where it is."""

    def __init__(self) -> None:
        self.axis = ServoAxis()

    def __call__(self, slave: CanopenSlave, dt: float) -> None:
        target = int(slave.get(*TARGET_POSITION))
        speed = float(slave.get(*PROFILE_VELOCITY))
        self.axis.step(target, speed, dt)
        position = round(self.axis.position)
        slave.set(*VELOCITY_ACTUAL, round(self.axis.velocity))
        status = STATUS_ENABLED | (STATUS_TARGET_REACHED if position == target else 0)
        slave.set(*STATUSWORD, status)
        slave.set(*POSITION_ACTUAL, position)

    def master_lost(self, slave: CanopenSlave, event: MasterLost) -> None:
        """Hold the position when the abort-connection option asks for an action."""
        if event.abort_option in (1, 2, 3):
            slave.set(*TARGET_POSITION, round(self.axis.position))


def _zero(var: Any) -> Any:
    """The zero value of an object's data type (what an object without a default reads as)."""
    if var.data_type == BOOLEAN:
        return False
    if var.data_type in INTEGER_TYPES:
        return 0
    if var.data_type in FLOAT_TYPES:
        return 0.0
    if var.data_type in (0x09, 0x0B):  # VISIBLE_STRING, UNICODE_STRING
        return ""
    return b""


class VirtualReceiver:
    """A node's receiving thread on python-can's ``virtual`` interface, in place of canopen's
    notifier: each frame is handed to ``notify`` (canopen's network) and then marked done on
    the bus's queue (``task_done``), so that :meth:`settle` can wait until every frame sent to
    the node so far has been handled, its answers sent. The kernel settles a simulated node so
    before virtual time moves on (:meth:`chcos.kernel.scheduler.Kernel.settle`)."""

    #: seconds the thread waits for a frame at most before it looks whether it must stop
    POLL = 0.05

    def __init__(self, bus: Any, notify: Callable[[int, bytearray, float], None],
                 name: str) -> None:
        self._bus = bus
        self._queue: Any = bus.queue   # python-can's virtual bus: the node's receive queue
        self._notify = notify
        self._running = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        #: frames handled so far (error and remote frames included, as ignored)
        self.handled = 0

    def start(self) -> None:
        """Start the thread."""
        self._running = True
        self._thread.start()

    def stop(self) -> None:
        """End the thread and wait for it (not from the thread itself)."""
        self._running = False
        if self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def settle(self, timeout: float) -> bool:
        """True once every frame put on the node's queue so far has been handled; False if
        ``timeout`` seconds passed first or the thread has ended with frames left."""
        done = self._queue.all_tasks_done
        with done:
            return bool(done.wait_for(lambda: self._queue.unfinished_tasks == 0
                                      or not self._thread.is_alive(), timeout)) \
                and self._queue.unfinished_tasks == 0

    def activity(self) -> int:
        """Frames put on the node's queue so far plus frames handled so far."""
        queued: int = self._queue.unfinished_tasks
        return 2 * self.handled + queued   # (queued + handled) + handled

    def _loop(self) -> None:
        while self._running:
            try:
                msg = self._bus.recv(self.POLL)
            except (can.CanError, OSError, ValueError):
                return   # the bus was shut down under it
            if msg is None:
                continue
            try:
                if not (msg.is_error_frame or msg.is_remote_frame):
                    self._notify(msg.arbitration_id, msg.data, msg.timestamp)
            except Exception:   # as canopen's listener: a failing callback drops one frame
                log.exception("simulated CANopen node: handling frame 0x%X failed",
                              msg.arbitration_id)
            finally:
                self.handled += 1
                self._queue.task_done()


class CanopenSlave:
    """One simulated CANopen node on a CAN bus (see the module doc).

    ``interface``/``channel``/``bitrate`` open a python-can bus (``virtual`` in tests);
    ``port`` is the UDP port of interface ``udp_multicast``.
    ``heartbeat_period`` (seconds) is the power-on value of 0x1017 (0: no heartbeat);
    ``tpdo_period`` overrides the event timer of every event-driven TPDO. ``servo`` attaches
    the servo plant when the EDS has its objects; ``plant`` is stepped after it.
    ``refuse_start_on_error``: an NMT start leaves the node PRE-OPERATIONAL while its error
    register is set, as many drives do. Raises :class:`ConfigError` for a bad node id or an
    unreadable EDS. Every method is thread-safe.
    """

    def __init__(self, node_id: int, eds: str | Path = SERVO_EDS, *, channel: str,
                 interface: str = "virtual", bitrate: int | None = None,
                 port: int | None = None,
                 heartbeat_period: float = 0.1, tpdo_period: float | None = None,
                 clock: Clock = Clock.REAL, servo: bool = True, plant: Plant | None = None,
                 refuse_start_on_error: bool = False) -> None:
        if not 1 <= node_id <= 127:
            raise ConfigError(f"canopen slave: node id {node_id} is not in 1..127")
        try:
            read = read_eds(eds, node_id)
        except ValueError as exc:
            raise ConfigError(f"canopen slave node {node_id}: cannot read EDS {eds}: {exc}") \
                from exc
        od = read.od
        self.node_id = node_id
        self.eds = Path(eds)
        #: What the EDS reader tolerated (empty numeric fields, a non-UTF-8 file).
        self.eds_warnings = read.warnings
        self._bus_args: dict[str, Any] = {"interface": interface, "channel": channel}
        if bitrate is not None:
            self._bus_args["bitrate"] = bitrate
        if port is not None:
            self._bus_args["port"] = port
        self._tpdo_period = tpdo_period
        self._clock = clock
        self._refuse_start = refuse_start_on_error
        self._lock = threading.RLock()
        self._changed = threading.Condition(self._lock)
        self._network: Any = canopen.Network()
        self._network.NOTIFIER_CYCLE = 0.05  # bounds how long stop() waits for the notifier
        node: Any = canopen.LocalNode(node_id, od)
        self._node: Any = node
        # NMT and the heartbeat are this class's: canopen's NmtSlave would start its own
        # heartbeat on a 0x1017 write and never sends a boot-up after a reset command.
        with contextlib.suppress(ValueError):
            self._node._write_callbacks.remove(self._node.nmt.on_write)
        node.add_read_callback(self._on_sdo_read)
        node.add_write_callback(self._on_sdo_write)
        self._factory: dict[tuple[int, int], bytes] = {}
        if od.get_variable(*HEARTBEAT_TIME) is not None:
            self._factory[HEARTBEAT_TIME] = od.get_variable(*HEARTBEAT_TIME).encode_raw(
                round(heartbeat_period * 1000))
        self._saved: dict[tuple[int, int], bytes] = {}
        self._state = NmtState.INITIALISING
        self._now = 0.0
        self._next_hb = 0.0
        self._hb_task: Any = None
        self._hb_suppressed = False
        self._muted = False
        self._faults: dict[int, Fault] = {}
        self._history: list[int] = []   # 0x1003, newest first
        self._aborts: dict[tuple[int, int], int] = {}
        self._tpdos: list[PdoConfig] = []
        self._rpdos: list[PdoConfig] = []
        self._timers: dict[int, _TpdoTimer] = {}
        self._rpdo_subs: list[int] = []
        self._pending_rpdos: dict[int, bytes] = {}
        self._consumers: dict[int, _Consumer] = {}
        self._plants: list[Plant] = []
        self._master_lost_hooks: list[Callable[[CanopenSlave, MasterLost], None]] = []
        if servo and all(od.get_variable(i, s) is not None for i, s in SERVO_OBJECTS):
            servo_plant = ServoPlant()
            self._plants.append(servo_plant)
            self._master_lost_hooks.append(servo_plant.master_lost)
        if plant is not None:
            self._plants.append(plant)
        self._started = False
        self._booted = False
        self._rt_stop = threading.Event()
        self._rt_thread: threading.Thread | None = None
        self._rx: VirtualReceiver | None = None
        self.stats = SlaveStats()
        #: Set whenever an RPDO has been applied to the object dictionary.
        self.rpdo_received = threading.Event()
        self._power_on()

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Open the bus and boot: boot-up message, PRE-OPERATIONAL, heartbeat. Raises
        :class:`chcos.errors.BusError` if the bus cannot be opened."""
        with self._lock:
            if self._started:
                return
            try:
                if self._bus_args["interface"] == "virtual":
                    # its own receiver, which settle() can wait for (see VirtualReceiver)
                    self._network.bus = can.Bus(**self._bus_args)
                    self._rx = VirtualReceiver(self._network.bus, self._network.notify,
                                               f"canopen-slave-{self.node_id}-rx")
                    self._rx.start()
                else:
                    self._network.connect(**self._bus_args)
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise BusError(f"canopen slave node {self.node_id}: cannot open CAN bus "
                               f"{self._bus_args}: {exc}") from exc
            node = self._node
            if not self._booted:   # a restart keeps the network's subscriptions
                self._network.add_node(node)
                # the SDO server answers through a gate (no SDO while STOPPED); NMT is ours
                self._network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
                self._network.unsubscribe(0, node.nmt.on_command)
            self._network.subscribe(node.sdo.rx_cobid, self._on_sdo_request)
            self._network.subscribe(0, self._on_nmt)
            self._network.subscribe(SYNC_COB, self._on_sync)
            self._started = True
            # the first start keeps what was set before it; a later one is a power cycle
            self._boot(NmtCommand.RESET_NODE, power_on=not self._booted)
            self._booted = True

    def stop(self) -> None:
        """Stop the real-time thread, the heartbeat and the bus. Idempotent; never raises."""
        self.stop_realtime()
        with self._lock:
            if not self._started:
                return
            self._started = False   # from here on nothing is sent
            self._stop_hb_task()
        # outside the lock: the receiving thread, which is joined here, may be waiting for it
        rx, self._rx = self._rx, None
        if rx is not None:
            rx.stop()
        with contextlib.suppress(Exception):  # the bus is going away anyway
            self._network.disconnect()

    def settle(self, timeout: float) -> bool:
        """Wait until every frame sent to this node so far has been handled (its answers
        sent): virtual time must not move on while it is in flight. Only on python-can's
        ``virtual`` interface (its own receiver); elsewhere, and when stopped, True at once.
        False if ``timeout`` wall seconds passed first."""
        rx = self._rx
        return True if rx is None else rx.settle(timeout)

    @property
    def activity(self) -> int:
        """Frames that reached this node plus frames it has handled, since its receiver started
        (``virtual`` interface only; 0 elsewhere): a count that grows whenever something is sent
        to the node and whenever the node is done with it (and has sent its answer)."""
        rx = self._rx
        return 0 if rx is None else rx.activity()

    def __enter__(self) -> CanopenSlave:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- object dictionary --------------------------------------------------------------------

    def get(self, index: int, subindex: int = 0) -> Any:
        """The decoded value of object ``index:subindex``; raises :class:`ConfigError` if the EDS
        has no such object."""
        with self._lock:
            return self._var(index, subindex).decode_raw(self._stored(index, subindex))

    def set(self, index: int, subindex: int, value: Any) -> None:
        """Set object ``index:subindex`` as the device would (no access check); a change of an
        object in an event-driven TPDO sends that TPDO at once when OPERATIONAL. Raises
        :class:`ConfigError` for an object the EDS lacks or a value its type cannot hold."""
        with self._lock:
            try:
                data = bytes(self._var(index, subindex).encode_raw(value))
            except (struct.error, TypeError, ValueError, OverflowError) as exc:
                raise ConfigError(f"canopen slave node {self.node_id}: 0x{index:04X}:"
                                  f"{subindex:02X} cannot hold {value!r}: {exc}") from exc
            old = self._node.data_store.get(index, {}).get(subindex)
            self._node.data_store.setdefault(index, {})[subindex] = data
            if old != data:
                self._changed_object(index, subindex)

    def data_type(self, index: int, subindex: int = 0) -> int:
        """The CiA 301 data type of object ``index:subindex``; raises :class:`ConfigError` if the
        EDS has no such object."""
        return int(self._var(index, subindex).data_type)

    @property
    def state(self) -> NmtState:
        """The node's NMT state."""
        return self._state

    @property
    def nmt_state(self) -> str:
        """The node's NMT state as canopen names it (``'OPERATIONAL'``, ``'PRE-OPERATIONAL'``)."""
        return self._state.label

    def wait_state(self, state: str | NmtState, timeout: float) -> bool:
        """Block until the NMT state is ``state``; False on timeout."""
        want = state if isinstance(state, NmtState) else NmtState[state.replace("-", "_")]
        with self._changed:
            return self._changed.wait_for(lambda: self._state == want, timeout)

    def wait_for(self, predicate: Callable[[CanopenSlave], bool], timeout: float) -> bool:
        """Block until ``predicate(self)`` holds (checked on every change); False on timeout."""
        with self._changed:
            return self._changed.wait_for(lambda: predicate(self), timeout)

    @property
    def error_register(self) -> ErrorBits:
        """0x1001 as the node answers it: the bits of every active fault."""
        with self._lock:
            bits = ErrorBits(0)
            for f in self._faults.values():
                bits |= f.register
            return bits

    @property
    def faults(self) -> tuple[Fault, ...]:
        """The active faults, oldest first."""
        with self._lock:
            return tuple(self._faults.values())

    @property
    def tpdos(self) -> tuple[PdoConfig, ...]:
        """The TPDOs as the node's parameters define them now."""
        with self._lock:
            return tuple(self._tpdos)

    @property
    def consumer(self) -> tuple[tuple[int, float], ...]:
        """The heartbeat consumer's entries: (watched node, timeout in seconds)."""
        with self._lock:
            return tuple((c.node, c.timeout) for c in self._consumers.values())

    def store(self) -> None:
        """Store the whole object dictionary as the power-on values (as 0x1010:01 ``'save'``)."""
        with self._lock:
            self._save(1)

    def add_master_lost_hook(self, hook: Callable[[CanopenSlave, MasterLost], None]) -> None:
        """Call ``hook(slave, event)`` when the heartbeat consumer finds its node silent (after
        EMCY 0x8130 and the 0x1029 state change): the 0x6007-like action of a drive."""
        with self._lock:
            self._master_lost_hooks.append(hook)

    def add_plant(self, plant: Plant) -> None:
        """Step ``plant(slave, dt)`` on every :meth:`tick`, after the plants there are."""
        with self._lock:
            self._plants.append(plant)

    # -- fault injection ----------------------------------------------------------------------

    def inject_fault(self, code: int, register: ErrorBits | int | None = None,
                     data: bytes = b"") -> None:
        """Raise fault ``code`` (an EMCY error code 0x1000..0xFFFF): 0x1001 gets its bits (from
        the code's class unless ``register`` is given) and an EMCY goes out (not while
        STOPPED). Raises :class:`ConfigError` for a code outside that range or data over 5
        bytes."""
        if not 0x1000 <= code <= 0xFFFF:
            raise ConfigError(f"canopen slave node {self.node_id}: fault code 0x{code:X}: "
                              "expected an EMCY error code 0x1000..0xFFFF")
        if len(data) > 5:
            raise ConfigError(f"canopen slave node {self.node_id}: EMCY data {data!r}: at most "
                              "5 bytes")
        bits = error_bits(code) if register is None else ErrorBits(register) | ErrorBits.GENERIC
        with self._lock:
            self._faults[code] = Fault(code, bits, data)
            depth = self._history_depth()
            if depth:
                self._history = [code, *self._history][:depth]
            self._emcy(code, self.error_register, data)
            self._changed.notify_all()

    def clear_fault(self, code: int | None = None) -> None:
        """Clear fault ``code`` (None: all); when none is left, send the error-reset EMCY
        (code 0x0000). Clearing a fault that is not active does nothing."""
        with self._lock:
            had = bool(self._faults)
            if code is None:
                self._faults.clear()
            else:
                self._faults.pop(code, None)
            if had and not self._faults:
                self._emcy(0, ErrorBits(0), b"")
            self._changed.notify_all()

    def stop_heartbeat(self) -> None:
        """Stop producing heartbeats (simulates a lost node; SDO and PDO keep working)."""
        with self._lock:
            self._hb_suppressed = True
            self._stop_hb_task()

    def start_heartbeat(self, period: float | None = None) -> None:
        """Resume heartbeats, every ``period`` seconds when given (written to 0x1017)."""
        with self._lock:
            self._hb_suppressed = False
            if period is not None and self._node.object_dictionary.get_variable(
                    *HEARTBEAT_TIME) is not None:
                self._node.data_store.setdefault(0x1017, {})[0] = \
                    self._var(*HEARTBEAT_TIME).encode_raw(round(period * 1000))
            self._restart_heartbeat()

    def silence(self) -> None:
        """Stop heartbeats, PDOs and EMCYs (SDO keeps answering); values set meanwhile are
        kept and go out with the next change or event timer after :meth:`restore`."""
        with self._lock:
            self._muted = True
            self._stop_hb_task()

    def restore(self) -> None:
        """Undo :meth:`silence`."""
        with self._lock:
            self._muted = False
            self._restart_heartbeat()

    def send_emcy(self, code: int, register: int = 0, data: bytes = b"") -> None:
        """Send one raw EMCY frame (``code`` 0 is an error reset); 0x1001 is not changed (see
        :meth:`inject_fault`)."""
        with self._lock:
            self._emcy(code, ErrorBits(register), data)

    def inject_sdo_abort(self, index: int, subindex: int, code: int) -> None:
        """Answer every SDO read of ``index:subindex`` with abort ``code`` until cleared."""
        with self._lock:
            self._aborts[(index, subindex)] = code

    def clear_sdo_abort(self, index: int, subindex: int) -> None:
        """Undo :meth:`inject_sdo_abort`."""
        with self._lock:
            self._aborts.pop((index, subindex), None)

    def reset(self, command: NmtCommand = NmtCommand.RESET_NODE) -> None:
        """Reset as if the master had sent ``command`` (or the node had rebooted): the
        configuration not stored is lost, a boot-up goes out."""
        with self._lock:
            self._boot(command)

    # -- simulation ---------------------------------------------------------------------------

    def tick(self, dt: float) -> None:
        """Advance ``dt`` seconds: the plants, the heartbeat producer (``clock=TICK``), the
        heartbeat consumer and the TPDO event timers."""
        with self._lock:
            self._now += dt
            for plant in self._plants:
                plant(self, dt)
            if self._clock is Clock.TICK and self._started:
                period = self._hb_period()
                if period > 0 and self._now + 1e-9 >= self._next_hb:
                    self._next_hb = self._now + period
                    self._heartbeat_frame()
            self._supervise()
            for pdo in self._tpdos:
                period_s = self._event_period(pdo)
                if period_s is None:
                    continue
                timer = self._timers.setdefault(pdo.number, _TpdoTimer())
                timer.since += dt
                if timer.since + 1e-9 >= period_s:
                    timer.since = 0.0
                    self._transmit(pdo)

    def run_realtime(self, step: float = 0.01) -> None:
        """Start a thread calling :meth:`tick` every ``step`` seconds of real time."""
        if self._rt_thread is not None:
            return
        self._rt_stop.clear()

        def loop() -> None:
            last = time.monotonic()
            while not self._rt_stop.wait(step):
                now = time.monotonic()
                self.tick(now - last)
                last = now

        self._rt_thread = threading.Thread(target=loop, name=f"canopen-slave-{self.node_id}",
                                           daemon=True)
        self._rt_thread.start()

    def stop_realtime(self) -> None:
        """Stop the :meth:`run_realtime` thread, if any."""
        thread, self._rt_thread = self._rt_thread, None
        if thread is not None:
            self._rt_stop.set()
            thread.join(timeout=2.0)

    def describe(self) -> str:
        """One line: node, state, error register, PDOs."""
        with self._lock:
            tp = ", ".join(f"TPDO{p.number} type {p.trans_type}" for p in self._tpdos) or "none"
            return (f"node {self.node_id} {self.nmt_state} error register "
                    f"0x{int(self.error_register):02X}; {tp}")

    # -- internals: object dictionary ---------------------------------------------------------

    def _var(self, index: int, subindex: int) -> Any:
        var = self._node.object_dictionary.get_variable(index, subindex)
        if var is None:
            raise ConfigError(f"canopen slave node {self.node_id}: no object "
                              f"0x{index:04X}:{subindex:02X} in {self.eds}")
        return var

    def _stored(self, index: int, subindex: int) -> bytes:
        """The object's bytes as the SDO server would answer, without injected aborts."""
        if index == 0x1001 and subindex == 0:
            return bytes([int(self.error_register)])
        stored = self._node.data_store.get(index, {}).get(subindex)
        if stored is not None:
            return bytes(stored)
        var = self._var(index, subindex)
        default = var.value if var.value is not None else var.default
        return bytes(var.encode_raw(default if default is not None else _zero(var)))

    def _int(self, index: int, subindex: int, missing: int = 0) -> int:
        """An integer object's value, ``missing`` when the EDS lacks it."""
        if self._node.object_dictionary.get_variable(index, subindex) is None:
            return missing
        try:
            return int(self.get(index, subindex))
        except (TypeError, ValueError):
            return missing

    def _power_on(self) -> None:
        """The object dictionary as at power-on: EDS defaults, the constructor's values, what
        was stored."""
        self._node.data_store.clear()
        self._load_area(lambda index: True)

    def _load_area(self, area: Callable[[int], bool]) -> None:
        for values in (self._factory, self._saved):
            for (index, sub), data in values.items():
                if area(index):
                    self._node.data_store.setdefault(index, {})[sub] = data

    def _save(self, sub: int) -> None:
        """Store an area (0x1010 sub 1 all, 2 communication, 3 application, 4 manufacturer)."""
        area = _AREAS.get(sub, _AREAS[1])
        for key in [k for k in self._saved if area(k[0])]:
            del self._saved[key]
        for index, subs in self._node.data_store.items():
            if area(index) and index not in (0x1001, 0x1010, 0x1011):
                for s, data in subs.items():
                    self._saved[(index, s)] = bytes(data)

    def _read_pdos(self) -> None:
        """(Re)read every PDO's parameters and (re)subscribe the RPDO COB-IDs."""
        self._tpdos = [p for n in range(512)
                       if (p := self._pdo(n, 0x1800, 0x1A00)) is not None]
        self._rpdos = [p for n in range(512)
                       if (p := self._pdo(n, 0x1400, 0x1600)) is not None]
        for cob in self._rpdo_subs:
            with contextlib.suppress(KeyError, ValueError):
                self._network.unsubscribe(cob, self._on_rpdo)
        self._rpdo_subs = []
        if self._started:
            for p in self._rpdos:
                if p.enabled and p.cob_id not in self._rpdo_subs:
                    self._network.subscribe(p.cob_id, self._on_rpdo)
                    self._rpdo_subs.append(p.cob_id)
        self._timers = {p.number: self._timers.get(p.number, _TpdoTimer()) for p in self._tpdos}

    def _pdo(self, n: int, comm: int, mapping: int) -> PdoConfig | None:
        od = self._node.object_dictionary
        if comm + n not in od or mapping + n not in od:
            return None
        cob = self._int(comm + n, 1, 0x8000_0000)
        entries = []
        for sub in range(1, self._int(mapping + n, 0) + 1):
            entry = self._int(mapping + n, sub)
            index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            if index and bits:
                entries.append((index, subindex, bits))
        return PdoConfig(number=n + 1, cob_id=cob & 0x1FFF_FFFF, enabled=not cob & 0x8000_0000,
                         trans_type=self._int(comm + n, 2, 255),
                         event_timer_ms=self._int(comm + n, 5), entries=tuple(entries))

    def _read_consumers(self) -> None:
        old = self._consumers
        self._consumers = {}
        if 0x1016 in self._node.object_dictionary:
            for sub in range(1, self._int(0x1016, 0) + 1):
                entry = self._int(0x1016, sub)
                nid, ms = (entry >> 16) & 0x7F, entry & 0xFFFF
                if nid and ms:
                    self._consumers[nid] = _Consumer(nid, ms / 1000)
        for nid in old.keys() - self._consumers.keys():
            with contextlib.suppress(KeyError, ValueError):
                self._network.unsubscribe(0x700 + nid, self._on_master_heartbeat)
        if self._started:
            for nid in self._consumers.keys() - old.keys():
                self._network.subscribe(0x700 + nid, self._on_master_heartbeat)

    # -- internals: NMT and heartbeat ---------------------------------------------------------

    def _boot(self, command: NmtCommand, power_on: bool = False) -> None:
        """Reset (node or communication), send the boot-up message and enter PRE-OPERATIONAL."""
        self._set_state(NmtState.INITIALISING)
        self._stop_hb_task()
        if command is NmtCommand.RESET_NODE:
            if not power_on:
                self._power_on()
        else:
            comm = _AREAS[2]
            for index in [i for i in self._node.data_store if comm(i)]:
                del self._node.data_store[index]
            self._load_area(comm)
        self._pending_rpdos.clear()
        self._timers.clear()
        self._read_pdos()
        self._read_consumers()
        self.stats.boots += 1
        self._send(0x700 + self.node_id, b"\x00")
        self._set_state(NmtState.PRE_OPERATIONAL)
        self._next_hb = self._now + self._hb_period()
        self._restart_heartbeat()
        for fault in self._faults.values():   # a fault still present is reported again
            self._emcy(fault.code, self.error_register, fault.data)

    def _set_state(self, state: NmtState) -> None:
        if state == self._state:
            return
        self._state = state
        if self._hb_task is not None:
            self._hb_task.update(bytes([int(state)]))
        self._changed.notify_all()

    def _hb_period(self) -> float:
        return self._int(*HEARTBEAT_TIME) / 1000

    def _stop_hb_task(self) -> None:
        task, self._hb_task = self._hb_task, None
        if task is not None:
            with contextlib.suppress(Exception):
                task.stop()

    def _restart_heartbeat(self) -> None:
        self._stop_hb_task()
        if self._clock is not Clock.REAL or not self._started or self._hb_suppressed \
                or self._muted or self._state is NmtState.INITIALISING:
            return
        period = self._hb_period()
        if period > 0:
            with contextlib.suppress(can.CanError, OSError):
                self._hb_task = self._network.send_periodic(
                    0x700 + self.node_id, bytes([int(self._state)]), period)

    def _heartbeat_frame(self) -> None:
        if not (self._hb_suppressed or self._muted):
            self._send(0x700 + self.node_id, bytes([int(self._state)]))

    def _on_nmt(self, can_id: int, data: bytes, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        try:
            command = NmtCommand(data[0])
        except ValueError:
            return  # an unknown command specifier is ignored, as by a real node
        with self._lock:
            if not self._started:
                return
            match command:
                case NmtCommand.START:
                    if not (self._refuse_start and self._faults):
                        self._set_state(NmtState.OPERATIONAL)
                case NmtCommand.STOP:
                    self._set_state(NmtState.STOPPED)
                case NmtCommand.ENTER_PRE_OPERATIONAL:
                    self._set_state(NmtState.PRE_OPERATIONAL)
                case NmtCommand.RESET_NODE | NmtCommand.RESET_COMMUNICATION:
                    self._boot(command)

    def _on_master_heartbeat(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._lock:
            consumer = self._consumers.get(can_id - 0x700)
            if consumer is None:
                return
            consumer.last = self._now
            consumer.armed = True
            if consumer.lost:
                consumer.lost = False
                if self._faults.get(EMCY_HEARTBEAT_LOST) is not None and not any(
                        c.lost for c in self._consumers.values()):
                    self.clear_fault(EMCY_HEARTBEAT_LOST)

    def _supervise(self) -> None:
        for consumer in self._consumers.values():
            if not consumer.armed or consumer.lost or \
                    self._now - consumer.last <= consumer.timeout + 1e-9:
                continue
            consumer.lost = True
            self.stats.masters_lost += 1
            self.inject_fault(EMCY_HEARTBEAT_LOST, ErrorBits.COMMUNICATION)
            try:
                behaviour = ErrorBehaviour(self._int(0x1029, 1))
            except ValueError:
                behaviour = ErrorBehaviour.NO_CHANGE
            if behaviour is ErrorBehaviour.PRE_OPERATIONAL and \
                    self._state is NmtState.OPERATIONAL:
                self._set_state(NmtState.PRE_OPERATIONAL)
            elif behaviour is ErrorBehaviour.STOPPED:
                self._set_state(NmtState.STOPPED)
            option = self._int(0x6007, 0) if self._node.object_dictionary.get_variable(
                0x6007, 0) is not None else None
            event = MasterLost(consumer.node, consumer.timeout, option)
            for hook in list(self._master_lost_hooks):
                hook(self, event)

    # -- internals: SDO -----------------------------------------------------------------------

    def _on_sdo_request(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._lock:
            if self._state in (NmtState.STOPPED, NmtState.INITIALISING):
                return
            self._node.sdo.on_request(can_id, data, timestamp)

    def _history_depth(self) -> int:
        """How many errors 0x1003 holds (its sub-indices in the EDS)."""
        obj = self._node.object_dictionary.get(0x1003) \
            if 0x1003 in self._node.object_dictionary else None
        return len([s for s in getattr(obj, "subindices", {}) if s]) if obj is not None else 0

    def _on_sdo_read(self, *, index: int, subindex: int, od: Any) -> Any:
        code = self._aborts.get((index, subindex))
        if code is not None:
            raise SdoAbortedError(code)
        if index == 0x1001 and subindex == 0:
            return int(self.error_register)
        if index == 0x1003:   # pre-defined error field: newest first
            if subindex == 0:
                return len(self._history)
            if subindex > len(self._history):
                raise SdoAbortedError(ABORT_NO_DATA)
            return self._history[subindex - 1]
        if index in (0x1010, 0x1011) and subindex >= 1:
            return 1   # saves on command / restores on command
        if self._node.data_store.get(index, {}).get(subindex) is not None:
            return None
        if od.value is not None or od.default is not None:
            return None
        return _zero(od)   # an object without a DefaultValue reads as its type's zero

    def _on_sdo_write(self, *, index: int, subindex: int, od: Any, data: bytes) -> None:
        value = int.from_bytes(data[:4], "little")
        if index == 0x1010 and subindex >= 1:
            if value != SAVE_SIGNATURE:
                raise SdoAbortedError(ABORT_NOT_STORED)
            self._save(subindex)
            return
        if index == 0x1011 and subindex >= 1:
            if value != LOAD_SIGNATURE:
                raise SdoAbortedError(ABORT_NOT_STORED)
            area = _AREAS.get(subindex, _AREAS[1])
            for key in [k for k in self._saved if area(k[0])]:
                del self._saved[key]   # EDS defaults again from the next reset
            return
        if index == 0x1003:
            if subindex != 0 or value != 0:
                raise SdoAbortedError(ABORT_INVALID_VALUE)   # only 0 (clear) may be written
            self._history.clear()
            return
        if 0x1400 <= index <= 0x1BFF:
            self._check_pdo_write(index, subindex, value)
        # the parameters below take effect at once: store first, then re-read them
        self._node.data_store.setdefault(index, {})[subindex] = bytes(data)
        if index == 0x1017:
            self._next_hb = self._now + self._hb_period()
            self._restart_heartbeat()
        elif index == 0x1016:
            self._read_consumers()
        elif 0x1400 <= index <= 0x1BFF:
            self._read_pdos()
        self._changed_object(index, subindex)

    def _check_pdo_write(self, index: int, subindex: int, value: int) -> None:
        """Refuse what a CiA 301 node refuses: a new COB-ID for a valid PDO; a mapping changed
        while its PDO is valid, or an entry while the entry count is not 0; an entry that
        names an object missing or not mappable in that direction; more than 64 bits."""
        od = self._node.object_dictionary
        comm = index if index < 0x1600 or 0x1800 <= index < 0x1A00 else index - 0x200
        valid = not self._int(comm, 1, 0x8000_0000) & 0x8000_0000
        if index == comm:
            old = self._int(comm, 1, 0x8000_0000)
            if subindex == 1 and valid and not value & 0x8000_0000 \
                    and (old ^ value) & 0x1FFF_FFFF:
                raise SdoAbortedError(ABORT_INVALID_VALUE)
            return
        if valid:
            raise SdoAbortedError(ABORT_STATE)
        if subindex == 0:
            if value and od.get_variable(index, value) is None:
                raise SdoAbortedError(ABORT_PDO_LENGTH)   # more entries than the EDS has
            if sum(self._int(index, s) & 0xFF for s in range(1, value + 1)) > 64:
                raise SdoAbortedError(ABORT_PDO_LENGTH)
            return
        if self._int(index, 0):
            raise SdoAbortedError(ABORT_STATE)
        obj_index, obj_sub = value >> 16, (value >> 8) & 0xFF
        if obj_index < 0x1000:
            return   # a dummy entry (data-type index) fills a gap
        var = od.get_variable(obj_index, obj_sub)
        if var is None:
            raise SdoAbortedError(ABORT_NO_OBJECT)
        receive = comm < 0x1800
        if not var.pdo_mappable or not (var.writable if receive else var.readable):
            raise SdoAbortedError(ABORT_NOT_MAPPABLE)

    # -- internals: PDO, SYNC, EMCY -----------------------------------------------------------

    def _event_period(self, pdo: PdoConfig) -> float | None:
        if not pdo.enabled or not pdo.event_driven:
            return None
        if self._tpdo_period is not None:
            return self._tpdo_period
        return pdo.event_timer_ms / 1000 if pdo.event_timer_ms else None

    def _changed_object(self, index: int, subindex: int) -> None:
        for pdo in self._tpdos:
            if pdo.maps(index, subindex):
                if pdo.event_driven:
                    self._transmit(pdo)
                elif pdo.trans_type == 0:
                    self._timers.setdefault(pdo.number, _TpdoTimer()).changed = True
        self._changed.notify_all()

    def _frame(self, pdo: PdoConfig) -> bytes:
        bits = 0
        offset = 0
        for index, subindex, size in pdo.entries:
            try:
                raw = int.from_bytes(self._stored(index, subindex), "little")
            except ConfigError:
                raw = 0   # a dummy entry (data-type index) fills the gap with zeros
            bits |= (raw & ((1 << size) - 1)) << offset
            offset += size
        return bits.to_bytes((offset + 7) // 8, "little")

    def _tpdo_event_period(self) -> float | None:
        """The shortest event period of the enabled event-driven TPDOs (``tpdo_period`` when
        given), None without one: for subclasses that time every TPDO together."""
        periods = [p for pdo in self._tpdos if (p := self._event_period(pdo)) is not None]
        return min(periods) if periods else None

    def _transmit(self, pdo: PdoConfig | Any) -> None:
        """Send one TPDO now (when OPERATIONAL and not silenced). ``pdo`` is a
        :class:`PdoConfig` or, for subclasses walking ``self._node.tpdo.map``, canopen's map
        of the same TPDO (the node's own parameters decide what it carries)."""
        if not isinstance(pdo, PdoConfig):
            number = int(pdo.com_record.od.index) - 0x1800 + 1
            found = next((p for p in self._tpdos if p.number == number), None)
            if found is None:
                return
            pdo = found
        if not (self._started and pdo.enabled and self._state is NmtState.OPERATIONAL) \
                or self._muted:
            return
        self.stats.tpdos += 1
        self._send(pdo.cob_id, self._frame(pdo))

    def _send(self, cob_id: int, data: bytes) -> None:
        if not self._started:
            return
        # A send error (full queue at shutdown) is not fatal: the next change or timer resends.
        with contextlib.suppress(can.CanError, OSError):
            self._network.send_message(cob_id, data)

    def _emcy(self, code: int, register: ErrorBits, data: bytes) -> None:
        if self._state in (NmtState.STOPPED, NmtState.INITIALISING) or self._muted:
            return
        cob = self._int(0x1014, 0, 0x80 + self.node_id)
        if cob & 0x8000_0000:
            return   # EMCY disabled in 0x1014
        self.stats.emcys += 1
        self._send(cob & 0x7FF,
                   struct.pack("<HB", code, int(register)) + data.ljust(5, b"\x00")[:5])

    def _on_sync(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._lock:
            self.stats.syncs += 1
            if self._state is not NmtState.OPERATIONAL:
                return
            for cob, frame in list(self._pending_rpdos.items()):
                self._apply_rpdo(cob, frame)
            self._pending_rpdos.clear()
            for pdo in self._tpdos:
                if not pdo.enabled or not pdo.synchronous:
                    continue
                timer = self._timers.setdefault(pdo.number, _TpdoTimer())
                if pdo.trans_type == 0:
                    if timer.changed:
                        timer.changed = False
                        self._transmit(pdo)
                    continue
                timer.syncs += 1
                if timer.syncs >= pdo.trans_type:
                    timer.syncs = 0
                    self._transmit(pdo)

    def _on_rpdo(self, can_id: int, data: bytes, timestamp: float) -> None:
        with self._lock:
            if self._state is not NmtState.OPERATIONAL:
                self.stats.rpdos_ignored += 1
                return
            pdo = next((p for p in self._rpdos if p.enabled and p.cob_id == can_id), None)
            if pdo is None:
                return
            if pdo.synchronous:
                self._pending_rpdos[can_id] = bytes(data)   # takes effect at the next SYNC
                return
            self._apply_rpdo(can_id, bytes(data))

    def _apply_rpdo(self, cob_id: int, data: bytes) -> None:
        pdo = next((p for p in self._rpdos if p.enabled and p.cob_id == cob_id), None)
        if pdo is None:
            return
        bits = int.from_bytes(data, "little")
        offset = 0
        for index, subindex, size in pdo.entries:
            var = self._node.object_dictionary.get_variable(index, subindex)
            raw = (bits >> offset) & ((1 << size) - 1)
            offset += size
            if var is None or offset > 8 * len(data):
                continue   # a dummy entry, or a frame shorter than the mapping
            nbytes = max(1, len(var) // 8) if var.data_type in INTEGER_TYPES or \
                var.data_type in FLOAT_TYPES or var.data_type == BOOLEAN else (size + 7) // 8
            # through the node's write hooks (subclasses watch RPDO-written objects there)
            with contextlib.suppress(SdoAbortedError):
                self._node.set_data(index, subindex, raw.to_bytes(nbytes, "little"))
        self.stats.rpdos += 1
        self._changed.notify_all()
        self.rpdo_received.set()


#: 0x1010/0x1011 sub-indices: 1 all, 2 communication, 3 application, 4 manufacturer objects.
_AREAS: dict[int, Callable[[int], bool]] = {
    1: lambda index: True,
    2: lambda index: 0x1000 <= index <= 0x1FFF,
    3: lambda index: 0x6000 <= index <= 0x9FFF,
    4: lambda index: 0x2000 <= index <= 0x5FFF,
}


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos sim canopen``: run a simulated servo drive in real time until interrupted or
    ``--duration`` elapses. Returns the process exit status (0 ok, 2 bad arguments or bus)."""
    parser = argparse.ArgumentParser(prog="chcos sim canopen",
                                     description="Simulated CANopen node (servo drive by "
                                                 "default): boot-up, NMT, heartbeat, PDOs, "
                                                 "SYNC, EMCY.")
    parser.add_argument("--node", type=int, default=1, help="node id 1..127 (default 1)")
    parser.add_argument("--eds", default=str(SERVO_EDS), help="EDS file (default: servo_drive)")
    parser.add_argument("--interface", default="virtual", help="python-can interface")
    parser.add_argument("--channel", required=True, help="python-can channel (e.g. vcan0)")
    parser.add_argument("--bitrate", type=int, default=None)
    parser.add_argument("--heartbeat", type=float, default=0.1, help="heartbeat period, s")
    parser.add_argument("--step", type=float, default=0.01, help="physics step, s")
    parser.add_argument("--duration", type=float, default=None, help="run this long, s")
    parser.add_argument("--refuse-start-on-error", action="store_true",
                        help="stay PRE-OPERATIONAL on NMT start while 0x1001 is set")
    parser.add_argument("--fault", metavar="CODE@START[-END]", action="append", default=[],
                        help="raise EMCY fault CODE (e.g. 0x4210) from START seconds (to END)")
    args = parser.parse_args(list(argv) if argv is not None else None)
    try:
        faults = [fault_arg(item) for item in args.fault]
        slave = CanopenSlave(args.node, args.eds, channel=args.channel,
                             interface=args.interface, bitrate=args.bitrate,
                             heartbeat_period=args.heartbeat,
                             refuse_start_on_error=args.refuse_start_on_error)
        slave.start()
    except (ConfigError, BusError) as exc:
        print(f"chcos sim canopen: {exc}", file=sys.stderr)
        return 2
    for warning in slave.eds_warnings:
        print(f"chcos sim canopen: warning: {warning}", file=sys.stderr)
    slave.run_realtime(args.step)
    print(f"canopen node {args.node} on {args.interface}:{args.channel}", flush=True)
    done = threading.Event()
    start = time.monotonic()
    active: set[int] = set()
    try:
        while not done.wait(0.05):
            t = time.monotonic() - start
            for code, t0, t1 in faults:
                if t0 <= t < t1 and code not in active:
                    slave.inject_fault(code)
                    active.add(code)
                    print(f"t={t:6.1f} s  fault 0x{code:04X} raised", flush=True)
                elif t >= t1 and code in active:
                    slave.clear_fault(code)
                    active.discard(code)
                    print(f"t={t:6.1f} s  fault 0x{code:04X} cleared", flush=True)
            if args.duration is not None and t >= args.duration:
                break
    except KeyboardInterrupt:
        pass
    finally:
        slave.stop()
    return 0


def fault_arg(item: str) -> tuple[int, float, float]:
    """``CODE@START[-END]`` -> (code, start, end); raises ConfigError naming the item."""
    code_text, at, span = item.partition("@")
    start_text, _, end_text = span.partition("-")
    try:
        code = int(code_text, 0)
        start = float(start_text)
        end = float(end_text) if end_text else float("inf")
    except ValueError:
        raise ConfigError(f"--fault {item!r}: expected CODE@START[-END], e.g. "
                          "0x4210@2-5") from None
    if not at or not 0x1000 <= code <= 0xFFFF or end <= start:
        raise ConfigError(f"--fault {item!r}: expected CODE@START[-END] with an EMCY code "
                          "0x1000..0xFFFF and END after START")
    return code, start, end
