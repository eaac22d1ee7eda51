"""canopen_slave - a simulated CANopen node as strict as the device it stands for (CiA 301).

The node is a deterministic function of the frames it receives and the times it is given:
:meth:`CanopenSlave.handle` takes one frame and the node's time and returns the frames it
answers with, :meth:`CanopenSlave.advance` runs its timers up to a time and returns what they
sent, :meth:`CanopenSlave.next_due` says when the next timer is due. No thread and no queue is
needed for that: an in-process bus on the kernel's thread calls them directly
(:meth:`~CanopenSlave.attach` starts the node without a python-can bus). :meth:`start` puts the
same node on a python-can bus instead (:mod:`chcos.apps.sim.canopen_transport`: a receiving
thread, and on ``Clock.REAL`` the bus's periodic send for the heartbeat).

What the node does (every rule on the wire: ``docs/canopen-sim.md``):

* **NMT** - boot-up (``0x700+id``, ``00``) at start and after every reset; INITIALISING ->
  PRE-OPERATIONAL <-> OPERATIONAL / STOPPED by NMT command; no PDO before OPERATIONAL, no SDO or
  EMCY while STOPPED. A reset reloads the power-on values (EDS defaults) unless the area was
  stored by writing ``'save'`` to 0x1010.
* **SDO** - :class:`chcos.apps.sim.sdo_server.SdoServer` (expedited, segmented, block with CRC)
  over :class:`chcos.apps.sim.object_store.ObjectStore` (what exists, access, length, limits)
  and the node's own objects (0x1001, 0x1003, 0x1010/0x1011, the PDO parameters, 0x1016, 0x1017).
* **PDOs** - from 0x1400/0x1600 and 0x1800/0x1A00 as they stand (re-read after a write and a
  reset). Event-driven TPDOs (254/255) go out on change, not within their inhibit time
  (0x180n:03: then at its end), and on their event timer (0x180n:05), which each transmission
  restarts; synchronous ones on every n-th SYNC, type 0 on the SYNC after a change. Synchronous
  RPDOs take effect at the next SYNC, others at once. An RPDO shorter than its mapping is not
  processed and raises EMCY 0x8210; a longer one is processed and raises 0x8220; the next RPDO of
  the right length clears it (error-reset EMCY).
* **Errors** - the error register 0x1001 is the union of the active faults' bits; every EMCY
  carries it. A fault raised sends its EMCY, a fault cleared the error-reset EMCY (code 0000)
  with the register of the faults left. EMCYs respect the inhibit time 0x1015 when the EDS has
  it.
* **Heartbeat** - the producer (0x1017) and a consumer (0x1016): when the node it watches falls
  silent: EMCY 0x8130, the 0x1029 error behaviour, the master-lost hooks (with 0x6007).
* **Timers** - drift-free (:mod:`chcos.apps.sim.canopen_timers`): each due time is the last due
  time plus the period. The node's time is the sum of its :meth:`tick` steps (the kernel's
  virtual clock, a test's steps, or :meth:`run_realtime` on the wall clock); on ``Clock.REAL``
  the heartbeat producer alone is the bus's periodic send (on SocketCAN the kernel's).

canopen's object dictionary objects are held as ``Any``: the library is only partly typed.
"""

from __future__ import annotations

import argparse
import enum
import logging
import struct
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from chcos import resources
from chcos.apps.sim import canopen_pdo as pdos
from chcos.apps.sim.canopen_pdo import PdoConfig
from chcos.apps.sim.canopen_timers import EPSILON, Periodic, TpdoTimer
from chcos.apps.sim.canopen_transport import BusTransport
from chcos.apps.sim.object_store import ObjectStore, fixed_size
from chcos.apps.sim.sdo_server import TIMEOUT, AbortCode, SdoAbort, SdoServer
from chcos.devices.eds_file import read_eds
from chcos.errors import ConfigError
from drivers.codecs.can import CanFrame

__all__ = ["SERVO_EDS", "CanopenSlave", "Clock", "ErrorBits", "Fault", "MasterLost",
           "NmtCommand", "NmtState", "PdoConfig", "ServoAxis", "SlaveStats", "main"]

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
EMCY_RPDO_LENGTH = 0x8210     # PDO not processed due to length error
EMCY_RPDO_TOO_LONG = 0x8220   # PDO length exceeded
#: EMCY codes of the node's own communication errors: a reset of communication ends them.
COMMUNICATION_ERRORS = frozenset({EMCY_HEARTBEAT_LOST, EMCY_RPDO_LENGTH, EMCY_RPDO_TOO_LONG})
SYNC_COB = 0x080
# the abort codes this module's callers name (the full list: sdo_server.AbortCode)
ABORT_NOT_STORED = AbortCode.NOT_STORED
ABORT_STATE = AbortCode.DEVICE_STATE
ABORT_NO_DATA = AbortCode.NO_DATA
ABORT_INVALID_VALUE = AbortCode.VALUE
ABORT_NO_OBJECT = AbortCode.NO_OBJECT


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
    """What times the heartbeat producer: the python-can bus's periodic send (``REAL``: a node
    alive on the wall clock without being ticked; on SocketCAN the kernel's broadcast manager
    times it), or the node's time, the sum of :meth:`CanopenSlave.tick` steps, as every other
    timer (``TICK``: virtual time)."""

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
    """The error-register bits an EMCY error code sets (its class, plus generic): current 2xxx,
    voltage 3xxx, temperature 4xxx, communication 81xx and 82xx (other 8xxx monitoring codes,
    a CiA 402 following error 8611 say, are generic only), device profile Fxxx, manufacturer
    FFxx."""
    bits = ErrorBits.GENERIC
    bits |= {0x2: ErrorBits.CURRENT, 0x3: ErrorBits.VOLTAGE, 0x4: ErrorBits.TEMPERATURE,
             0xF: ErrorBits.PROFILE}.get(code >> 12, ErrorBits(0))
    if code >> 8 in (0x81, 0x82):
        bits |= ErrorBits.COMMUNICATION
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


@dataclass
class _Consumer:
    node: int
    timeout: float
    last: float = 0.0
    armed: bool = False   # supervision starts with the first heartbeat received
    lost: bool = False

    def due(self) -> float | None:
        """When the watched node counts as lost if nothing comes before."""
        return self.last + self.timeout if self.armed and not self.lost else None


@dataclass
class SlaveStats:
    """What the node did, for tests and ``chcos sim`` scripts."""

    boots: int = 0
    syncs: int = 0
    tpdos: int = 0
    rpdos: int = 0
    rpdos_ignored: int = 0
    rpdos_length_errors: int = 0
    emcys: int = 0
    masters_lost: int = 0
    sdo_requests: int = 0
    sdo_aborts: int = 0


Plant = Callable[["CanopenSlave", float], None]
"""A plant model stepped by :meth:`CanopenSlave.tick`: ``plant(slave, dt)``."""

WriteHook = Callable[[int, int, bytes], None]
"""Told of every object an SDO download or an RPDO wrote: ``hook(index, subindex, data)``."""


class FrameLike(Protocol):
    """What the node reads of a received frame (``can.Message`` and
    :class:`drivers.codecs.can.CanFrame` have it)."""

    @property
    def arbitration_id(self) -> int: ...
    @property
    def is_extended_id(self) -> bool: ...
    @property
    def is_remote_frame(self) -> bool: ...
    @property
    def data(self) -> Any: ...


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


class _NodeDictionary:
    """The node's object dictionary as its SDO server sees it: the store's rules, then the
    node's own objects (see :class:`CanopenSlave`)."""

    def __init__(self, node: CanopenSlave) -> None:
        self._node = node

    def read(self, index: int, subindex: int) -> bytes:
        return self._node._sdo_read(index, subindex)

    def open_write(self, index: int, subindex: int) -> int | None:
        return fixed_size(self._node._store.writable(index, subindex))

    def write(self, index: int, subindex: int, data: bytes) -> None:
        self._node._sdo_write(index, subindex, data)


class CanopenSlave:
    """One simulated CANopen node (see the module doc).

    ``interface``/``channel``/``bitrate`` name the python-can bus :meth:`start` opens
    (``virtual`` in tests); ``port`` is the UDP port of interface ``udp_multicast``.
    ``heartbeat_period`` (seconds) is the power-on value of 0x1017 (0: no heartbeat);
    ``tpdo_period`` overrides the event timer of every event-driven TPDO. ``clock`` says what
    the node's time is. ``servo`` attaches the servo plant when the EDS has its objects;
    ``plant`` is stepped after it. ``refuse_start_on_error``: an NMT start leaves the node
    PRE-OPERATIONAL while its error register is set, as many drives do. ``sdo_timeout``:
    seconds between a client's frames before a transfer is aborted (0x05040000). Raises
    :class:`ConfigError` for a bad node id or an unreadable EDS. Every method is thread-safe.
    """

    def __init__(self, node_id: int, eds: str | Path = SERVO_EDS, *, channel: str,
                 interface: str = "virtual", bitrate: int | None = None,
                 port: int | None = None,
                 heartbeat_period: float = 0.1, tpdo_period: float | None = None,
                 clock: Clock = Clock.REAL, servo: bool = True, plant: Plant | None = None,
                 refuse_start_on_error: bool = False, sdo_timeout: float = TIMEOUT) -> None:
        if not 1 <= node_id <= 127:
            raise ConfigError(f"canopen slave: node id {node_id} is not in 1..127")
        try:
            read = read_eds(eds, node_id)
        except ValueError as exc:
            raise ConfigError(f"canopen slave node {node_id}: cannot read EDS {eds}: {exc}") \
                from exc
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
        self._store = ObjectStore(read.od)
        self._sdo = SdoServer(_NodeDictionary(self), sdo_timeout)
        self._factory: dict[tuple[int, int], bytes] = {}
        hb_var = self._store.find(*HEARTBEAT_TIME)
        if hb_var is not None:
            self._factory[HEARTBEAT_TIME] = bytes(hb_var.encode_raw(
                round(heartbeat_period * 1000)))
        self._saved: dict[tuple[int, int], bytes] = {}
        self._init_state()
        self._plants: list[Plant] = []
        self._master_lost_hooks: list[Callable[[CanopenSlave, MasterLost], None]] = []
        self._write_hooks: list[WriteHook] = []
        if servo and all(self._store.find(i, s) is not None for i, s in SERVO_OBJECTS):
            servo_plant = ServoPlant()
            self._plants.append(servo_plant)
            self._master_lost_hooks.append(servo_plant.master_lost)
        if plant is not None:
            self._plants.append(plant)
        self._out: list[CanFrame] = []
        self._sink: Callable[[CanFrame], None] | None = None
        self._started = False
        self._booted = False
        self._transport: BusTransport | None = None
        self._rt_stop = threading.Event()
        self._rt_thread: threading.Thread | None = None
        self.stats = SlaveStats()
        #: Set whenever an RPDO has been applied to the object dictionary.
        self.rpdo_received = threading.Event()
        self._power_on()

    def _init_state(self) -> None:
        """The node's state before its first start: time, timers, faults, PDOs, consumers."""
        self._state = NmtState.INITIALISING
        self._tick_time = 0.0      # the sum of the tick steps
        self._time = 0.0           # the latest time the node was given
        self._hb = Periodic()
        self._hb_suppressed = False
        self._muted = False
        self._faults: dict[int, Fault] = {}
        self._history: list[int] = []   # 0x1003, newest first
        self._aborts: dict[tuple[int, int], int] = {}
        self._tpdos: list[PdoConfig] = []
        self._rpdos: list[PdoConfig] = []
        self._tpdo_timers: dict[int, TpdoTimer] = {}
        self._syncs_seen: dict[int, int] = {}     # synchronous TPDO -> SYNCs since the last
        self._sync_changed: set[int] = set()      # type-0 TPDOs changed since the last SYNC
        self._pending_rpdos: dict[int, bytes] = {}
        self._length_errors: dict[int, int] = {}  # RPDO number -> its length error's EMCY code
        self._consumers: dict[int, _Consumer] = {}
        self._emcy_queue: list[bytes] = []
        self._emcy_last: float | None = None

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Open the python-can bus and boot: boot-up message, PRE-OPERATIONAL, heartbeat.
        Raises :class:`chcos.errors.BusError` if the bus cannot be opened."""
        with self._lock:
            if self._started:
                return
            transport = BusTransport(self._bus_args, self._receive,
                                     f"canopen-slave-{self.node_id}")
            self._transport = transport
            self._begin(transport.send)

    def attach(self, sink: Callable[[CanFrame], None] | None = None) -> None:
        """Boot without a python-can bus: what the node sends on its own (boot-up, what the
        methods called from outside cause) goes to ``sink`` (None: kept until the next
        :meth:`handle`, :meth:`advance` or :meth:`take` returns it); frames reach the node by
        :meth:`handle`, time by :meth:`advance` or :meth:`tick`. For an in-process bus on
        the kernel's thread and for tests scripting the wire; raises :class:`ConfigError` on
        ``Clock.REAL`` (its heartbeat is a bus's periodic send)."""
        if self._clock is not Clock.TICK:
            raise ConfigError(f"canopen slave node {self.node_id}: attach() runs the node on "
                              "its tick time: build it with clock=Clock.TICK")
        with self._lock:
            if not self._started:
                self._begin(sink)

    def _begin(self, sink: Callable[[CanFrame], None] | None) -> None:
        self._sink = sink
        self._started = True
        # the first start keeps what was set before it; a later one is a power cycle
        self._boot(NmtCommand.RESET_NODE, power_on=not self._booted)
        self._booted = True
        self._flush()

    def stop(self) -> None:
        """Stop the real-time thread, the timers and the bus. Idempotent; never raises."""
        self.stop_realtime()
        with self._lock:
            if not self._started:
                return
            self._started = False   # from here on nothing is sent
            self._sink = None
            self._out.clear()
            transport, self._transport = self._transport, None
        # outside the lock: the receiving thread, which is joined here, may be waiting for it
        if transport is not None:
            transport.close()

    def settle(self, timeout: float) -> bool:
        """Wait until every frame sent to this node so far has been handled (its answers
        sent): virtual time must not move on while it is in flight. Only on python-can's
        ``virtual`` interface (its own receiver); elsewhere, and when stopped, True at once.
        False if ``timeout`` wall seconds passed first."""
        transport = self._transport
        return True if transport is None else transport.settle(timeout)

    @property
    def activity(self) -> int:
        """Frames that reached this node plus frames it has handled, since its receiver started
        (``virtual`` interface only; 0 elsewhere): a count that grows whenever something is sent
        to the node and whenever the node is done with it (and has sent its answer)."""
        transport = self._transport
        return 0 if transport is None else transport.activity()

    def __enter__(self) -> CanopenSlave:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the node as a function of frames and time --------------------------------------------

    def now(self) -> float:
        """The node's time: the sum of the :meth:`tick` steps."""
        return self._tick_time


    def handle(self, frame: FrameLike, now: float | None = None) -> list[CanFrame]:
        """Take one received frame at the node's time ``now`` (None: :meth:`now`), after the
        timers due by then; return every frame the node sends in answer (and whatever it had
        not yet handed to a sink). Frames for other nodes are ignored; never raises for a
        frame's content."""
        with self._lock:
            at = self._at(now)
            self._run_timers(at)
            if self._started and not frame.is_remote_frame and not frame.is_extended_id:
                self._dispatch(frame.arbitration_id, bytes(frame.data), at)
            return self.take()

    def advance(self, now: float) -> list[CanFrame]:
        """Run the timers due by ``now`` (heartbeat, event timers, the heartbeat consumer, the
        SDO timeout, held EMCYs); return what they sent."""
        with self._lock:
            self._run_timers(self._at(now))
            return self.take()

    def next_due(self) -> float | None:
        """The node time at which a timer of the node is due next (None: none is running; on
        ``Clock.REAL`` the heartbeat producer, on the wall clock, is not counted)."""
        with self._lock:
            if not self._started:
                return None
            times = [self._hb.due if self._clock is Clock.TICK else None, self._sdo.deadline,
                     *(t.due() for t in self._tpdo_timers.values()),
                     *(c.due() for c in self._consumers.values())]
            if self._emcy_queue and self._emcy_last is not None:
                times.append(self._emcy_last + self._emcy_inhibit())
            due = [t for t in times if t is not None]
            return min(due) if due else None

    def take(self) -> list[CanFrame]:
        """The frames the node sent that no sink has taken yet (oldest first)."""
        with self._lock:
            out, self._out = self._out, []
            return out

    def tick(self, dt: float) -> None:
        """Advance the node's time ``dt`` seconds: the plants, then the timers due. What the
        node sends goes to its bus (or sink)."""
        with self._lock:
            self._tick_time += dt
            for plant in self._plants:
                plant(self, dt)
            self._run_timers(self._at(None))
            self._flush()

    def _at(self, now: float | None) -> float:
        """The time of what happens now: ``now`` (or the clock's), never before the latest."""
        self._time = max(self._time, self.now() if now is None else now)
        return self._time

    def _receive(self, frame: Any) -> list[CanFrame]:
        """A frame from the python-can transport's thread: handled and answered under the
        node's lock, so that what the node sends from its threads keeps its order."""
        with self._lock:
            out = self.handle(frame)
            if self._sink is not None:
                for answer in out:
                    self._sink(answer)
                return []
            return out

    def _flush(self) -> None:
        """Hand what was sent to the sink, if there is one (else it waits for :meth:`take`)."""
        if self._sink is not None and self._out:
            out, self._out = self._out, []
            for frame in out:
                self._sink(frame)

    def _send(self, cob_id: int, data: bytes) -> None:
        if self._started:
            self._out.append(CanFrame(cob_id, bytes(data)))

    def _dispatch(self, cob: int, data: bytes, now: float) -> None:
        if cob == 0x000:
            self._on_nmt(data, now)
        elif cob == SYNC_COB:
            self._on_sync(now)
        elif cob == 0x600 + self.node_id:
            self._on_sdo(data, now)
        elif 0x701 <= cob <= 0x77F and cob - 0x700 in self._consumers:
            self._on_master_heartbeat(cob - 0x700, now)
        elif any(p.enabled and p.cob_id == cob for p in self._rpdos):
            self._on_rpdo(cob, data, now)

    def _run_timers(self, now: float) -> None:
        if not self._started:
            return
        if self._clock is Clock.TICK:
            for _due in self._hb.fire(now):
                self._heartbeat_frame()
        self._supervise(now)
        for pdo in self._tpdos:
            timer = self._tpdo_timers.get(pdo.number)
            if timer is not None:
                for _due in timer.fire(now):
                    self._transmit(pdo)
        for answer in self._sdo.expire(now):
            self.stats.sdo_aborts += 1
            self._send(0x580 + self.node_id, answer)
        self._release_emcys(now)

    # -- object dictionary --------------------------------------------------------------------

    def get(self, index: int, subindex: int = 0) -> Any:
        """The decoded value of object ``index:subindex``; raises :class:`ConfigError` if the EDS
        has no such object (sub-index 0 only for a plain variable)."""
        with self._lock:
            return self._var(index, subindex).decode_raw(self._raw(index, subindex))

    def set(self, index: int, subindex: int, value: Any) -> None:
        """Set object ``index:subindex`` as the device would (no access check); a change of an
        object in an event-driven TPDO sends that TPDO when OPERATIONAL (after its inhibit
        time). Raises :class:`ConfigError` for an object the EDS lacks or a value its type
        cannot hold."""
        with self._lock:
            try:
                data = bytes(self._var(index, subindex).encode_raw(value))
            except (struct.error, TypeError, ValueError, OverflowError) as exc:
                raise ConfigError(f"canopen slave node {self.node_id}: 0x{index:04X}:"
                                  f"{subindex:02X} cannot hold {value!r}: {exc}") from exc
            old = self._store.stored(index, subindex)
            self._store.put(index, subindex, data)
            if old != data:
                self._changed_object(index, subindex, self._at(None))
            self._flush()

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
    def rpdos(self) -> tuple[PdoConfig, ...]:
        """The RPDOs as the node's parameters define them now."""
        with self._lock:
            return tuple(self._rpdos)

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

    def add_write_hook(self, hook: WriteHook) -> None:
        """Call ``hook(index, subindex, data)`` after an SDO download or an RPDO wrote an
        object (in the order they were written)."""
        with self._lock:
            self._write_hooks.append(hook)

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
            self._raise(code, bits, data, self._at(None))
            self._flush()

    def clear_fault(self, code: int | None = None) -> None:
        """Clear fault ``code`` (None: all): the error-reset EMCY (code 0000) goes out with the
        register of the faults left. Clearing a fault that is not active does nothing."""
        with self._lock:
            if code is None:
                had = bool(self._faults)
                self._faults.clear()
                if had:
                    self._emcy(0, ErrorBits(0), b"", self._at(None))
            else:
                self._clear(code, self._at(None))
            self._changed.notify_all()
            self._flush()

    def stop_heartbeat(self) -> None:
        """Stop producing heartbeats (simulates a lost node; SDO and PDO keep working)."""
        with self._lock:
            self._hb_suppressed = True
            self._real_heartbeat()

    def start_heartbeat(self, period: float | None = None) -> None:
        """Resume heartbeats, every ``period`` seconds from now when given (written to
        0x1017); else at the producer's next due time (``Clock.TICK``) or at once
        (``Clock.REAL``)."""
        with self._lock:
            self._hb_suppressed = False
            if period is not None and self._store.find(*HEARTBEAT_TIME) is not None:
                self._store.put(*HEARTBEAT_TIME,
                                self._var(*HEARTBEAT_TIME).encode_raw(round(period * 1000)))
                self._hb.start(self._at(None), self._hb_period())
            self._real_heartbeat()
            self._flush()

    def silence(self) -> None:
        """Stop heartbeats, PDOs and EMCYs (SDO keeps answering); values set meanwhile are
        kept and go out with the next change or event timer after :meth:`restore`."""
        with self._lock:
            self._muted = True
            self._real_heartbeat()

    def restore(self) -> None:
        """Undo :meth:`silence`."""
        with self._lock:
            self._muted = False
            self._real_heartbeat()

    def send_emcy(self, code: int, register: int = 0, data: bytes = b"") -> None:
        """Send one raw EMCY frame (``code`` 0 is an error reset); 0x1001 is not changed (see
        :meth:`inject_fault`)."""
        with self._lock:
            self._emcy(code, ErrorBits(register), data, self._at(None))
            self._flush()

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
            self._flush()

    # -- real time ----------------------------------------------------------------------------

    def run_realtime(self, step: float = 0.01) -> None:
        """Start a thread calling :meth:`tick` every ``step`` seconds of real time, with the
        wall time since the last call: the node's time follows the wall clock."""
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
        var = self._store.find(index, subindex)
        if var is None:
            raise ConfigError(f"canopen slave node {self.node_id}: no object "
                              f"0x{index:04X}:{subindex:02X} in {self.eds}")
        return var

    def _raw(self, index: int, subindex: int) -> bytes:
        """The object's bytes as the SDO server would answer, without injected aborts."""
        if index == 0x1001 and subindex == 0:
            return bytes([int(self.error_register)])
        return self._store.raw(index, subindex)

    def _int(self, index: int, subindex: int, missing: int = 0) -> int:
        """An integer object's value, ``missing`` when the EDS lacks it."""
        return pdos.integer(self._store, index, subindex, missing)

    def _power_on(self) -> None:
        """The object dictionary as at power-on: EDS defaults, the constructor's values, what
        was stored."""
        self._store.clear()
        self._load_area(lambda index: True)

    def _load_area(self, area: Callable[[int], bool]) -> None:
        for values in (self._factory, self._saved):
            for (index, sub), data in values.items():
                if area(index):
                    self._store.put(index, sub, data)

    def _save(self, sub: int) -> None:
        """Store an area (0x1010 sub 1 all, 2 communication, 3 application, 4 manufacturer)."""
        area = _AREAS.get(sub, _AREAS[1])
        for key in [k for k in self._saved if area(k[0])]:
            del self._saved[key]
        for (index, s), data in self._store.items():
            if area(index) and index not in (0x1001, 0x1010, 0x1011):
                self._saved[(index, s)] = data

    def _history_depth(self) -> int:
        """How many errors 0x1003 holds (its sub-indices in the EDS)."""
        return len([s for s in self._store.subindices(0x1003) if s])

    # -- internals: SDO -----------------------------------------------------------------------

    def _on_sdo(self, data: bytes, now: float) -> None:
        if self._state in (NmtState.STOPPED, NmtState.INITIALISING):
            return
        self.stats.sdo_requests += 1
        for answer in self._sdo.receive(data, now):
            if answer[0] == 0x80:
                self.stats.sdo_aborts += 1
            self._send(0x580 + self.node_id, answer)

    def _sdo_read(self, index: int, subindex: int) -> bytes:
        """An upload: injected aborts, then the store's rules, then the node's own objects."""
        code = self._aborts.get((index, subindex))
        if code is not None:
            raise SdoAbort(code)
        var = self._store.readable(index, subindex)
        if index == 0x1003 and subindex > 0:   # pre-defined error field: newest first
            if subindex > len(self._history):
                raise SdoAbort(AbortCode.NO_DATA)
            return bytes(var.encode_raw(self._history[subindex - 1]))
        if index == 0x1003:
            return bytes(var.encode_raw(len(self._history)))
        if index in (0x1010, 0x1011) and subindex >= 1:
            return bytes(var.encode_raw(1))   # saves / restores on command
        return self._raw(index, subindex)

    def _sdo_write(self, index: int, subindex: int, data: bytes) -> None:
        """A download: the store's rules, the node's own objects, then it takes effect."""
        var = self._store.writable(index, subindex)
        self._store.check_value(var, data)
        value = int.from_bytes(data[:4], "little")
        now = self._time
        if index in (0x1010, 0x1011) and subindex >= 1:
            self._store_command(index, subindex, value)
            return
        if index == 0x1003:
            if subindex != 0 or value != 0:
                raise SdoAbort(AbortCode.VALUE)   # only 0 (clear) may be written
            self._history.clear()
            return
        if 0x1400 <= index <= 0x1BFF:
            pdos.check_write(self._store, index, subindex, value)
        self._store.put(index, subindex, data)
        if index == 0x1017:
            self._hb.start(now, self._hb_period())
            self._real_heartbeat()
        elif index == 0x1016:
            self._read_consumers()
        elif 0x1400 <= index <= 0x1BFF:
            self._read_pdos(now)
        self._changed_object(index, subindex, now)
        for hook in list(self._write_hooks):
            hook(index, subindex, data)

    def _store_command(self, index: int, subindex: int, value: int) -> None:
        """0x1010 ('save': store an area) and 0x1011 ('load': EDS defaults from the next
        reset); another signature is refused with 0x08000020."""
        if value != (SAVE_SIGNATURE if index == 0x1010 else LOAD_SIGNATURE):
            raise SdoAbort(AbortCode.NOT_STORED)
        if index == 0x1010:
            self._save(subindex)
            return
        area = _AREAS.get(subindex, _AREAS[1])
        for key in [k for k in self._saved if area(k[0])]:
            del self._saved[key]

    # -- internals: PDO, SYNC, EMCY -----------------------------------------------------------

    def _event_period(self, pdo: PdoConfig) -> float | None:
        if not pdo.enabled or not pdo.event_driven:
            return None
        if self._tpdo_period is not None:
            return self._tpdo_period
        return pdo.event_timer_ms / 1000 if pdo.event_timer_ms else None

    def _read_pdos(self, now: float) -> None:
        """(Re)read every PDO's parameters; a TPDO whose timing changed restarts its timer."""
        self._tpdos = pdos.read_all(self._store, pdos.TPDO_COMM, pdos.TPDO_MAP)
        self._rpdos = pdos.read_all(self._store, pdos.RPDO_COMM, pdos.RPDO_MAP)
        timers: dict[int, TpdoTimer] = {}
        for pdo in self._tpdos:
            if not (pdo.enabled and pdo.event_driven):
                continue
            timer = self._tpdo_timers.get(pdo.number) or TpdoTimer()
            event = self._event_period(pdo)
            if pdo.number not in self._tpdo_timers or (timer.inhibit, timer.event) != \
                    (pdo.inhibit, event):
                timer.configure(now, pdo.inhibit, event)
            timers[pdo.number] = timer
        self._tpdo_timers = timers

    def _changed_object(self, index: int, subindex: int, now: float) -> None:
        for pdo in self._tpdos:
            if not pdo.maps(index, subindex):
                continue
            timer = self._tpdo_timers.get(pdo.number)
            if timer is not None:
                if timer.changed(now) and self._transmit(pdo):
                    timer.sent(now)
            elif pdo.trans_type == 0:
                self._sync_changed.add(pdo.number)
        self._changed.notify_all()

    def _transmit(self, pdo: PdoConfig) -> bool:
        """Send one TPDO now (when OPERATIONAL and not silenced); True if it went out."""
        if not (self._started and pdo.enabled and self._state is NmtState.OPERATIONAL) \
                or self._muted:
            return False
        self.stats.tpdos += 1
        self._send(pdo.cob_id, pdos.pack(self._store, pdo))
        return True

    def _tpdo_event_period(self) -> float | None:
        """The shortest event period of the enabled event-driven TPDOs (``tpdo_period`` when
        given), None without one."""
        periods = [p for pdo in self._tpdos if (p := self._event_period(pdo)) is not None]
        return min(periods) if periods else None

    def _on_sync(self, now: float) -> None:
        self.stats.syncs += 1
        if self._state is not NmtState.OPERATIONAL:
            return
        for cob, frame in list(self._pending_rpdos.items()):
            self._apply_rpdo(cob, frame, now)
        self._pending_rpdos.clear()
        for pdo in self._tpdos:
            if not pdo.enabled or not pdo.synchronous:
                continue
            if pdo.trans_type == 0:
                if pdo.number in self._sync_changed:
                    self._sync_changed.discard(pdo.number)
                    self._transmit(pdo)
                continue
            seen = self._syncs_seen.get(pdo.number, 0) + 1
            self._syncs_seen[pdo.number] = 0 if seen >= pdo.trans_type else seen
            if seen >= pdo.trans_type:
                self._transmit(pdo)

    def _on_rpdo(self, cob: int, data: bytes, now: float) -> None:
        if self._state is not NmtState.OPERATIONAL:
            self.stats.rpdos_ignored += 1
            return
        pdo = next(p for p in self._rpdos if p.enabled and p.cob_id == cob)
        if len(data) < pdo.length:            # not processed: EMCY 0x8210
            self.stats.rpdos_length_errors += 1
            self._length_error(pdo, EMCY_RPDO_LENGTH, len(data), now)
            return
        if len(data) > pdo.length:            # processed, the first bytes: EMCY 0x8220
            self.stats.rpdos_length_errors += 1
            self._length_error(pdo, EMCY_RPDO_TOO_LONG, len(data), now)
        else:
            self._length_ok(pdo, now)
        if pdo.synchronous:
            self._pending_rpdos[cob] = data   # takes effect at the next SYNC
            return
        self._apply_rpdo(cob, data, now)

    def _length_error(self, pdo: PdoConfig, code: int, received: int, now: float) -> None:
        """RPDO ``pdo`` arrived with ``received`` bytes: raise ``code`` (once, until an RPDO of
        the right length clears it). The EMCY's manufacturer bytes: the PDO number (16 bits),
        the bytes received, the bytes mapped."""
        old = self._length_errors.get(pdo.number)
        if old == code:
            return
        self._length_errors[pdo.number] = code
        if old is not None and old not in self._length_errors.values():
            self._clear(old, now)
        if code not in self._faults:
            self._raise(code, error_bits(code),
                        struct.pack("<HBB", pdo.number, received, pdo.length), now)

    def _length_ok(self, pdo: PdoConfig, now: float) -> None:
        old = self._length_errors.pop(pdo.number, None)
        if old is not None and old not in self._length_errors.values():
            self._clear(old, now)

    def _apply_rpdo(self, cob_id: int, data: bytes, now: float) -> None:
        pdo = next((p for p in self._rpdos if p.enabled and p.cob_id == cob_id), None)
        if pdo is None:
            return
        for index, subindex, raw in pdos.unpack(self._store, pdo, data[:pdo.length]):
            self._store.put(index, subindex, raw)
            self._changed_object(index, subindex, now)
            for hook in list(self._write_hooks):
                hook(index, subindex, raw)
        self.stats.rpdos += 1
        self._changed.notify_all()
        self.rpdo_received.set()

    def _raise(self, code: int, bits: ErrorBits, data: bytes, now: float) -> None:
        """A fault: 0x1001 gets its bits, 0x1003 its code, and its EMCY goes out."""
        self._faults[code] = Fault(code, bits, data)
        depth = self._history_depth()
        if depth:
            self._history = [code, *self._history][:depth]
        self._emcy(code, self.error_register, data, now)
        self._changed.notify_all()

    def _clear(self, code: int, now: float) -> None:
        """A fault over: the error-reset EMCY with the register of the faults left."""
        if self._faults.pop(code, None) is not None:
            self._emcy(0, self.error_register, b"", now)

    def _emcy_inhibit(self) -> float:
        """0x1015, the EMCY inhibit time, seconds (0 when the EDS has none)."""
        return self._int(0x1015, 0) / 10_000

    def _emcy(self, code: int, register: ErrorBits, data: bytes, now: float) -> None:
        if self._state in (NmtState.STOPPED, NmtState.INITIALISING) or self._muted:
            return
        frame = struct.pack("<HB", code, int(register)) + data.ljust(5, b"\x00")[:5]
        inhibit = self._emcy_inhibit()
        if self._emcy_queue or (inhibit and self._emcy_last is not None
                                and now < self._emcy_last + inhibit - EPSILON):
            self._emcy_queue.append(frame)    # held until the inhibit time is over
            return
        self._emcy_frame(frame, now)

    def _emcy_frame(self, frame: bytes, at: float) -> None:
        cob = self._int(0x1014, 0, 0x80 + self.node_id)
        if cob & 0x8000_0000:
            return   # EMCY disabled in 0x1014
        self._emcy_last = at
        self.stats.emcys += 1
        self._send(cob & 0x7FF, frame)

    def _release_emcys(self, now: float) -> None:
        inhibit = self._emcy_inhibit()
        while self._emcy_queue and self._emcy_last is not None:
            due = self._emcy_last + inhibit
            if now < due - EPSILON:
                return
            self._emcy_frame(self._emcy_queue.pop(0), due)

    # -- internals: NMT, heartbeat, consumer --------------------------------------------------

    def _boot(self, command: NmtCommand, power_on: bool = False) -> None:
        """Reset (node or communication), send the boot-up message and enter PRE-OPERATIONAL."""
        now = self._at(None)
        self._set_state(NmtState.INITIALISING)
        self._sdo.reset()
        if command is NmtCommand.RESET_NODE:
            if not power_on:
                self._power_on()
        else:
            comm = _AREAS[2]
            for (index, sub), _data in self._store.items():
                if comm(index):
                    self._store.drop(index, sub)
            self._load_area(comm)
        for code in COMMUNICATION_ERRORS:   # the node's own: gone with the communication
            self._faults.pop(code, None)
        self._length_errors.clear()
        self._pending_rpdos.clear()
        self._syncs_seen.clear()
        self._sync_changed.clear()
        self._emcy_queue.clear()
        self._tpdo_timers = {}
        self._read_pdos(now)
        self._read_consumers()
        self.stats.boots += 1
        self._send(0x700 + self.node_id, b"\x00")
        self._set_state(NmtState.PRE_OPERATIONAL)
        self._hb.start(now, self._hb_period())
        self._real_heartbeat()
        for fault in self._faults.values():   # a fault still present is reported again
            self._emcy(fault.code, self.error_register, fault.data, now)

    def _set_state(self, state: NmtState) -> None:
        if state == self._state:
            return
        if state in (NmtState.STOPPED, NmtState.INITIALISING):
            self._sdo.reset()
        self._state = state
        transport = self._transport
        if self._clock is Clock.REAL and transport is not None:
            if state is NmtState.INITIALISING:
                transport.stop_periodic()
            else:   # the next heartbeat carries the new state, its timing kept
                transport.modify_periodic(CanFrame(0x700 + self.node_id, bytes([int(state)])))
        self._changed.notify_all()

    def _real_heartbeat(self) -> None:
        """``Clock.REAL``: (re)start the bus's periodic heartbeat (the first at once), or stop
        it while the node is silenced, suppressed or initialising."""
        transport = self._transport
        if self._clock is not Clock.REAL or transport is None:
            return
        self._flush()   # what the node sent before (its boot-up) goes out first
        if self._started and not (self._hb_suppressed or self._muted) \
                and self._state is not NmtState.INITIALISING:
            transport.periodic(CanFrame(0x700 + self.node_id, bytes([int(self._state)])),
                               self._hb_period())
        else:
            transport.stop_periodic()

    def _hb_period(self) -> float:
        return self._int(*HEARTBEAT_TIME) / 1000

    def _heartbeat_frame(self) -> None:
        if not (self._hb_suppressed or self._muted or self._state is NmtState.INITIALISING):
            self._send(0x700 + self.node_id, bytes([int(self._state)]))

    def _on_nmt(self, data: bytes, now: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id):
            return
        try:
            command = NmtCommand(data[0])
        except ValueError:
            return  # an unknown command specifier is ignored, as by a real node
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

    def _read_consumers(self) -> None:
        old = self._consumers
        self._consumers = {}
        if self._store.has(0x1016):
            for sub in range(1, self._int(0x1016, 0) + 1):
                entry = self._int(0x1016, sub)
                nid, ms = (entry >> 16) & 0x7F, entry & 0xFFFF
                if nid and ms:
                    kept = old.get(nid)
                    self._consumers[nid] = kept if kept is not None and \
                        kept.timeout == ms / 1000 else _Consumer(nid, ms / 1000)

    def _on_master_heartbeat(self, node: int, now: float) -> None:
        consumer = self._consumers[node]
        consumer.last = now
        consumer.armed = True
        if consumer.lost:
            consumer.lost = False
            if not any(c.lost for c in self._consumers.values()):
                self._clear(EMCY_HEARTBEAT_LOST, now)
                self._changed.notify_all()

    def _supervise(self, now: float) -> None:
        for consumer in self._consumers.values():
            due = consumer.due()
            if due is None or now <= due + EPSILON:
                continue
            consumer.lost = True
            self.stats.masters_lost += 1
            self._raise(EMCY_HEARTBEAT_LOST, ErrorBits.GENERIC | ErrorBits.COMMUNICATION,
                        b"", now)
            try:
                behaviour = ErrorBehaviour(self._int(0x1029, 1))
            except ValueError:
                behaviour = ErrorBehaviour.NO_CHANGE
            if behaviour is ErrorBehaviour.PRE_OPERATIONAL and \
                    self._state is NmtState.OPERATIONAL:
                self._set_state(NmtState.PRE_OPERATIONAL)
            elif behaviour is ErrorBehaviour.STOPPED:
                self._set_state(NmtState.STOPPED)
            option = self._int(0x6007, 0) if self._store.find(0x6007, 0) is not None else None
            event = MasterLost(consumer.node, consumer.timeout, option)
            for hook in list(self._master_lost_hooks):
                hook(self, event)


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
    from chcos.errors import BusError

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
    try:
        _run_faults(slave, faults, args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        slave.stop()
    return 0


def _run_faults(slave: CanopenSlave, faults: list[tuple[int, float, float]],
                duration: float | None) -> None:
    """Raise and clear the ``--fault`` items on the node's (real-time) clock until
    ``duration`` seconds have passed (None: until interrupted)."""
    done = threading.Event()
    start = slave.now()
    active: set[int] = set()
    while not done.wait(0.05):
        t = slave.now() - start
        for code, t0, t1 in faults:
            if t0 <= t < t1 and code not in active:
                slave.inject_fault(code)
                active.add(code)
                print(f"t={t:6.1f} s  fault 0x{code:04X} raised", flush=True)
            elif t >= t1 and code in active:
                slave.clear_fault(code)
                active.discard(code)
                print(f"t={t:6.1f} s  fault 0x{code:04X} cleared", flush=True)
        if duration is not None and t >= duration:
            return


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
