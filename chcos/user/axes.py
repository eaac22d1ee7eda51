"""axes - the task API of a CiA 402 axis: ``ctx.axis("x")`` and its commands that complete.

``await ctx.axis("x").enable()`` returns once the drive's statusword confirms OPERATION_ENABLED
and raises :class:`drivers.codecs.cia402.AxisCommandFailed` (a ChcosError) naming the state reached,
the statusword and 0x603F when it does not; the task never touches a controlword bit. The axis
must be on one of the task's output ports (an actuator it commands): the task then owns it, and
its abnormal completion runs the axis's safe stop as any actuator's safe value. While a command
waits the task is WAITING; the command runs on the CANopen driver's I/O thread
(:mod:`drivers.canopen_axis`) and its result comes back through the kernel's interrupt queue.
An axis hosted by another satellite is commanded the same way (:class:`RemoteAxis`): the command
travels over the satellite link, runs on that satellite's driver, and its result comes back.

The readings (:attr:`AxisHandle.state`, :attr:`~AxisHandle.position`, ...) are what the drive
last confirmed; the same values are the sensors ``x.state``, ``x.position``, ... of Devtab.
"""

from __future__ import annotations

import concurrent.futures
import time
import types
from collections.abc import Callable, Generator
from typing import TYPE_CHECKING, Any, Protocol

from chcos.errors import ChcosError, CommandSyntaxError, DeviceError, MessageError
from chcos.kernel.scheduler import BLOCK
from chcos.tables.messages import EndpointKind
from chcos.tables.tasks import TaskState
from drivers.canopen_axis import AxisCall, AxisStatus, Done
from drivers.codecs.cia402 import (
    AxisCommandFailed,
    Fault,
    Mode,
    Op,
    Result,
    State,
    mode_name,
    mode_of,
)

if TYPE_CHECKING:
    from chcos.kernel.scheduler import Kernel
    from chcos.tables.tasks import TaskEntry


class AxisDriver(Protocol):
    """What a driver hosting axes offers (:class:`drivers.canopen_node.CanopenDriver`)."""

    def axis_call(self, device: str, call: AxisCall, done: Done) -> None:
        """Start ``call`` on axis ``device``; ``done`` gets its result (any thread)."""

    def axis_status(self, device: str) -> AxisStatus:
        """What the drive last confirmed."""


class AxisLink(Protocol):
    """What reaches an axis hosted by another satellite (the communications manager,
    :class:`chcos.comm.manager.CommManager`)."""

    axis_results: dict[str, Result]

    def axis_call(self, device: str, machine: int, source: str, call: AxisCall,
                  done: Done) -> None:
        """Send ``source``'s ``call`` to satellite ``machine``; ``done`` gets the result."""


class RemoteAxis:
    """An axis hosted by satellite ``machine``, commanded over the satellite link by task
    ``source`` (:class:`AxisDriver`): each command travels as an axis request, runs on the
    hosting satellite's driver, and its result (the drive's confirmation, or the failure
    naming the state reached) comes back as on a local axis. Its status is what the last
    result confirmed (state, statusword, 0x603F, mode; no position or velocity: link the
    axis's sensors for those)."""

    def __init__(self, link: AxisLink, machine: int, source: str) -> None:
        self.link = link
        self.machine = machine
        self.source = source

    def axis_call(self, device: str, call: AxisCall, done: Done) -> None:
        """Send ``call``. Raises MessageError when the hosting satellite is not up."""
        self.link.axis_call(device, self.machine, self.source, call, done)

    def axis_status(self, device: str) -> AxisStatus:
        """What the last result of axis ``device`` confirmed (nothing before one)."""
        r = self.link.axis_results.get(device)
        if r is None:
            return AxisStatus()
        fault = Fault(r.error_code, r.statusword) \
            if r.state in (State.FAULT, State.FAULT_REACTION_ACTIVE) and r.statusword is not None \
            else None
        return AxisStatus(r.state, r.statusword, r.mode_display, fault=fault)


def find_axis(devices: Any, name: str) -> AxisDriver:
    """The driver hosting axis ``name`` in Devtab ``devices``. Raises MessageError naming the
    device when it is not an axis driven by this process."""
    try:
        entry = devices.get(name)
    except Exception as exc:
        raise MessageError(f"no axis {name!r}: {exc}") from exc
    drv = entry.driver
    if entry.spec.address.get("profile") != "cia402" or entry.spec.direction != "actuator":
        raise MessageError(f"{name} is not a CiA 402 axis (a device-map table with "
                           f"profile = \"cia402\")")
    if drv is None or not hasattr(drv, "axis_call"):
        raise MessageError(f"axis {name} is not driven by this process (machine "
                           f"{entry.spec.machine})")
    driver: AxisDriver = drv
    return driver


class AxisHandle:
    """The commands and readings of one axis for one task (``ctx.axis(name)``)."""

    def __init__(self, name: str, driver: AxisDriver, task: TaskEntry, kernel: Kernel) -> None:
        self.name = name
        self._driver = driver
        self._t = task
        self._k = kernel

    # ---- readings -----------------------------------------------------------------------------
    @property
    def status(self) -> AxisStatus:
        """Everything the drive last confirmed, at once."""
        return self._driver.axis_status(self.name)

    @property
    def state(self) -> State | None:
        """The drive's power state (None before the first statusword)."""
        return self.status.state

    @property
    def statusword(self) -> int | None:
        """The last statusword 0x6041."""
        return self.status.statusword

    @property
    def mode(self) -> int | None:
        """The mode the drive shows on 0x6061."""
        return self.status.mode_display

    @property
    def position(self) -> float | None:
        """Position actual in user units."""
        return self.status.position

    @property
    def velocity(self) -> float | None:
        """Velocity actual in user units per second."""
        return self.status.velocity

    @property
    def fault(self) -> Fault | None:
        """The drive's fault (error code 0x603F and statusword), None when not in a fault."""
        return self.status.fault

    # ---- commands -----------------------------------------------------------------------------
    def enable(self) -> Generator[Any, Any, Result]:
        """Walk the state machine to OPERATION_ENABLED (never out of a fault)."""
        return self._call(AxisCall(Op.ENABLE))

    def disable(self) -> Generator[Any, Any, Result]:
        """Disable voltage (SWITCH_ON_DISABLED; a moving axis coasts)."""
        return self._call(AxisCall(Op.DISABLE))

    def quick_stop(self) -> Generator[Any, Any, Result]:
        """Quick stop; done once stopped (per 0x605A)."""
        return self._call(AxisCall(Op.QUICK_STOP))

    def fault_reset(self) -> Generator[Any, Any, Result]:
        """The fault reset's edge; done when the drive left FAULT (also while the axis device
        is failed by that fault: the reset is how it recovers)."""
        return self._call(AxisCall(Op.FAULT_RESET))

    def set_mode(self, mode: Mode | int | str | None = None) -> Generator[Any, Any, Result]:
        """Write 0x6060 (``mode``: a :class:`Mode`, its number or its name as in the map,
        ``"PP"``, ``"csv"``...; None: the map's ``mode``); done when 0x6061 shows it. Raises
        ValueError naming a mode that is none of these, before anything is written."""
        if mode is None:
            return self._call(AxisCall(Op.SET_MODE, None))
        chosen = mode_of(mode)
        if chosen is None:
            raise ValueError(f"axis {self.name}: set_mode({mode!r}): expected a mode name "
                             f"({', '.join(Mode.__members__)}) or number")
        return self._call(AxisCall(Op.SET_MODE, int(chosen)))

    def home(self) -> Generator[Any, Any, Result]:
        """Homing (mode HM, operation enabled); done on homing attained."""
        return self._call(AxisCall(Op.HOME))

    def move_to(self, position: float) -> Generator[Any, Any, Result]:
        """Move to ``position`` (user units; PP or CSP); done on target reached."""
        return self._call(AxisCall(Op.MOVE_TO, float(position)))

    def at_velocity(self, velocity: float) -> Generator[Any, Any, Result]:
        """Run at ``velocity`` (user units/s; PV or CSV); done when the drive is at it."""
        return self._call(AxisCall(Op.AT_VELOCITY, float(velocity)))

    def safe_stop(self) -> Generator[Any, Any, Result]:
        """The axis's safe stop sequence (quick stop, wait, disable voltage, per the map)."""
        return self._call(AxisCall(Op.SAFE_STOP))

    @types.coroutine
    def _call(self, call: AxisCall) -> Generator[Any, Any, Result]:
        """Start ``call`` and wait for the drive to confirm it. Raises AxisCommandFailed (the
        state reached, statusword, 0x603F), or the engine's refusal (AxisBusy,
        AxisLimitError, ValueError) before anything was written."""
        t, k, name = self._t, self._k, self.name
        waiting = [True]

        def forget(_t: TaskEntry) -> None:     # the wait ended otherwise (killed, cancelled)
            waiting[0] = False

        def arrive(outcome: Result | Exception) -> None:    # kernel thread
            if waiting[0]:
                waiting[0] = False
                t.unwait = None
                k.wake(t, t.base_prio, value=outcome)

        def done(outcome: Result | Exception) -> None:      # the driver's thread
            k.interrupt(arrive, outcome)

        t.unwait = forget
        k.block(t, TaskState.WAITING)
        try:
            self._driver.axis_call(name, call, done)
        except BaseException:
            t.unwait = None
            t.state = TaskState.CURRENT
            raise
        outcome = yield BLOCK
        if isinstance(outcome, Exception):
            raise outcome
        assert isinstance(outcome, Result)
        if not outcome.ok:
            raise AxisCommandFailed(name, outcome)
        return outcome


def axis_handle(task: TaskEntry, kernel: Kernel, devices: Any, name: str) -> AxisHandle:
    """``ctx.axis(name)``: the axis must be on one of the task's output ports. Raises
    MessageError naming the task and the axis otherwise, DeviceError for an unknown device."""
    if not any(lk.dst == name and lk.dst_kind is EndpointKind.DEVICE for lk in task.out_links):
        if name not in devices:
            raise DeviceError(f"no device {name!r}")
        raise MessageError(f"task {task.name} has no output port to axis {name}: link it to "
                           f"the axis (it then owns it, and its safe stop follows the task)")
    spec = devices.get(name).spec
    if devices.is_local(spec.machine):
        return AxisHandle(name, find_axis(devices, name), task, kernel)
    if spec.address.get("profile") != "cia402" or spec.direction != "actuator":
        raise MessageError(f"{name} is not a CiA 402 axis (a device-map table with "
                           f"profile = \"cia402\")")
    link = getattr(devices, "remote", None)
    if link is None or not hasattr(link, "axis_call"):
        raise MessageError(f"axis {name} is on machine {spec.machine}, which this process "
                           f"does not drive, and no satellite link leads there")
    return AxisHandle(name, RemoteAxis(link, spec.machine, task.name), task, kernel)


# ---- the operator's commands (host shell: ``axis NAME WORD``) -------------------------------

#: the engine operation of each word of the host's ``axis`` command
OPERATOR_OPS: dict[str, Op] = {
    "enable": Op.ENABLE, "disable": Op.DISABLE, "quick-stop": Op.QUICK_STOP,
    "fault-reset": Op.FAULT_RESET, "safe-stop": Op.SAFE_STOP, "set-mode": Op.SET_MODE,
    "home": Op.HOME,
}
#: wall-clock seconds an operator's command waits for its result at most (the engine ends
#: every command at its own timeout from the map; this only bounds a driver that stopped)
OPERATOR_WAIT = 120.0
#: seconds between two looks at a waiting command (and the slice a kernel that does not run
#: by itself is run for meanwhile)
OPERATOR_SLICE = 0.01


def describe(name: str, status: AxisStatus) -> str:
    """One line of what axis ``name``'s drive last confirmed: state, statusword, 0x603F,
    mode, position, velocity, and the command running."""
    def num(v: float | None) -> str:
        return "unknown" if v is None else f"{v:g}"

    state = "unknown (no statusword)" if status.state is None else status.state.name
    sw = "none" if status.statusword is None else f"0x{status.statusword:04X}"
    if status.fault is not None:
        code = status.fault.error_code
        ec = "unknown" if code is None else f"0x{code:04X}"
    else:
        ec = "none" if status.state is not None else "unknown"
    busy = "" if status.busy is None else f", running {status.busy.value}"
    return (f"axis {name}: state {state}, statusword {sw}, 0x603F {ec}, mode "
            f"{mode_name(status.mode_display)}, position {num(status.position)}, velocity "
            f"{num(status.velocity)}{busy}")


def operator_call(name: str, word: str, mode: str = "") -> AxisCall:
    """The call of the host's ``axis NAME WORD [MODE]`` (``word`` one of
    :data:`OPERATOR_OPS`). Raises CommandSyntaxError naming a mode that is no mode name or
    number."""
    op = OPERATOR_OPS[word]
    if op is not Op.SET_MODE or not mode:
        return AxisCall(op)
    chosen = mode_of(int(mode) if mode.lstrip("-").isdigit() else mode)
    if chosen is None:
        raise CommandSyntaxError(f"axis {name} set-mode: {mode!r} is no mode; expected "
                                 f"a name ({', '.join(Mode.__members__)}) or its number")
    return AxisCall(op, int(chosen))


def operator_command(devices: Any, name: str, word: str, mode: str,
                     pump: Callable[[], None] | None) -> str:
    """Carry out the host's ``axis NAME WORD [MODE]`` on Devtab ``devices`` (``word``:
    ``status`` or one of :data:`OPERATOR_OPS`): ``status`` describes the
    axis; a command is started on the axis's driver and waited for until the drive confirmed
    it (``pump``, if given, is called between looks: it runs a kernel that does not run by
    itself). Returns the result and what the drive shows; raises AxisCommandFailed (the state
    reached, statusword, 0x603F), the engine's refusal (AxisBusy, AxisLimitError), MessageError
    for a device that is no axis of this process, DeviceError when no result came within
    :data:`OPERATOR_WAIT` s."""
    driver = find_axis(devices, name)
    if word == "status":
        return describe(name, driver.axis_status(name))
    call = operator_call(name, word, mode)
    fut: concurrent.futures.Future[Result | Exception] = concurrent.futures.Future()

    def done(outcome: Result | Exception) -> None:      # the driver's thread
        if not fut.done():
            fut.set_result(outcome)

    driver.axis_call(name, call, done)
    deadline = time.monotonic() + OPERATOR_WAIT
    while True:
        try:
            outcome = fut.result(timeout=OPERATOR_SLICE)
            break
        except concurrent.futures.TimeoutError:
            if time.monotonic() > deadline:
                raise DeviceError(f"axis {name} {word}: no result within {OPERATOR_WAIT} s "
                                  f"({describe(name, driver.axis_status(name))})") from None
            if pump is not None:
                pump()
    if isinstance(outcome, ChcosError):
        raise outcome
    if isinstance(outcome, Exception):      # ValueError: the map gives no mode
        raise DeviceError(f"axis {name} {word}: {outcome}") from outcome
    if not outcome.ok:
        raise AxisCommandFailed(name, outcome)
    return f"axis {name}: {outcome}"

