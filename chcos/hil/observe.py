"""observe - what a running system does, as typed records on its clock, for the HIL evidence.

An :class:`Observer` watches one :class:`chcos.system.embedded.System` through the seams that
exist: the device table's listener (every reading: it stands between the device table and the
message manager, passing everything on), its health listeners (every status change), its
observers (every bus error, every command handed to a driver, confirmed or failed:
:mod:`chcos.devices.observers`) and a kernel instrument (every system event: abnormal ends,
restarts, pre-emptions, invokes...). With ``poll`` it also reads, every ``poll`` seconds of clock
time and at each status change, what the drivers show of their buses
(:meth:`chcos.devices.devtab.Devtab.bus_status`: CANopen nodes' NMT state and lifecycle, boot-ups,
EMCYs, a CAN controller's state) and the bus counters (reconnects).

Each observation is one :class:`Record` handed to every sink (:class:`Sink`): the trace of a run
(:mod:`chcos.hil.trace`) and device-state coverage (:mod:`chcos.hil.coverage`). A value is
recorded when it changes; a fast-path command (on the wire at once) is a ``command`` and a
``confirmed`` record at the same instant. Everything runs on the kernel thread.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

from chcos.devices.entry import DeviceStatus
from chcos.devices.observers import BusReport, CommandReport, WriteStage
from chcos.errors import SensorFailure
from chcos.hil.catalogue import failure_class, safe_class
from chcos.kernel.instrument import Instrument

if TYPE_CHECKING:
    from chcos.kernel.timers import Timer
    from chcos.system.embedded import System


class Kind(enum.StrEnum):
    """What a record says. The first seven are a run's trace; ``node`` and ``bus-state``
    come from polling (coverage only)."""

    VALUE = "value"              # a sensor's reading changed: value
    STATUS = "status"            # a device's status: value OK/failed/stale/suspended, cause class
    COMMAND = "command"          # an actuator command handed over: value, cause its source
    CONFIRMED = "confirmed"      # on the wire (confirmed by the driver)
    WRITE_FAILED = "write-failed"  # not written: text why
    BUS_ERROR = "bus-error"      # subject the bus: value the error class, cause the device
    EVENT = "event"              # subject a task (or the event kind): value the event kind
    NODE = "node"                # subject bus/node: cause the field (nmt, lifecycle...), value
    BUS_STATE = "bus-state"      # subject the bus: cause controller/reconnects, value


#: the kinds a run's trace holds (the others depend on polling)
TRACE_KINDS = frozenset({Kind.VALUE, Kind.STATUS, Kind.COMMAND, Kind.CONFIRMED,
                         Kind.WRITE_FAILED, Kind.BUS_ERROR, Kind.EVENT})


@dataclass(frozen=True, slots=True)
class Record:
    """One observation at clock time ``t`` (seconds since the observer's start): ``kind``,
    its ``subject`` (a device, task, bus or node), the ``value``, a ``cause`` class (compared
    by a diff) and free ``text`` for people (a failure's reason: addresses and wall-clock
    figures in it differ between runs)."""

    t: float
    kind: Kind
    subject: str
    value: Any = None
    cause: str = ""
    text: str = ""


class Sink(Protocol):
    """Who takes the records (on the kernel thread)."""

    def record(self, rec: Record) -> None:
        """One observation."""


#: system events that other records already say (status changes, failed writes)
_SKIPPED_EVENTS = frozenset({"device-ok", "device-failed", "device-stale", "device-suspended",
                             "write-failed"})
_PREEMPT = re.compile(r"\S+ took (\S+) from")
_WORD = re.compile(r"[A-Za-z_][\w.\-]*")


def event_subject(kind: str, detail: str, tasks: Iterable[str]) -> str:
    """The task a system event concerns: the one pre-empted for ``preempt``, else the first
    task named in ``detail``; the event's kind if it names none (``estop``, ``boot``)."""
    if kind == "preempt" and (m := _PREEMPT.match(detail)) is not None:
        return str(m.group(1))
    names = set(tasks)
    for word in _WORD.findall(detail):
        name = str(word).rstrip(".:")
        if name in names:
            return name
    return kind


def same(a: Any, b: Any) -> bool:
    """True if two readings are the same value (NaN is the same as NaN)."""
    if a is b:
        return True
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return type(a) is type(b) and bool(a == b)


class Observer(Instrument):
    """Watches ``system`` (see the module doc) from :meth:`attach` until :meth:`detach`; times
    are seconds since ``start`` (default: the clock's time at attach)."""

    def __init__(self, system: System, *, start: float | None = None,
                 poll: float | None = None) -> None:
        self.system = system
        self.sinks: list[Sink] = []
        self._start = start
        self._poll_period = poll
        self._timer: Timer | None = None
        self._attached = False
        self._last: dict[str, Any] = {}
        self._status: dict[str, str] = {}
        #: per device and per bus the last bus error since: (sequence number, class)
        self._seq = 0
        self._dev_error: dict[str, tuple[int, str]] = {}
        self._bus_error: dict[str, tuple[int, str]] = {}
        self._changed_at: dict[str, int] = {}
        self._polled: dict[tuple[str, str], Any] = {}

    # ---- life -------------------------------------------------------------------------------
    def attach(self) -> Observer:
        """Start watching; returns self. Idempotent."""
        if self._attached:
            return self
        s = self.system
        if self._start is None:
            self._start = s.kernel.clock.now()
        self._attached = True
        s.kernel.add_instrument(self)
        s.devtab.listen(self)
        s.devtab.add_health_listener(self._health)
        s.devtab.add_observer(self)
        if self._poll_period is not None:
            self._timer = s.kernel.every(self._poll_period, self.poll)
        return self

    def detach(self) -> None:
        """Stop watching (a last poll first, with ``poll``); the system goes on as before."""
        if not self._attached:
            return
        if self._poll_period is not None:
            self.poll()
        self._attached = False
        s = self.system
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        s.devtab.remove_observer(self)
        s.devtab.remove_health_listener(self._health)
        s.devtab.listen(s.msgmgr)
        s.kernel.remove_instrument(self)

    def now(self) -> float:
        """Seconds since the start."""
        return self.system.kernel.clock.now() - (self._start or 0.0)

    def _emit(self, kind: Kind, subject: str, value: Any = None, cause: str = "",
              text: str = "") -> None:
        rec = Record(self.now(), kind, subject, value, cause, text)
        for sink in self.sinks:
            sink.record(rec)

    # ---- the device table's listener (stands in front of the message manager) ---------------
    def reading(self, device: str, value: Any) -> bool:
        """A reading: recorded if it changed the device's value, then passed on."""
        if device not in self._last or not same(self._last[device], value):
            self._last[device] = value
            self._emit(Kind.VALUE, device, value)
        return self.system.msgmgr.reading(device, value)

    def sensor_failed(self, device: str, failure: SensorFailure) -> None:
        """Passed on (the status change is recorded by the health listener)."""
        self.system.msgmgr.sensor_failed(device, failure)

    # ---- health, bus errors, commands -------------------------------------------------------
    def _health(self, device: str, healthy: bool, cause: str) -> None:
        e = self.system.devtab.get(device)
        status = e.status.value
        was = self._status.get(device, DeviceStatus.OK.value)
        self._status[device] = status
        if e.status is DeviceStatus.OK:
            cls = {"failed": "recovered", "stale": "recovered", "suspended": "resumed"}.get(was,
                                                                                         "")
            text = cause
        elif e.status is DeviceStatus.FAILED:
            cls, text = failure_class(self._error_before(device, e.spec.bus), e.reason), e.reason
        elif e.status is DeviceStatus.STALE:
            cls, text = "stale_after", e.reason
        else:
            cls, text = "host", e.reason
        self._seq += 1
        self._changed_at[device] = self._seq
        self._emit(Kind.STATUS, device, status, cls, text)
        if self._poll_period is not None:
            self.poll()

    def _error_before(self, device: str, bus: str) -> str | None:
        """The class of the last bus error of ``device`` or its bus since its last status
        change (None: none)."""
        since = self._changed_at.get(device, 0)
        best = max((x for x in (self._dev_error.get(device), self._bus_error.get(bus))
                    if x is not None and x[0] > since), default=None)
        return None if best is None else best[1]

    def bus_error(self, report: BusReport) -> None:
        """A bus error: recorded, and kept as the cause of a failure that follows it."""
        self._seq += 1
        where = self._dev_error if report.device else self._bus_error
        where[report.device or report.bus] = (self._seq, report.kind)
        self._emit(Kind.BUS_ERROR, report.bus, report.kind, report.device, report.detail)
        if self._poll_period is not None and report.kind == "boot-up":
            self.poll()

    def command(self, report: CommandReport) -> None:
        """A command's stage: ``command`` (with ``confirmed`` for one on the wire at once),
        ``confirmed`` or ``write-failed``; the cause is the source, or ``safe:<reason>``."""
        cause = f"safe:{safe_class(report.safe)}" if report.safe else report.source
        if report.stage is WriteStage.FAILED:
            self._emit(Kind.WRITE_FAILED, report.device, report.value, cause, report.reason)
            return
        if report.source:       # handed over now (a tracked write reports no source later)
            self._emit(Kind.COMMAND, report.device, report.value, cause)
        if report.stage is WriteStage.CONFIRMED:
            self._emit(Kind.CONFIRMED, report.device, report.value,
                       f"safe:{safe_class(report.safe)}" if report.safe else "")

    # ---- the kernel's events ----------------------------------------------------------------
    def event(self, kind: str, detail: str) -> None:
        """A system event (those status records and failed writes already say are left out)."""
        if kind in _SKIPPED_EVENTS:
            return
        tasks = (t.name for t in self.system.tsktab)
        self._emit(Kind.EVENT, event_subject(kind, detail, tasks), kind, "", detail)

    # ---- what the drivers show --------------------------------------------------------------
    def poll(self) -> None:
        """Read the drivers' bus status and the bus counters; a record for each change."""
        devtab = self.system.devtab
        for bus, doc in devtab.bus_status().items():
            for node in doc.get("nodes", ()):
                where = f"{bus}/{node.get('node')}"
                for key in ("nmt", "state", "boots", "heartbeat_losses", "emcys", "last_emcy",
                            "ready", "heartbeat_lost"):
                    if key in node:
                        self._changed(Kind.NODE, where, key, node[key])
            ctl = doc.get("controller")
            if isinstance(ctl, dict) and "state" in ctl:
                self._changed(Kind.BUS_STATE, bus, "controller", ctl["state"])
        for bus, st in devtab.bus_stats.items():
            if st.counts.get("reconnects"):
                self._changed(Kind.BUS_STATE, bus, "reconnects", st.counts["reconnects"])

    def _changed(self, kind: Kind, subject: str, key: str, value: Any) -> None:
        k = (subject, key)
        if k in self._polled and same(self._polled[k], value):
            return
        self._polled[k] = value
        self._emit(kind, subject, value, key)
