"""cia402 - the CiA 402 drive profile as pure logic: the power state machine as data, the planner
that walks it, the modes of operation, and :class:`Axis`, an engine of commands that complete.

No I/O here. A host (the CANopen driver, a test) feeds an :class:`Axis` the drive's readings
(statusword 0x6041, modes display 0x6061, position 0x6064, velocity 0x606C, error code 0x603F)
and the time, and sends what it returns: object writes (in order, one frame or SDO each),
object reads to request, and the results of commands (done, or failed naming the state reached,
the statusword and 0x603F). The engine never commands anything by itself: a drive that faulted
stays disabled until a task asks for a fault reset and then an enable.

Object indices are those of axis 0; :attr:`AxisConfig.axis` shifts them by 0x800 per axis for
multi-axis drives.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import Enum, IntEnum
from typing import Any

from chcos.errors import ChcosError

# -- objects -----------------------------------------------------------------------------------


class Obj(IntEnum):
    """The CiA 402 objects an axis uses (index of axis 0, sub-index 0)."""

    ERROR_CODE = 0x603F
    CONTROLWORD = 0x6040
    STATUSWORD = 0x6041
    QUICK_STOP_OPTION = 0x605A
    MODES = 0x6060
    MODES_DISPLAY = 0x6061
    POSITION_ACTUAL = 0x6064
    VELOCITY_ACTUAL = 0x606C
    TARGET_POSITION = 0x607A
    PROFILE_VELOCITY = 0x6081
    TARGET_VELOCITY = 0x60FF


#: Index offset between the axes of a multi-axis drive.
AXIS_OFFSET = 0x800


# -- errors ------------------------------------------------------------------------------------


class Cia402Error(ChcosError):
    """Root of the CiA 402 profile's errors."""


class StatuswordError(Cia402Error):
    """A statusword matches no state of the CiA 402 state machine."""


class Unreachable(Cia402Error):
    """A target cannot be reached from the drive's state by the controlword alone (a fault
    needs a fault reset first). ``state`` is the state it was asked from."""

    def __init__(self, state: State, target: Target) -> None:
        super().__init__(f"{target.name} cannot be reached from {state.name}"
                         + (" (a fault reset is needed first)"
                            if state in (State.FAULT, State.FAULT_REACTION_ACTIVE) else ""))
        self.state = state
        self.target = target


class AxisBusy(Cia402Error):
    """A command was given while another one runs (only quick stop, disable and safe stop
    supersede a running command)."""


class AxisLimitError(Cia402Error):
    """A set-point is outside the axis's limits or not a finite number; nothing was written."""


class AxisCommandFailed(Cia402Error):
    """A command of an axis ended without the drive confirming it: ``result`` names the
    command, the state reached, the statusword and 0x603F (its ``str`` is the message)."""

    def __init__(self, axis: str, result: Result) -> None:
        super().__init__(f"axis {axis}: {result}")
        self.axis = axis
        self.result = result


# -- the state machine as data ---------------------------------------------------------------


class State(Enum):
    """The power states of CiA 402 (statusword bits 0-3, 5, 6)."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


#: (mask, value, state): the statusword patterns of CiA 402, first match wins.
STATUS_PATTERNS: tuple[tuple[int, int, State], ...] = (
    (0x004F, 0x0000, State.NOT_READY_TO_SWITCH_ON),
    (0x004F, 0x0040, State.SWITCH_ON_DISABLED),
    (0x006F, 0x0021, State.READY_TO_SWITCH_ON),
    (0x006F, 0x0023, State.SWITCHED_ON),
    (0x006F, 0x0027, State.OPERATION_ENABLED),
    (0x006F, 0x0007, State.QUICK_STOP_ACTIVE),
    (0x004F, 0x000F, State.FAULT_REACTION_ACTIVE),
    (0x004F, 0x0008, State.FAULT),
)

SW_VOLTAGE_ENABLED = 1 << 4
SW_WARNING = 1 << 7
SW_REMOTE = 1 << 9
SW_TARGET_REACHED = 1 << 10
SW_INTERNAL_LIMIT = 1 << 11
#: PP: set-point acknowledge; PV: speed 0; HM: homing attained.
SW_OMS12 = 1 << 12
#: PP/CSP: following error; HM: homing error.
SW_OMS13 = 1 << 13

CW_SWITCH_ON = 1 << 0
CW_ENABLE_VOLTAGE = 1 << 1
CW_QUICK_STOP = 1 << 2
CW_ENABLE_OPERATION = 1 << 3
#: PP: new set-point; HM: homing operation start.
CW_OMS4 = 1 << 4
#: PP: change set immediately.
CW_OMS5 = 1 << 5
CW_FAULT_RESET = 1 << 7
CW_HALT = 1 << 8


def decode_state(statusword: int) -> State:
    """The state a statusword shows. Raises :class:`StatuswordError` for a pattern CiA 402
    does not define (e.g. 0x0001)."""
    for mask, value, state in STATUS_PATTERNS:
        if statusword & mask == value:
            return state
    raise StatuswordError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


class Command(Enum):
    """The device control commands of CiA 402 (:data:`CONTROLWORDS` gives their controlwords).
    Fault reset is a rising edge of bit 7: bit 7 clear, then set."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"
    ENABLE_OPERATION = "enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    DISABLE_OPERATION = "disable operation"
    FAULT_RESET = "fault reset"

    @property
    def controlword(self) -> int:
        """The controlword that gives the command (for fault reset, the one with bit 7 set)."""
        return CONTROLWORDS[self][-1]

    @property
    def sequence(self) -> tuple[int, ...]:
        """The controlwords to send in order (two for the fault reset's edge)."""
        return CONTROLWORDS[self]


#: Command -> the controlwords that give it, in order.
CONTROLWORDS: dict[Command, tuple[int, ...]] = {
    Command.SHUTDOWN: (0x0006,),
    Command.SWITCH_ON: (0x0007,),
    Command.ENABLE_OPERATION: (0x000F,),
    Command.DISABLE_VOLTAGE: (0x0000,),
    Command.QUICK_STOP: (0x0002,),
    Command.DISABLE_OPERATION: (0x0007,),
    Command.FAULT_RESET: (0x0000, 0x0080),
}


def decode_command(controlword: int, previous: int | None = None) -> Command | None:
    """The command a controlword gives after ``previous`` (None: unknown, no edge possible),
    per the CiA 402 table; None for a pattern that is no command. Switch on and disable
    operation share 0x07: the result is SWITCH_ON, :data:`TRANSITIONS` treats both alike."""
    if controlword & CW_FAULT_RESET and previous is not None and not previous & CW_FAULT_RESET:
        return Command.FAULT_RESET
    if not controlword & CW_ENABLE_VOLTAGE:
        return Command.DISABLE_VOLTAGE
    if not controlword & CW_QUICK_STOP:
        return Command.QUICK_STOP
    low = controlword & 0x0F
    if low == 0x06:
        return Command.SHUTDOWN
    if low == 0x07:
        return Command.SWITCH_ON
    if low == 0x0F:
        return Command.ENABLE_OPERATION
    return None


#: (state, command) -> state after the command, for every commanded transition of CiA 402
#: (transition numbers of the standard's diagram in the comments). A pair absent here leaves
#: the state unchanged. Quick stop's outcome from OPERATION_ENABLED is QUICK_STOP_ACTIVE; from
#: there the drive goes on by itself to SWITCH_ON_DISABLED unless 0x605A is 5..8
#: (:func:`quick_stop_stays`).
TRANSITIONS: dict[tuple[State, Command], State] = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,            # 2
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): State.SWITCHED_ON,                  # 3
    (State.READY_TO_SWITCH_ON, Command.DISABLE_OPERATION): State.SWITCHED_ON,          # 3
    (State.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,     # 3+4
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,     # 7
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,          # 7
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,            # 4
    (State.SWITCHED_ON, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,                   # 6
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,            # 10
    (State.SWITCHED_ON, Command.QUICK_STOP): State.SWITCH_ON_DISABLED,                 # 10
    (State.OPERATION_ENABLED, Command.DISABLE_OPERATION): State.SWITCHED_ON,           # 5
    (State.OPERATION_ENABLED, Command.SWITCH_ON): State.SWITCHED_ON,                   # 5
    (State.OPERATION_ENABLED, Command.SHUTDOWN): State.READY_TO_SWITCH_ON,             # 8
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,      # 9
    (State.OPERATION_ENABLED, Command.QUICK_STOP): State.QUICK_STOP_ACTIVE,            # 11
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): State.SWITCH_ON_DISABLED,      # 12
    (State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): State.OPERATION_ENABLED,      # 16
    (State.FAULT, Command.FAULT_RESET): State.SWITCH_ON_DISABLED,                      # 15
}

#: States the drive leaves by itself (transitions 0/1, 14), whatever it is commanded.
AUTOMATIC: dict[State, State] = {
    State.NOT_READY_TO_SWITCH_ON: State.SWITCH_ON_DISABLED,
    State.FAULT_REACTION_ACTIVE: State.FAULT,
}


def quick_stop_stays(option: int) -> bool:
    """True when quick stop option code ``option`` (0x605A) keeps the drive in QUICK_STOP_ACTIVE
    after it stopped (5..8); otherwise (0..4, and the manufacturer's negative codes, taken as
    the default 2) the drive goes on to SWITCH_ON_DISABLED by itself."""
    return 5 <= option <= 8


def next_state(state: State, command: Command, quick_stop_option: int = 2) -> State:
    """The state a drive in ``state`` goes to on ``command``: :data:`TRANSITIONS`, except that
    transition 16 (quick stop active -> operation enabled) exists only for option codes 5..8."""
    if (state is State.QUICK_STOP_ACTIVE and command is Command.ENABLE_OPERATION
            and not quick_stop_stays(quick_stop_option)):
        return state
    return TRANSITIONS.get((state, command), state)


# -- the planner -------------------------------------------------------------------------------


class Target(Enum):
    """Where a command wants the drive's state machine."""

    ENABLED = "operation enabled"
    DISABLED = "switch on disabled"
    QUICK_STOP = "quick stopped"
    FAULT_CLEARED = "fault cleared"


class Plan(Enum):
    """What the planner says besides a controlword."""

    DONE = "done"
    WAIT = "wait"


#: target -> state -> the next command, or a Plan. A state absent for a target is unreachable.
PLANNER: dict[Target, dict[State, Command | Plan]] = {
    Target.ENABLED: {
        State.NOT_READY_TO_SWITCH_ON: Plan.WAIT,
        State.SWITCH_ON_DISABLED: Command.SHUTDOWN,
        State.READY_TO_SWITCH_ON: Command.SWITCH_ON,
        State.SWITCHED_ON: Command.ENABLE_OPERATION,
        State.OPERATION_ENABLED: Plan.DONE,
        # out of a quick stop through switch on disabled: transition 16 exists only on some
        # option codes, and the walk from the bottom is valid on all of them
        State.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,
    },
    Target.DISABLED: {
        State.NOT_READY_TO_SWITCH_ON: Plan.WAIT,
        State.SWITCH_ON_DISABLED: Plan.DONE,
        State.READY_TO_SWITCH_ON: Command.DISABLE_VOLTAGE,
        State.SWITCHED_ON: Command.DISABLE_VOLTAGE,
        State.OPERATION_ENABLED: Command.DISABLE_VOLTAGE,
        State.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,
    },
    Target.QUICK_STOP: {
        State.NOT_READY_TO_SWITCH_ON: Plan.WAIT,
        State.SWITCH_ON_DISABLED: Plan.DONE,
        State.READY_TO_SWITCH_ON: Command.QUICK_STOP,
        State.SWITCHED_ON: Command.QUICK_STOP,
        State.OPERATION_ENABLED: Command.QUICK_STOP,
        State.QUICK_STOP_ACTIVE: Plan.DONE,
    },
    Target.FAULT_CLEARED: {
        State.NOT_READY_TO_SWITCH_ON: Plan.WAIT,
        State.SWITCH_ON_DISABLED: Plan.DONE,
        State.READY_TO_SWITCH_ON: Plan.DONE,
        State.SWITCHED_ON: Plan.DONE,
        State.OPERATION_ENABLED: Plan.DONE,
        State.QUICK_STOP_ACTIVE: Plan.DONE,
        State.FAULT_REACTION_ACTIVE: Plan.WAIT,
        State.FAULT: Command.FAULT_RESET,
    },
}


def plan(state: State, target: Target) -> Command | Plan:
    """The next command that brings a drive in ``state`` toward ``target``, or
    :attr:`Plan.DONE` (there) or :attr:`Plan.WAIT` (the drive moves on by itself). Raises
    :class:`Unreachable` naming the state when the controlword cannot get there (a fault:
    nothing but a fault reset leaves it)."""
    step = PLANNER[target].get(state)
    if step is None:
        raise Unreachable(state, target)
    return step


def next_controlwords(state: State, target: Target) -> tuple[int, ...]:
    """The controlword(s) to send next from ``state`` toward ``target``, in order (two for a
    fault reset's edge); empty when there (or when the drive moves on by itself). Raises
    :class:`Unreachable` naming the state."""
    step = plan(state, target)
    return step.sequence if isinstance(step, Command) else ()


# -- modes -------------------------------------------------------------------------------------


class Mode(IntEnum):
    """Modes of operation (0x6060, confirmed on 0x6061)."""

    NONE = 0
    PP = 1    # profile position
    VL = 2    # velocity
    PV = 3    # profile velocity
    PT = 4    # profile torque
    HM = 6    # homing
    IP = 7    # interpolated position
    CSP = 8   # cyclic synchronous position
    CSV = 9   # cyclic synchronous velocity
    CST = 10  # cyclic synchronous torque


def mode_name(value: int | None) -> str:
    """``value`` of 0x6061 for a message: ``"1 (PP)"``, ``"-3 (manufacturer)"``, ``"unknown"``."""
    if value is None:
        return "unknown"
    try:
        return f"{value} ({Mode(value).name})"
    except ValueError:
        return f"{value} ({'manufacturer' if value < 0 else 'reserved'})"


# -- the axis engine ---------------------------------------------------------------------------


class Op(Enum):
    """The commands of an :class:`Axis`."""

    ENABLE = "enable"
    DISABLE = "disable"
    QUICK_STOP = "quick stop"
    FAULT_RESET = "fault reset"
    SET_MODE = "set mode"
    HOME = "home"
    MOVE_TO = "move to"
    AT_VELOCITY = "at velocity"
    SAFE_STOP = "safe stop"


class SafeStop(Enum):
    """The safe action of an axis (e-stop, abnormal completion, shutdown, node failure)."""

    QUICK_STOP_THEN_DISABLE = "quick stop, then disable voltage once stopped"
    HALT_THEN_DISABLE = "halt, then disable voltage once stopped"
    QUICK_STOP = "quick stop (stay in quick stop active when 0x605A is 5..8)"
    DISABLE_VOLTAGE = "disable voltage at once (the axis coasts)"


@dataclass(frozen=True)
class Timeouts:
    """Seconds each command may take before it fails; ``error_code``: how long a failure by
    fault waits for 0x603F before it is reported without it."""

    enable: float = 2.0
    disable: float = 1.0
    quick_stop: float = 5.0
    fault_reset: float = 1.0
    set_mode: float = 1.0
    home: float = 30.0
    move: float = 30.0
    velocity: float = 10.0
    safe_stop: float = 5.0
    error_code: float = 0.5


@dataclass(frozen=True)
class AxisConfig:
    """One axis of a CiA 402 drive: units, limits, timeouts and safe action.

    ``counts_per_unit``: drive counts per user unit (mm, degree); velocities are units per
    second. ``position_limits``/``max_velocity`` in user units (None: no limit).
    ``position_window``/``velocity_window``: counts within which a target counts as reached;
    ``standstill``: counts per second under which the axis counts as stopped.
    ``edge_gap``: seconds between the two controlwords of a fault reset's edge (they must be two
    frames). ``resend``: seconds after which an unanswered controlword is sent again.
    ``read_every``: seconds between reads requested while a command waits for an object.
    """

    name: str = "axis"
    axis: int = 0
    counts_per_unit: float = 1.0
    position_limits: tuple[float, float] | None = None
    max_velocity: float | None = None
    quick_stop_option: int = 2
    safe_stop: SafeStop = SafeStop.QUICK_STOP_THEN_DISABLE
    timeouts: Timeouts = field(default_factory=Timeouts)
    position_window: int = 0
    velocity_window: int = 0
    standstill: int = 0
    edge_gap: float = 0.01
    resend: float = 0.5
    read_every: float = 0.1

    def __post_init__(self) -> None:
        if not (math.isfinite(self.counts_per_unit) and self.counts_per_unit != 0):
            raise ValueError(f"axis {self.name}: counts_per_unit must be a finite non-zero "
                             f"number, got {self.counts_per_unit!r}")
        if not 0 <= self.axis <= 7:
            raise ValueError(f"axis {self.name}: axis must be 0..7, got {self.axis}")

    def index(self, obj: Obj) -> int:
        """The object index of ``obj`` for this axis (0x800 per axis)."""
        return int(obj) + AXIS_OFFSET * self.axis


class ReceiveOrder:
    """One axis's order of events on the wire: a strictly increasing mark for every reading
    received, every SDO read asked and every controlword sent. A reading is judged against the
    controlword it follows by these marks, never by when the host got round to feeding it (a
    TPDO can wait in a queue behind the write of a newer controlword). Thread-safe without a
    lock (a codec takes no I/O or threading): the marks come from one ``itertools.count``,
    whose ``next`` is atomic, and only the host's reader thread records PDO marks (its I/O
    thread marks writes and SDO reads, and looks PDO marks up).

    It also remembers, per object, the mark of the last PDO that carried it
    (:meth:`pdo_received`), so that an SDO answer asked before that PDO arrived is known to be
    older than a value still on its way to the engine."""

    def __init__(self) -> None:
        self._marks = itertools.count(1)
        self._pdo: dict[Obj, int] = {}

    def mark(self) -> int:
        """The next mark (any thread)."""
        return next(self._marks)

    def pdo_received(self, objs: tuple[Obj, ...]) -> int:
        """The mark of a PDO carrying ``objs``, received now (the reader thread only)."""
        mark = next(self._marks)
        for obj in objs:
            self._pdo[obj] = mark
        return mark

    def last_pdo(self, obj: Obj) -> int:
        """The mark of the last PDO that carried ``obj`` (0: none yet)."""
        return self._pdo.get(obj, 0)


@dataclass(frozen=True)
class Reading:
    """Values read from the drive (raw counts; None: not in this update). A host feeds the
    objects of one PDO in one reading: 0x603F is taken before the statusword.

    ``received``: the reading's :class:`ReceiveOrder` mark, when the host got it (a PDO) or
    asked for it (an SDO read, ``answer`` True); None: received now, after everything the
    engine has seen. A value older than the one the engine holds is ignored (counted in
    :attr:`Axis.stale_readings`), as is an SDO answer asked before a PDO carrying the same
    object arrived (that PDO is newer and is on its way)."""

    statusword: int | None = None
    mode_display: int | None = None
    position: int | None = None
    velocity: int | None = None
    error_code: int | None = None
    received: int | None = None
    answer: bool = False

    def values(self) -> dict[Obj, int]:
        """The objects this reading carries, with their raw values."""
        pairs = ((Obj.ERROR_CODE, self.error_code), (Obj.MODES_DISPLAY, self.mode_display),
                 (Obj.POSITION_ACTUAL, self.position), (Obj.VELOCITY_ACTUAL, self.velocity),
                 (Obj.STATUSWORD, self.statusword))
        return {obj: value for obj, value in pairs if value is not None}


@dataclass(frozen=True)
class Write:
    """One object write for the host to send, in order (each its own frame or SDO)."""

    obj: Obj
    index: int
    value: int


@dataclass(frozen=True)
class Result:
    """How a command ended: ``ok``, or why not, with what the drive showed at that moment."""

    op: Op
    ok: bool
    state: State | None
    statusword: int | None
    error_code: int | None
    mode_display: int | None
    reason: str
    elapsed: float

    def __str__(self) -> str:
        sw = "none" if self.statusword is None else f"0x{self.statusword:04X}"
        ec = "unknown" if self.error_code is None else f"0x{self.error_code:04X}"
        state = "no statusword" if self.state is None else self.state.name
        verdict = ("done" + (f": {self.reason}" if self.reason else "")) if self.ok \
            else f"failed: {self.reason}"
        return (f"{self.op.value} {verdict} (state {state}, statusword {sw}, 0x603F {ec}, "
                f"after {self.elapsed:.3f} s)")


def result_doc(result: Result) -> dict[str, Any]:
    """``result`` as a JSON object (for the satellite link: an axis hosted elsewhere)."""
    return {"op": result.op.value, "ok": result.ok,
            "state": None if result.state is None else result.state.name,
            "statusword": result.statusword, "error_code": result.error_code,
            "mode_display": result.mode_display, "reason": result.reason,
            "elapsed": result.elapsed}


def result_from_doc(doc: Mapping[str, Any]) -> Result:
    """The :class:`Result` a :func:`result_doc` object carries. Raises :class:`Cia402Error`
    naming the field that is missing or not what it should be."""
    def optional_int(key: str) -> int | None:
        value = doc.get(key)
        if value is not None and (isinstance(value, bool) or not isinstance(value, int)):
            raise Cia402Error(f"axis result: {key!r}: expected a whole number or null, got "
                              f"{value!r:.40}")
        return value

    try:
        op = Op(doc.get("op"))
        state = None if doc.get("state") is None else State[str(doc.get("state"))]
    except (ValueError, KeyError) as exc:
        raise Cia402Error(f"axis result: unknown command or state: {exc}") from None
    ok, reason, elapsed = doc.get("ok"), doc.get("reason"), doc.get("elapsed")
    if not isinstance(ok, bool) or not isinstance(reason, str) \
            or isinstance(elapsed, bool) or not isinstance(elapsed, (int, float)):
        raise Cia402Error(f"axis result: expected ok (true/false), reason (a text) and elapsed "
                          f"(seconds), got {dict(doc)!r:.120}")
    return Result(op, ok, state, optional_int("statusword"), optional_int("error_code"),
                  optional_int("mode_display"), reason, float(elapsed))


@dataclass(frozen=True)
class Fault:
    """A drive fault seen by the axis: its error code (0x603F, None if it could not be read)
    and the statusword."""

    error_code: int | None
    statusword: int


@dataclass(frozen=True)
class Actions:
    """What the host must do after a call: ``writes`` in order, ``reads`` to request (their
    answers come back as a :class:`Reading`), ``results`` of commands that ended, and
    ``faults`` newly raised (None in it: a fault cleared)."""

    writes: tuple[Write, ...] = ()
    reads: tuple[Obj, ...] = ()
    results: tuple[Result, ...] = ()
    faults: tuple[Fault | None, ...] = ()


class _Phase(Enum):
    """Where a running command is."""

    START = "start"
    LOW = "bit 7 low"          # fault reset: 0x00 sent
    HIGH = "bit 7 high"        # fault reset: 0x80 sent
    RETRY = "retry"            # fault reset: the drive stayed in FAULT, a new edge
    LEFT = "left the fault"    # fault reset: out of FAULT, reading the new 0x603F
    CONFIRMING = "confirming"  # set mode: waiting for 0x6061
    RUNNING = "running"        # motion: under way
    STOPPING = "stopping"      # safe stop: waiting for standstill
    DISABLING = "disabling"    # safe stop: disable voltage sent


@dataclass
class _Job:
    op: Op
    started: float
    deadline: float
    phase: _Phase = _Phase.START
    mode: int | None = None
    target: int | None = None
    since: float = 0.0
    acked: bool = False


@dataclass
class _Out:
    writes: list[Write] = field(default_factory=list)
    reads: list[Obj] = field(default_factory=list)
    results: list[Result] = field(default_factory=list)
    faults: list[Fault | None] = field(default_factory=list)

    def actions(self) -> Actions:
        return Actions(tuple(self.writes), tuple(dict.fromkeys(self.reads)),
                       tuple(self.results), tuple(self.faults))


#: Commands that may interrupt a running one (which then fails as superseded).
PREEMPTING = (Op.QUICK_STOP, Op.DISABLE, Op.SAFE_STOP)


class Axis:
    """The commands of one CiA 402 axis as things that complete, driven by readings and time.

    Every public method takes ``now`` (seconds, any monotonic origin) and returns
    :class:`Actions`. One command runs at a time; :meth:`quick_stop`, :meth:`disable` and
    :meth:`safe_stop` supersede a running one, the others raise :class:`AxisBusy`. A command
    fails when the drive faults (naming 0x603F), when the planner finds the target unreachable,
    or at its timeout (naming the state reached). Nothing is written without a command.

    A reading older than a command proves nothing about it: a command is judged done (or
    failed by a state the drive left) only on a statusword received after its last write went
    out (controlword, target or mode), a target as reached only on a position or velocity
    received after it, and the axis counts as stopped only on a velocity received after the
    last controlword (see :class:`ReceiveOrder`); until then the engine asks for reads. Quick
    stop and safe stop act at once on the last state known, with controlwords safe in any
    state.
    """

    def __init__(self, config: AxisConfig) -> None:
        self.config = config
        self.statusword: int | None = None
        self.mode_display: int | None = None
        self.position_counts: int | None = None
        self.velocity_counts: int | None = None
        self.error_code: int | None = None
        self.controlword: int | None = None
        self._cw_time = 0.0
        self._error_code_time = -math.inf
        self._fault_since: float | None = None
        self._fault_reported = False
        self.fault: Fault | None = None
        self._job: _Job | None = None
        self._last_read: dict[Obj, float] = {}
        #: the order of readings and writes on the wire (the host marks what it receives)
        self.order = ReceiveOrder()
        #: the mark of the value the engine holds, per object
        self._held: dict[Obj, int] = {}
        #: the mark of the last write (controlword, target, mode; 0: none yet)
        self._write_mark = 0
        #: readings (or some of their values) ignored as older than what the engine holds
        self.stale_readings = 0
        #: the objects that have come in readings the drive sent by itself (PDOs), not only
        #: as answers to reads: a statusword never pushed is read at each command's start
        self._pushed: set[Obj] = set()

    # -- readings ----------------------------------------------------------------------------

    @property
    def state(self) -> State | None:
        """The drive's state from the last statusword (None before one arrived or for a
        pattern CiA 402 does not define)."""
        if self.statusword is None:
            return None
        try:
            return decode_state(self.statusword)
        except StatuswordError:
            return None

    @property
    def position(self) -> float | None:
        """Position actual in user units."""
        if self.position_counts is None:
            return None
        return self.position_counts / self.config.counts_per_unit

    @property
    def velocity(self) -> float | None:
        """Velocity actual in user units per second."""
        if self.velocity_counts is None:
            return None
        return self.velocity_counts / self.config.counts_per_unit

    @property
    def busy(self) -> Op | None:
        """The command running, if any."""
        return self._job.op if self._job else None

    def update(self, reading: Reading, now: float) -> Actions:
        """Take new readings at time ``now`` and advance the running command. A value older
        than the one held (by :attr:`Reading.received`) is ignored: the engine never goes
        back to an earlier state of the drive."""
        mark = reading.received if reading.received is not None else self.order.mark()
        stale = False
        if not reading.answer:
            self._pushed.update(reading.values())
        for obj, value in reading.values().items():
            if mark < self._held.get(obj, 0) or (reading.answer
                                                 and self.order.last_pdo(obj) > mark):
                stale = True
                continue
            self._held[obj] = mark
            match obj:
                case Obj.ERROR_CODE:
                    self.error_code = value
                    self._error_code_time = now
                case Obj.MODES_DISPLAY:
                    self.mode_display = value
                case Obj.POSITION_ACTUAL:
                    self.position_counts = value
                case Obj.VELOCITY_ACTUAL:
                    self.velocity_counts = value
                case _:
                    self.statusword = value
        self.stale_readings += stale
        return self._step(now)

    def lost(self, reason: str, now: float) -> Actions:
        """The drive can no longer be heard (node failed, rebooted, bus lost): the running
        command fails with ``reason``, and the readings are forgotten so that nothing stale is
        reported as the drive's state. The next statusword starts afresh; a drive that rebooted
        is enabled again only on a new command."""
        out = _Out()
        self._finish(out, now, False, f"drive lost: {reason}")
        self.statusword = self.mode_display = None
        self.position_counts = self.velocity_counts = None
        self.controlword = None
        if self._fault_since is not None or self.fault is not None:
            self._fault_since, self._fault_reported, self.fault = None, False, None
            out.faults.append(None)
        return out.actions()

    def poll(self, now: float) -> Actions:
        """Advance timers (timeouts, the fault reset's edge, resends) at time ``now``; call it
        every cycle of the host."""
        return self._step(now)

    # -- commands ----------------------------------------------------------------------------

    def enable(self, now: float) -> Actions:
        """Walk the state machine to OPERATION_ENABLED (never out of a fault)."""
        return self._start(_Job(Op.ENABLE, now, now + self.config.timeouts.enable), now)

    def disable(self, now: float) -> Actions:
        """Disable voltage: SWITCH_ON_DISABLED (a moving axis coasts; see :meth:`safe_stop`)."""
        return self._start(_Job(Op.DISABLE, now, now + self.config.timeouts.disable), now)

    def quick_stop(self, now: float) -> Actions:
        """Quick stop; done once stopped: in QUICK_STOP_ACTIVE for 0x605A 5..8, in
        SWITCH_ON_DISABLED otherwise."""
        return self._start(_Job(Op.QUICK_STOP, now, now + self.config.timeouts.quick_stop), now)

    def fault_reset(self, now: float) -> Actions:
        """A rising edge of controlword bit 7 (0x00, then 0x80 ``edge_gap`` later, repeated
        while the drive stays in FAULT); done when the drive left FAULT. Done at once when it
        is not in a fault."""
        return self._start(_Job(Op.FAULT_RESET, now, now + self.config.timeouts.fault_reset),
                           now)

    def set_mode(self, mode: Mode | int, now: float) -> Actions:
        """Write 0x6060; done when 0x6061 shows ``mode``. A failure names 0x6061's value."""
        job = _Job(Op.SET_MODE, now, now + self.config.timeouts.set_mode, mode=int(mode))
        return self._start(job, now)

    def home(self, now: float) -> Actions:
        """Start homing (mode HM confirmed, operation enabled); done on homing attained and
        target reached (statusword bits 12 and 10); a homing error (bit 13) fails it."""
        return self._start(_Job(Op.HOME, now, now + self.config.timeouts.home), now)

    def move_to(self, position: float, now: float) -> Actions:
        """Move to ``position`` (user units): in PP the new set-point handshake (bit 4, acked
        on statusword bit 12), in CSP a target written directly; done on target reached (bit
        10) with the position within ``position_window``. Raises :class:`AxisLimitError`."""
        counts = self._position_counts(position)
        job = _Job(Op.MOVE_TO, now, now + self.config.timeouts.move, target=counts)
        return self._start(job, now)

    def at_velocity(self, velocity: float, now: float) -> Actions:
        """Run at ``velocity`` (user units/s) in PV or CSV; done on target reached (bit 10) or
        the velocity within ``velocity_window``. Raises :class:`AxisLimitError`."""
        counts = self._velocity_counts(velocity)
        job = _Job(Op.AT_VELOCITY, now, now + self.config.timeouts.velocity, target=counts)
        return self._start(job, now)

    def safe_stop(self, now: float) -> Actions:
        """The axis's safe action (:attr:`AxisConfig.safe_stop`) as a sequence: by default
        quick stop, wait until stopped, then disable voltage; done in SWITCH_ON_DISABLED (in
        QUICK_STOP_ACTIVE for :attr:`SafeStop.QUICK_STOP` with 0x605A 5..8). "Stopped" is a
        velocity received after the quick stop went out (never the last one held, which may
        predate a move just started); the drive may also go to SWITCH_ON_DISABLED by itself
        (0x605A 0..4). The first step acts at once on the last state known: a state older
        than the last controlword gets the quick stop, safe in any state. Not stopped in
        time: voltage disabled anyway and the command fails. Targets are left alone. A drive
        in FAULT is sent nothing: its drive function is disabled (no torque), so the safe stop
        is done as it is, the reason naming 0x603F; a drive in FAULT_REACTION_ACTIVE is waited
        for until it shows FAULT (within the timeout). Never a fault reset, never an enable."""
        return self._start(_Job(Op.SAFE_STOP, now, now + self.config.timeouts.safe_stop), now)

    # -- limits ------------------------------------------------------------------------------

    def _position_counts(self, position: float) -> int:
        cfg = self.config
        if not isinstance(position, (int, float)) or not math.isfinite(position):
            raise AxisLimitError(f"axis {cfg.name}: move to {position!r}: not a finite number")
        if cfg.position_limits is not None:
            low, high = cfg.position_limits
            if not low <= position <= high:
                raise AxisLimitError(f"axis {cfg.name}: move to {position}: outside the "
                                     f"limits {low}..{high}")
        return round(position * cfg.counts_per_unit)

    def _velocity_counts(self, velocity: float) -> int:
        cfg = self.config
        if not isinstance(velocity, (int, float)) or not math.isfinite(velocity):
            raise AxisLimitError(f"axis {cfg.name}: velocity {velocity!r}: not a finite number")
        if cfg.max_velocity is not None and abs(velocity) > cfg.max_velocity:
            raise AxisLimitError(f"axis {cfg.name}: velocity {velocity}: above the limit "
                                 f"{cfg.max_velocity}")
        return round(velocity * cfg.counts_per_unit)

    # -- engine ------------------------------------------------------------------------------

    def _start(self, job: _Job, now: float) -> Actions:
        out = _Out()
        if self._job is not None:
            if job.op not in PREEMPTING:
                raise AxisBusy(f"axis {self.config.name}: {job.op.value} refused: "
                               f"{self._job.op.value} is running")
            self._finish(out, now, False, f"superseded by {job.op.value}")
        job.since = now
        self._job = job
        if self.statusword is None:
            out.reads.append(Obj.STATUSWORD)
        elif Obj.STATUSWORD not in self._pushed and job.op not in (Op.SAFE_STOP,
                                                                    Op.QUICK_STOP):
            # no PDO brings the statusword: the one held may be old (a fault since, seen only
            # by its EMCY), so the command is judged on one read now (the stops act at once on
            # the last state known, with controlwords safe in any state, as always)
            self._write_mark = self.order.mark()
            out.reads.append(Obj.STATUSWORD)
            self._last_read[Obj.STATUSWORD] = now
        self._watch_fault(out, now)
        self._advance(out, now)
        return out.actions()

    def _step(self, now: float) -> Actions:
        out = _Out()
        self._watch_fault(out, now)
        self._advance(out, now)
        return out.actions()

    def _watch_fault(self, out: _Out, now: float) -> None:
        """Track the drive's fault: note when it began, ask for 0x603F, report it once the code
        is fresh (or could not be read in time), and report its end."""
        faulted = self.state in (State.FAULT, State.FAULT_REACTION_ACTIVE)
        if self.state is State.FAULT_REACTION_ACTIVE and Obj.STATUSWORD not in self._pushed:
            self._request(out, now, Obj.STATUSWORD)   # no PDO says when the reaction ends
        if faulted and self._fault_since is None:
            self._fault_since = now
            self._fault_reported = False
            if self._error_code_time < now:
                out.reads.append(Obj.ERROR_CODE)
        elif not faulted and self._fault_since is not None and self.state is not None:
            self._fault_since = None
            if self._fault_reported:
                self.fault = None
                out.faults.append(None)
            self._fault_reported = False
        if faulted and not self._fault_reported and self._fault_code_ready(now):
            assert self.statusword is not None
            self.fault = Fault(self._fresh_error_code(), self.statusword)
            self._fault_reported = True
            out.faults.append(self.fault)

    def _fault_code_ready(self, now: float) -> bool:
        since = self._fault_since
        return since is not None and (self._error_code_time >= since
                                      or now >= since + self.config.timeouts.error_code)

    def _fresh_error_code(self) -> int | None:
        since = self._fault_since
        if since is not None and self._error_code_time >= since:
            return self.error_code
        return None

    def _finish(self, out: _Out, now: float, ok: bool, reason: str = "") -> None:
        job = self._job
        if job is None:
            return
        self._job = None
        error_code = self._fresh_error_code() if self._fault_since is not None else \
            self.error_code
        out.results.append(Result(job.op, ok, self.state, self.statusword, error_code,
                                  self.mode_display, reason, now - job.started))

    def _send(self, out: _Out, obj: Obj, value: int) -> None:
        """Write ``obj``; readings received before this are older than it."""
        out.writes.append(Write(obj, self.config.index(obj), value))
        self._write_mark = self.order.mark()

    def _send_cw(self, out: _Out, now: float, controlword: int) -> None:
        """Write the controlword when it changes, or again after ``resend`` seconds."""
        if controlword != self.controlword or now - self._cw_time >= self.config.resend:
            self._write_cw(out, now, controlword)

    def _write_cw(self, out: _Out, now: float, controlword: int) -> None:
        self._send(out, Obj.CONTROLWORD, controlword)
        self.controlword, self._cw_time = controlword, now

    def _request(self, out: _Out, now: float, obj: Obj) -> None:
        """Ask for ``obj`` by SDO, at most every ``read_every`` seconds."""
        if now - self._last_read.get(obj, -math.inf) >= self.config.read_every:
            out.reads.append(obj)
            self._last_read[obj] = now

    def _after_write(self, obj: Obj) -> bool:
        """True when the value held of ``obj`` was received after the last write (the
        controlword, a target, the mode): only such a value can confirm a command."""
        return self._held.get(obj, 0) > self._write_mark

    def _stopped(self, out: _Out, now: float) -> bool:
        """True when a reading received after the last write shows standstill: the
        velocity within ``standstill``, or, for a drive whose velocity is never read, the
        statusword's target reached bit. A velocity older than the write (the axis may
        have started moving since) proves nothing: it is asked for again."""
        if self._after_write(Obj.VELOCITY_ACTUAL):
            assert self.velocity_counts is not None
            return abs(self.velocity_counts) <= self.config.standstill
        self._request(out, now, Obj.VELOCITY_ACTUAL)
        if self.velocity_counts is None and self._after_write(Obj.STATUSWORD):
            return bool((self.statusword or 0) & SW_TARGET_REACHED)
        return False

    def _advance(self, out: _Out, now: float) -> None:
        job = self._job
        if job is None:
            return
        state = self.state
        if job.op is Op.SAFE_STOP and state in (State.FAULT, State.FAULT_REACTION_ACTIVE):
            self._safe_stop_faulted(out, now, job, state)
            return
        if (state in (State.FAULT, State.FAULT_REACTION_ACTIVE)
                and job.op is not Op.FAULT_RESET):
            if self._fault_code_ready(now):
                self._finish(out, now, False, f"the drive is in {state.name}")
            return
        if state is None:
            if now >= job.deadline:
                self._finish(out, now, False, "no statusword within the timeout"
                             if self.statusword is None else
                             f"statusword 0x{self.statusword:04X} shows no CiA 402 state")
            return
        if not self._judges_now(job, state):
            # the statusword predates the last write: it says nothing about the command
            self._request(out, now, Obj.STATUSWORD)
            if now >= job.deadline:
                self._timeout(out, now, job)
            return
        match job.op:
            case Op.ENABLE:
                self._walk(out, now, job, state, Target.ENABLED)
            case Op.DISABLE:
                self._walk(out, now, job, state, Target.DISABLED)
            case Op.FAULT_RESET:
                self._fault_reset(out, now, job, state)
            case Op.QUICK_STOP:
                self._quick_stop(out, now, job, state)
            case Op.SAFE_STOP:
                self._safe_stop(out, now, job, state)
            case Op.SET_MODE:
                self._set_mode(out, now, job)
            case Op.HOME | Op.MOVE_TO | Op.AT_VELOCITY:
                self._motion(out, now, job, state)
        if self._job is job and now >= job.deadline:
            self._timeout(out, now, job)

    def _judges_now(self, job: _Job, state: State) -> bool:
        """True when ``job`` may act on ``state``: a statusword received after the last
        write; or, whatever its age, the first step of a quick stop or safe stop (they
        send controlwords safe in any state, at once), a fault reset's edge while the drive
        shows a fault (timed, not judged), and a mode change (judged on 0x6061)."""
        if self._after_write(Obj.STATUSWORD) or job.op is Op.SET_MODE:
            return True
        if job.op in (Op.QUICK_STOP, Op.SAFE_STOP) and job.phase == _Phase.START:
            return True
        return job.op is Op.FAULT_RESET and state in (State.FAULT, State.FAULT_REACTION_ACTIVE)

    def _timeout(self, out: _Out, now: float, job: _Job) -> None:
        timeout = job.deadline - job.started
        state = self.state
        if job.op is Op.SET_MODE:
            assert job.mode is not None
            self._finish(out, now, False, f"0x6061 shows {mode_name(self.mode_display)}, not "
                         f"{mode_name(job.mode)}, after {timeout} s")
            return
        if job.op is Op.SAFE_STOP and job.phase == _Phase.STOPPING:
            # not stopped in time: remove the power anyway, and say so
            self._send_cw(out, now, Command.DISABLE_VOLTAGE.controlword)
            self._finish(out, now, False, f"not stopped within {timeout} s; voltage disabled "
                         "while moving")
            return
        where = state.name if state is not None else "unknown"
        self._finish(out, now, False, f"not done within {timeout} s (state {where})")

    def _walk(self, out: _Out, now: float, job: _Job, state: State, target: Target) -> None:
        try:
            step = plan(state, target)
        except Unreachable as exc:
            self._finish(out, now, False, str(exc))
            return
        if state is State.QUICK_STOP_ACTIVE and not self._stopped(out, now):
            return  # voltage stays on until the quick stop has stopped the axis
        if step is Plan.DONE:
            self._finish(out, now, True)
        elif isinstance(step, Command):
            self._send_cw(out, now, step.controlword)

    def _fault_reset(self, out: _Out, now: float, job: _Job, state: State) -> None:
        if state is State.FAULT_REACTION_ACTIVE:
            return
        if state is not State.FAULT:
            if job.phase == _Phase.START:
                self._finish(out, now, True, "not in a fault")
                return
            if not self._after_write(Obj.ERROR_CODE):
                # out of FAULT: the result shows the drive's new 0x603F, read after the reset
                # (at most error_code seconds: a drive that does not answer it is done anyway)
                if job.phase is not _Phase.LEFT:
                    job.phase, job.since = _Phase.LEFT, now
                    self.error_code = None      # the fault's code is no longer the drive's
                if now < job.since + self.config.timeouts.error_code:
                    self._request(out, now, Obj.ERROR_CODE)
                    return
                self._finish(out, now, True, "the drive left FAULT; its new 0x603F was not "
                                             "read")
                return
            self._finish(out, now, True)
            return
        # the edge: bit 7 clear, edge_gap later set; again if the drive stays in FAULT
        if job.phase in (_Phase.START, _Phase.RETRY):
            self._write_cw(out, now, 0x0000)
            job.phase, job.since = _Phase.LOW, now
        elif job.phase == _Phase.LOW and now >= job.since + self.config.edge_gap:
            self._write_cw(out, now, Command.FAULT_RESET.controlword)
            job.phase, job.since = _Phase.HIGH, now
        elif job.phase == _Phase.HIGH and now >= job.since + self.config.resend:
            job.phase = _Phase.RETRY
            self._fault_reset(out, now, job, state)

    def _quick_stop(self, out: _Out, now: float, job: _Job, state: State) -> None:
        stays = quick_stop_stays(self.config.quick_stop_option)
        powered = (State.OPERATION_ENABLED, State.SWITCHED_ON, State.READY_TO_SWITCH_ON)
        if job.phase == _Phase.START:
            job.phase = _Phase.STOPPING
            if state in powered or not self._after_write(Obj.STATUSWORD):
                # a state older than the last controlword may hide an enabled drive: the
                # quick stop is safe in any state
                self._send_cw(out, now, Command.QUICK_STOP.controlword)
                return
        if state is State.SWITCH_ON_DISABLED:
            self._finish(out, now, True)
        elif state is State.QUICK_STOP_ACTIVE:
            if stays and self._stopped(out, now):
                self._finish(out, now, True)
        elif state in powered:
            self._send_cw(out, now, Command.QUICK_STOP.controlword)

    def _safe_stop(self, out: _Out, now: float, job: _Job, state: State) -> None:
        kind = self.config.safe_stop
        if job.phase == _Phase.START:
            # the first step acts at once on the last state known; what comes after is judged
            # only on readings received after it (``_judges_now``)
            fresh = self._after_write(Obj.STATUSWORD)
            if fresh and state is State.SWITCH_ON_DISABLED:
                self._finish(out, now, True)
                return
            if fresh and state is State.NOT_READY_TO_SWITCH_ON:
                return
            if kind is SafeStop.DISABLE_VOLTAGE or (
                    fresh and state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON)):
                self._send_cw(out, now, Command.DISABLE_VOLTAGE.controlword)
                job.phase = _Phase.DISABLING
                return
            if fresh and state is State.QUICK_STOP_ACTIVE:
                job.phase = _Phase.STOPPING     # already braking: wait until stopped
            else:
                # enabled, or a state older than the last controlword (which may hide an
                # enabled drive): halt brakes an enabled drive only, and would enable one
                # that is not, so a state of unknown age gets the quick stop, safe in any
                halt = kind is SafeStop.HALT_THEN_DISABLE and fresh
                self._send_cw(out, now, Command.ENABLE_OPERATION.controlword | CW_HALT if halt
                              else Command.QUICK_STOP.controlword)
                job.phase = _Phase.STOPPING
                return      # standstill is judged on a velocity received after this
        if job.phase == _Phase.STOPPING:
            if state is State.SWITCH_ON_DISABLED:
                self._finish(out, now, True)
            elif state in (State.QUICK_STOP_ACTIVE, State.OPERATION_ENABLED) \
                    and self._stopped(out, now):
                if kind is SafeStop.QUICK_STOP and state is State.QUICK_STOP_ACTIVE:
                    self._finish(out, now, True)
                    return
                self._send_cw(out, now, Command.DISABLE_VOLTAGE.controlword)
                job.phase = _Phase.DISABLING
            elif state in (State.READY_TO_SWITCH_ON, State.SWITCHED_ON):
                self._send_cw(out, now, Command.DISABLE_VOLTAGE.controlword)
                job.phase = _Phase.DISABLING
        if job.phase == _Phase.DISABLING:
            if state is State.SWITCH_ON_DISABLED:
                self._finish(out, now, True)
            else:
                self._send_cw(out, now, Command.DISABLE_VOLTAGE.controlword)

    def _safe_stop_faulted(self, out: _Out, now: float, job: _Job, state: State) -> None:
        """The safe stop of a drive in a fault: nothing is sent (a controlword cannot leave
        FAULT but by a fault reset, and a reset would let a task enable it again). In FAULT the
        drive function is disabled (CiA 402: power stage off, no torque): the safe outcome is
        reached, and said so with 0x603F. In FAULT_REACTION_ACTIVE the drive is still braking
        by its own reaction: wait until it shows FAULT, within the safe stop's timeout."""
        if state is State.FAULT_REACTION_ACTIVE:
            if now >= job.deadline:
                self._finish(out, now, False, f"still in FAULT_REACTION_ACTIVE after "
                             f"{job.deadline - job.started} s (the drive's own fault reaction "
                             f"did not end)")
            return
        if not self._fault_code_ready(now):
            return      # 0x603F is on its way (or its wait ends): the result names it
        code = self._fresh_error_code()
        ec = "unknown" if code is None else f"0x{code:04X}"
        self._finish(out, now, True, f"the drive is in FAULT (0x603F {ec}): drive function "
                     f"disabled, no torque; left in FAULT, nothing sent")

    def _set_mode(self, out: _Out, now: float, job: _Job) -> None:
        assert job.mode is not None
        if job.phase == _Phase.START:
            self._send(out, Obj.MODES, job.mode)
            job.phase = _Phase.CONFIRMING
            out.reads.append(Obj.MODES_DISPLAY)
            self._last_read[Obj.MODES_DISPLAY] = now
            return
        if self.mode_display == job.mode and self._after_write(Obj.MODES_DISPLAY):
            self._finish(out, now, True)
        else:
            self._request(out, now, Obj.MODES_DISPLAY)

    def _motion(self, out: _Out, now: float, job: _Job, state: State) -> None:
        cfg = self.config
        wanted = {Op.HOME: (Mode.HM,), Op.MOVE_TO: (Mode.PP, Mode.CSP),
                  Op.AT_VELOCITY: (Mode.PV, Mode.CSV)}[job.op]
        sw = self.statusword or 0
        if job.phase == _Phase.START:
            if state is not State.OPERATION_ENABLED:
                self._finish(out, now, False, f"needs OPERATION_ENABLED, the drive is in "
                             f"{state.name}")
                return
            if self.mode_display not in wanted:
                self._finish(out, now, False, f"needs mode {' or '.join(m.name for m in wanted)}"
                             f"; 0x6061 shows {mode_name(self.mode_display)}")
                return
            base = Command.ENABLE_OPERATION.controlword
            match job.op, self.mode_display:
                case Op.HOME, _:
                    self._send_cw(out, now, base)
                    self._send_cw(out, now, base | CW_OMS4)
                case Op.MOVE_TO, Mode.PP:
                    assert job.target is not None
                    self._send(out, Obj.TARGET_POSITION, job.target)
                    self._send_cw(out, now, base)
                    self._send_cw(out, now, base | CW_OMS4)
                case Op.MOVE_TO, _:
                    assert job.target is not None
                    self._send(out, Obj.TARGET_POSITION, job.target)
                    job.acked = True
                case _:
                    assert job.target is not None
                    self._send(out, Obj.TARGET_VELOCITY, job.target)
                    self._send_cw(out, now, base)
                    job.acked = True
            job.phase = _Phase.RUNNING
            return
        if state is not State.OPERATION_ENABLED:
            self._finish(out, now, False, f"the drive left OPERATION_ENABLED for {state.name}")
            return
        match job.op:
            case Op.HOME:
                if sw & SW_OMS13:
                    self._send_cw(out, now, Command.ENABLE_OPERATION.controlword)
                    self._finish(out, now, False, "homing error (statusword bit 13)")
                elif sw & SW_OMS12 and sw & SW_TARGET_REACHED:
                    self._send_cw(out, now, Command.ENABLE_OPERATION.controlword)
                    self._finish(out, now, True)
            case Op.MOVE_TO:
                assert job.target is not None
                if not job.acked:
                    if sw & SW_OMS12:
                        job.acked = True
                        self._send_cw(out, now, Command.ENABLE_OPERATION.controlword)
                    return
                if sw & SW_OMS13 and self.mode_display == Mode.CSP:
                    self._finish(out, now, False, "following error (statusword bit 13)")
                    return
                pos = self.position_counts if self._after_write(Obj.POSITION_ACTUAL) else None
                if pos is None:
                    self._request(out, now, Obj.POSITION_ACTUAL)
                near = pos is not None and abs(pos - job.target) <= cfg.position_window
                if near and (sw & SW_TARGET_REACHED or self.mode_display == Mode.CSP):
                    self._finish(out, now, True)
            case Op.AT_VELOCITY:
                assert job.target is not None
                vel = self.velocity_counts if self._after_write(Obj.VELOCITY_ACTUAL) else None
                if vel is None:
                    self._request(out, now, Obj.VELOCITY_ACTUAL)
                near = vel is not None and abs(vel - job.target) <= cfg.velocity_window
                if near or (self.mode_display == Mode.PV and sw & SW_TARGET_REACHED
                            and self.velocity_counts is None):
                    self._finish(out, now, True)


# -- configuration from a device map -----------------------------------------------------------

#: The keys of an axis table in a device map, besides those the map itself owns.
AXIS_KEYS = ("axis", "counts_per_unit", "position_limits", "max_velocity", "quick_stop_option",
             "safe_stop", "timeouts", "position_window", "velocity_window", "standstill",
             "edge_gap", "resend", "read_every")


def _number(value: object, where: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value) or (positive and value <= 0):
        raise Cia402Error(f"{where}: expected a finite{' positive' if positive else ''} "
                          f"number, got {value!r}")
    return float(value)


def _count(value: object, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise Cia402Error(f"{where}: expected a whole number of counts >= 0, got {value!r}")
    return value


def config_from_table(name: str, table: dict[str, object], where: str) -> AxisConfig:
    """An :class:`AxisConfig` from the axis keys of a device-map table (:data:`AXIS_KEYS`;
    others are the caller's). ``where`` names the file and key for messages (``"cell.toml:
    device[3]"``). Raises :class:`Cia402Error` naming ``where.key`` and what was expected."""
    kw: dict[str, object] = {"name": name}
    for key, value in table.items():
        at = f"{where}.{key}"
        match key:
            case "axis":
                if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 7:
                    raise Cia402Error(f"{at}: expected an axis number 0..7, got {value!r}")
                kw[key] = value
            case "counts_per_unit":
                kw[key] = _number(value, at, positive=True)
            case "max_velocity" | "edge_gap" | "resend" | "read_every":
                kw[key] = _number(value, at, positive=True)
            case "position_window" | "velocity_window" | "standstill":
                kw[key] = _count(value, at)
            case "quick_stop_option":
                if isinstance(value, bool) or not isinstance(value, int) \
                        or not -32768 <= value <= 32767:
                    raise Cia402Error(f"{at}: expected 0x605A's value (an INTEGER16), got "
                                      f"{value!r}")
                kw[key] = value
            case "position_limits":
                if not isinstance(value, (list, tuple)) or len(value) != 2:
                    raise Cia402Error(f"{at}: expected [low, high], got {value!r}")
                low, high = (_number(v, at) for v in value)
                if low >= high:
                    raise Cia402Error(f"{at}: low {low} is not below high {high}")
                kw[key] = (low, high)
            case "safe_stop":
                choices = {s.name.lower(): s for s in SafeStop}
                if value not in choices:
                    raise Cia402Error(f"{at}: expected one of {', '.join(choices)}, got "
                                      f"{value!r}")
                kw[key] = choices[str(value)]
            case "timeouts":
                if not isinstance(value, dict):
                    raise Cia402Error(f"{at}: expected a table of seconds per command")
                fields = Timeouts.__dataclass_fields__
                unknown = sorted(set(value) - set(fields))
                if unknown:
                    raise Cia402Error(f"{at}.{unknown[0]}: unknown timeout; expected one of "
                                      f"{', '.join(fields)}")
                kw[key] = Timeouts(**{k: _number(v, f"{at}.{k}", positive=True)
                                      for k, v in value.items()})
            case _:
                raise Cia402Error(f"{at}: unknown key for a cia402 axis; expected one of "
                                  f"{', '.join(AXIS_KEYS)}")
    return AxisConfig(**kw)  # type: ignore[arg-type]


# ---- the axis in a device map: its profile, its sensors, its modes by name ----------------

#: the ``profile`` of an axis table in a device map, and the address key marking its devices
PROFILE = "cia402"


class AxisReading(Enum):
    """The sensors of an axis: ``<axis>.<value>``."""

    STATE = "state"
    STATUSWORD = "statusword"
    MODE = "mode"
    POSITION = "position"
    VELOCITY = "velocity"
    FAULT = "fault"


#: the object each sensor shows (axis 0; its ``index`` in the address, for tools that read
#: CANopen addresses without knowing axes)
READING_OBJECTS: dict[AxisReading, int] = {
    AxisReading.STATE: 0x6041, AxisReading.STATUSWORD: 0x6041, AxisReading.MODE: 0x6061,
    AxisReading.POSITION: 0x6064, AxisReading.VELOCITY: 0x606C, AxisReading.FAULT: 0x603F,
}


def axis_names(name: str) -> dict[AxisReading, str]:
    """The sensor device names of axis ``name``."""
    return {r: f"{name}.{r.value}" for r in AxisReading}


def is_axis_address(address: Mapping[str, Any]) -> bool:
    """True for the address of a device an axis table became (actuator or sensor)."""
    return address.get("profile") == PROFILE


def mode_of(value: object) -> Mode | None:
    """A mode of operation from a map value: a name (``"PP"``, ``"csp"``) or its number; None
    if it is neither."""
    if isinstance(value, str):
        return Mode.__members__.get(value.upper())
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            return Mode(value)
        except ValueError:
            return None
    return None
