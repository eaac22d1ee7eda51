"""canopen_axis - a CiA 402 axis as a device of the ``canopen`` driver: the devices one
``profile = "cia402"`` table of a device map becomes, the command codes its actuator takes, the
calls tasks make, and :class:`AxisHost`, which runs one :class:`drivers.codecs.cia402.Axis` engine
for the driver (readings in, writes out in order, reads answered, results completing the calls,
faults failing and recovering the axis device alone).

A device map's axis table ``x`` becomes these Devtab devices (all on the axis's bus):

* actuator ``x``: the axis. Its value is an :class:`AxisCode` (a command without argument, so
  the host shell and the north side can give it); its safe value is
  :attr:`AxisCode.SAFE_STOP`: e-stop, abnormal completion of the owning task, shutdown and its
  recovery run the axis's safe stop *sequence*, and the write is confirmed only when the drive's
  statusword confirms the sequence ended (or that the drive is in FAULT, its power stage
  off: confirmed as it is, nothing sent, the reason logged). A drive fault fails this device
  alone (cause ``drive-fault``, naming 0x603F); the sensors stay readable and the fault reset
  stays possible.
* sensors ``x.state`` (the :class:`drivers.codecs.cia402.State` name, e.g.
  ``"OPERATION_ENABLED"``),
  ``x.statusword``, ``x.mode`` (0x6061), ``x.position`` and ``x.velocity`` (user units),
  ``x.fault`` (0x603F while in a fault, else 0): what the drive confirmed.

The engine is used by the driver's I/O thread only; :meth:`AxisHost.status` is a snapshot any
thread may read, and :meth:`AxisHost.pdo_received` is called by the reader thread as a TPDO
arrives: its mark travels with the reading, so that a TPDO that waited in the I/O thread's queue
behind an SDO answer or a controlword write is known to be the older one (the engine never goes
back to an earlier state, nor takes a reading older than a controlword as its confirmation).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from typing import Any

from drivers.base import DriverHost
from drivers.codecs.cia402 import (
    PREEMPTING,
    Actions,
    Axis,
    AxisBusy,
    AxisConfig,
    AxisReading,
    Fault,
    Mode,
    Obj,
    Op,
    Reading,
    Result,
    State,
    Write,
    axis_names,
)

log = logging.getLogger(__name__)


class AxisCode(IntEnum):
    """What a write to an axis's actuator commands (the value is the code). The safe value of
    every axis is :attr:`SAFE_STOP`."""

    SAFE_STOP = 0
    ENABLE = 1
    DISABLE = 2
    QUICK_STOP = 3
    FAULT_RESET = 4
    SET_MODE = 5      # the map's ``mode``
    HOME = 6


#: the engine operation of each code
CODE_OPS: dict[AxisCode, Op] = {
    AxisCode.SAFE_STOP: Op.SAFE_STOP, AxisCode.ENABLE: Op.ENABLE, AxisCode.DISABLE: Op.DISABLE,
    AxisCode.QUICK_STOP: Op.QUICK_STOP, AxisCode.FAULT_RESET: Op.FAULT_RESET,
    AxisCode.SET_MODE: Op.SET_MODE, AxisCode.HOME: Op.HOME,
}


@dataclass(frozen=True)
class AxisCall:
    """One command of an axis: the engine's operation and its argument (the mode for
    SET_MODE, the position for MOVE_TO in user units, the velocity for AT_VELOCITY)."""

    op: Op
    arg: float | None = None


@dataclass(frozen=True)
class AxisStatus:
    """What the drive last confirmed (None: not known, e.g. before the first statusword or
    after the node was lost), and the command running."""

    state: State | None = None
    statusword: int | None = None
    mode_display: int | None = None
    position: float | None = None
    velocity: float | None = None
    fault: Fault | None = None
    busy: Op | None = None


#: called with a command's result, or the exception that refused it (busy, limits, stopped)
Done = Callable[[Result | Exception], None]


@dataclass
class _Pending:
    """A running command's caller (None: nobody waits, e.g. a node-loss safe stop), and the
    callers of the same safe stop asked for again while it ran (they get its result)."""

    op: Op
    done: Done | None
    joined: list[Done] = field(default_factory=list)


@dataclass
class AxisHost:
    """One axis of a node, hosted by the driver (see the module doc). ``send`` puts one write
    on the wire (an RPDO composed from the node's image, or an SDO download; raises on failure),
    ``read`` answers a read by SDO (the raw value, or None if the drive did not answer),
    ``deliver`` hands sensor readings to the host, ``fail``/``recover`` the axis device's
    health. All on the driver's I/O thread."""

    name: str
    node: int
    config: AxisConfig
    mode: Mode | None
    send: Callable[[Write], None]
    read: Callable[[Obj, int], int | None]
    deliver: Callable[[list[tuple[str, Any]]], None]
    fail: Callable[[str, str], None]
    recover: Callable[[str, str], None]
    report: Callable[[str], None]
    engine: Axis = field(init=False)
    sensors: dict[AxisReading, str] = field(init=False)
    _pending: list[_Pending] = field(default_factory=list)
    #: device commands waiting for the running command to end (Devtab writes, in order)
    _queued: list[tuple[AxisCall, Done | None]] = field(default_factory=list)
    _status: AxisStatus = field(default_factory=AxisStatus)
    _shown: dict[AxisReading, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.engine = Axis(self.config)
        self.sensors = axis_names(self.name)

    # -- any thread ----------------------------------------------------------------------------

    def status(self) -> AxisStatus:
        """A snapshot of what the drive confirmed (any thread)."""
        return self._status

    def pdo_received(self, objs: tuple[Obj, ...]) -> int:
        """The receive mark of a TPDO carrying ``objs`` of this axis, arriving now (the reader
        thread, before it queues the values for :meth:`reading`)."""
        return self.engine.order.pdo_received(objs)

    # -- the I/O thread ------------------------------------------------------------------------

    def objects(self) -> dict[tuple[int, int], Obj]:
        """The objects this axis takes readings from, by (index, subindex) with its offset."""
        objs = (Obj.STATUSWORD, Obj.MODES_DISPLAY, Obj.POSITION_ACTUAL, Obj.VELOCITY_ACTUAL,
                Obj.ERROR_CODE)
        return {(self.config.index(o), 0): o for o in objs}

    def reading(self, values: Mapping[Obj, int], now: float, received: int | None = None,
                *, answer: bool = False) -> None:
        """The values of one TPDO (``received``: its mark from :meth:`pdo_received`; None:
        received now) or SDO answers (``answer``; ``received`` the mark taken before they
        were asked) of this axis's objects."""
        self._perform(self.engine.update(_reading(values, received, answer), now), now)

    def refresh(self, now: float) -> None:
        """Read every object of the axis by SDO (those the drive answers) as one reading,
        marked as asked before the first read: a TPDO that arrives meanwhile is newer and
        wins for the objects it carries."""
        asked = self.engine.order.mark()
        values = {}
        for (index, _sub), obj in self.objects().items():
            value = self.read(obj, index)
            if value is not None:
                values[obj] = value
        if values:
            self.reading(values, now, asked, answer=True)

    def poll(self, now: float) -> None:
        """Advance the engine's timers."""
        self._perform(self.engine.poll(now), now)

    def command(self, call: AxisCall, done: Done | None, now: float, *,
                queue: bool = False) -> None:
        """Start ``call``; ``done`` gets its result, or the exception that refused it. With
        ``queue`` (device commands: Devtab writes, which come one after the other without
        waiting) a command that does not supersede the running one waits for it to end; a
        superseding one (quick stop, disable, safe stop) fails the queued ones."""
        eng = self.engine
        if call.op in (Op.SAFE_STOP, Op.QUICK_STOP) and eng.busy is Op.SAFE_STOP \
                and self._pending:
            # e-stop, then the abnormal end of the task it interrupted (or that task's own
            # quick stop): one sequence, not one superseding the other (each caller gets its
            # result: the axis stopped)
            if done is not None:
                self._pending[-1].joined.append(done)
            return
        if call.op in PREEMPTING:
            dropped, self._queued = self._queued, []
            for queued, queued_done in dropped:
                if queued_done is not None:
                    queued_done(AxisBusy(f"axis {self.name}: {queued.op.value} dropped: "
                                         f"superseded by {call.op.value}"))
        elif queue and (eng.busy is not None or self._queued):
            self._queued.append((call, done))
            return
        try:
            match call.op:
                case Op.ENABLE:
                    acts = eng.enable(now)
                case Op.DISABLE:
                    acts = eng.disable(now)
                case Op.QUICK_STOP:
                    acts = eng.quick_stop(now)
                case Op.FAULT_RESET:
                    acts = eng.fault_reset(now)
                case Op.SAFE_STOP:
                    acts = eng.safe_stop(now)
                case Op.HOME:
                    acts = eng.home(now)
                case Op.SET_MODE:
                    mode = self.mode if call.arg is None else int(call.arg)
                    if mode is None:
                        raise ValueError(f"axis {self.name}: set mode without a mode, and the "
                                         f"map gives none (key mode)")
                    acts = eng.set_mode(mode, now)
                case Op.MOVE_TO:
                    acts = eng.move_to(float(call.arg if call.arg is not None else math.nan),
                                       now)
                case Op.AT_VELOCITY:
                    acts = eng.at_velocity(float(call.arg if call.arg is not None
                                                 else math.nan), now)
        except Exception as exc:    # busy, limits: refused before anything was written
            if done is not None:
                done(exc)
            return
        # a superseded command's result comes first in acts: it belongs to the old caller
        self._pending.append(_Pending(call.op, done))
        self._perform(acts, now)

    def lost(self, reason: str, now: float) -> None:
        """The node failed or rebooted: the running command fails, the readings are
        forgotten (the sensors keep their last values, failed by the node's own causes)."""
        self._perform(self.engine.lost(reason, now), now)

    def _perform(self, acts: Actions, now: float) -> None:
        """Do what the engine asks, in order, feeding SDO answers back until it asks nothing."""
        while True:
            for w in acts.writes:
                try:
                    self.send(w)
                except Exception as exc:    # the command goes on: resends, or its timeout
                    self.report(f"axis {self.name}: write 0x{w.index:04X} = {w.value} "
                                f"failed: {exc}")
            for result in acts.results:
                self._complete(result)
            for fault in acts.faults:
                self._fault(fault)
            answers: dict[Obj, int] = {}
            asked = self.engine.order.mark()
            for obj in acts.reads:
                value = self.read(obj, self.config.index(obj))
                if value is not None:
                    answers[obj] = value
            self._show()
            if not answers:
                break
            acts = self.engine.update(_reading(answers, asked, True), now)

        if self._queued and self.engine.busy is None:
            call, done = self._queued.pop(0)
            self.command(call, done, now)

    def _complete(self, result: Result) -> None:
        if not self._pending:
            return
        p = self._pending.pop(0)
        if result.ok and result.reason and p.op is Op.SAFE_STOP:
            # reached, but not by the sequence: say how (a drive in FAULT is safe as it is)
            log.warning("axis %s: %s", self.name, result)
        for joined in p.joined:
            joined(result)
        if p.done is not None:
            p.done(result)
        elif not result.ok and not p.joined:
            self.report(f"axis {self.name}: {result}")

    def _fault(self, fault: Fault | None) -> None:
        if fault is None:
            self.recover(self.name, f"axis {self.name}: the drive left its fault")
            return
        code = "unknown" if fault.error_code is None else f"0x{fault.error_code:04X}"
        self.fail(self.name, f"axis {self.name}: drive fault, error code 0x603F {code}, "
                             f"statusword 0x{fault.statusword:04X}")

    def _show(self) -> None:
        """The snapshot, and the sensors whose value changed."""
        eng = self.engine
        state = eng.state
        self._status = AxisStatus(state, eng.statusword, eng.mode_display, eng.position,
                                  eng.velocity, eng.fault, eng.busy)
        fault = eng.fault
        values: dict[AxisReading, Any] = {
            AxisReading.STATE: None if state is None else state.name,
            AxisReading.STATUSWORD: eng.statusword,
            AxisReading.MODE: eng.mode_display,
            AxisReading.POSITION: eng.position,
            AxisReading.VELOCITY: eng.velocity,
            AxisReading.FAULT: 0 if fault is None else (fault.error_code or 0),
        }
        if state is None:
            values[AxisReading.FAULT] = None
        out = [(self.sensors[r], v) for r, v in values.items()
               if v is not None and self._shown.get(r) != v]
        self._shown.update((r, v) for r, v in values.items() if v is not None)
        if out:
            self.deliver(out)


def _reading(values: Mapping[Obj, int], received: int | None, answer: bool) -> Reading:
    """The engine's reading of ``values`` (see :class:`drivers.codecs.cia402.Reading`)."""
    return Reading(statusword=values.get(Obj.STATUSWORD),
                   mode_display=values.get(Obj.MODES_DISPLAY),
                   position=values.get(Obj.POSITION_ACTUAL),
                   velocity=values.get(Obj.VELOCITY_ACTUAL),
                   error_code=values.get(Obj.ERROR_CODE),
                   received=received, answer=answer)


def device_write(axis: AxisHost, host: DriverHost, device: str, value: Any) -> None:
    """A Devtab write to axis ``device``'s actuator (on ``axis``): the command of code ``value``,
    queued behind a running one. ``host.written`` once the drive confirmed it; otherwise
    ``host.write_failed`` naming the state reached, or why ``value`` is no command code."""

    def done(outcome: Result | Exception) -> None:
        if isinstance(outcome, Result) and outcome.ok:
            host.written(device, value)
        else:
            host.write_failed(device, value, f"axis {device}: {outcome}"
                              if isinstance(outcome, Result) else str(outcome))

    try:
        code = AxisCode(int(value))
    except (ValueError, TypeError) as exc:
        host.write_failed(device, value, f"axis {device}: {exc}")
        return
    axis.command(AxisCall(CODE_OPS[code]), done, host.now(), queue=True)
