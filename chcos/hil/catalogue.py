"""catalogue - what each device, bus and task of a cell *can* reach, from its device map and its
profile: the denominator of device-state coverage (:mod:`chcos.hil.coverage`).

A state is a :class:`State`: a class (:class:`StateClass`: device status, failure cause, safe
value, CANopen NMT, EMCY, CiA 402, bus state, bus errors, task) and a name within it. What a
subject can reach depends on what it is: every driven device can be OK, fail and recover; a
sensor with ``stale_after`` can go stale; an actuator with a ``safe_value`` can be put there on an
abnormal end, an e-stop, a recovery and at shutdown; a device's failure causes are those its bus
kind reports (a Modbus TCP sensor: no answer, the connection lost, each exception code a server
sends; a CANopen device: its node rebooted, its heartbeat lost if it is supervised, an EMCY); a
CANopen device has its node's NMT states and EMCYs, a Modbus sensor has none; a CiA 402 axis
(``profile = "cia402"``: one subject for the axis and its ``x.state``... sensors) has the eight
states of its state machine and the drive fault; a CAN bus can go error-passive and bus-off; a
task can end abnormally, be pre-empted and, with a restart policy, restart. docs/hil-evidence.md
has the tables.

:func:`failure_class` names the cause class of one failure from the bus error its driver
reported before it (or, where the driver reports none, the failure's text).
"""

from __future__ import annotations

import enum
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec


class StateClass(enum.StrEnum):
    """The classes of states, in the order the coverage table shows them."""

    STATUS = "status"
    FAILURE = "failure"
    SAFE = "safe value"
    NMT = "NMT"
    EMCY = "EMCY"
    CIA402 = "CiA 402"
    BUS_STATE = "bus state"
    BUS_ERRORS = "bus errors"
    TASK = "task"


class SubjectKind(enum.StrEnum):
    """What a coverage subject is."""

    DEVICE = "device"
    BUS = "bus"
    TASK = "task"


@dataclass(frozen=True, order=True, slots=True)
class State:
    """One state of a subject: ``cls`` and ``name`` (``failure``/``timeout``)."""

    cls: StateClass
    name: str

    def __str__(self) -> str:
        return f"{self.cls}: {self.name}"


@dataclass
class Subject:
    """A device (an axis with its sensors is one), a bus or a task, and the states it can
    reach (its catalogue). ``role`` says more: ``sensor``, ``actuator``, ``axis``, the bus
    kind, the task's level; ``bus`` and ``kind`` are the bus a device is on and that bus's
    kind; ``file`` the device map it comes from."""

    kind: SubjectKind
    name: str
    role: str
    bus: str = ""
    bus_kind: str = ""
    file: str = ""
    states: tuple[State, ...] = ()
    #: the device names this subject stands for (an axis: the actuator and its sensors)
    devices: tuple[str, ...] = field(default=())

    @property
    def key(self) -> str:
        """The subject's key in a coverage file: ``device:level``, ``bus:plc``, ``task:fill``."""
        return f"{self.kind}:{self.name}"


#: the statuses of every driven device (stale only for sensors with ``stale_after``)
STATUS_OK, STATUS_STALE, STATUS_FAILED, STATUS_RECOVERED = "OK", "stale", "failed", "recovered"
#: the reasons a safe value is written (an e-stop's reason is free text: anything else is one)
SAFE_REASONS = ("abnormal completion", "e-stop", "recovery", "shutdown")
#: CANopen NMT states and transitions a node's devices can see
NMT_STATES = ("boot-up", "PRE-OPERATIONAL", "OPERATIONAL", "STOPPED", "reboot")
#: what an EMCY can be: a fault, or the error reset that ends it
EMCY_STATES = ("EMCY", "error reset")
#: the CiA 402 power states, as the axis's ``x.state`` sensor names them
CIA402_STATES = ("NOT_READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON",
                 "SWITCHED_ON", "OPERATION_ENABLED", "QUICK_STOP_ACTIVE",
                 "FAULT_REACTION_ACTIVE", "FAULT")
#: task states
TASK_STATES = ("abnormal end", "pre-empted", "restart")
#: Modbus exception codes a server answers at run time (01..04, 06 busy)
MODBUS_EXCEPTIONS = tuple(f"exception-{c}" for c in (1, 2, 3, 4, 6))

#: failure causes by bus kind (the classes :func:`failure_class` gives)
FAILURE_CAUSES: Mapping[str, tuple[str, ...]] = {
    "modbus-tcp": ("timeout", "disconnected", *MODBUS_EXCEPTIONS),
    "modbus-rtu": ("timeout", "crc", "framing", *MODBUS_EXCEPTIONS),
    "can": ("malformed", "bus-off"),
    "serial": ("disconnected",),
}
#: bus states by bus kind
BUS_STATES: Mapping[str, tuple[str, ...]] = {
    "modbus-tcp": ("disconnected", "reconnected"),
    "can": ("error-passive", "bus-off"),
    "canopen": ("error-passive", "bus-off"),
    "serial": ("disconnected",),
}
#: errors of the frames on the wire by bus kind (what does not fail a device by itself)
BUS_ERRORS: Mapping[str, tuple[str, ...]] = {
    "modbus-tcp": ("malformed",),
    "modbus-rtu": ("crc", "framing", "malformed"),
    "can": ("error-frame", "wrong-length", "undecodable", "unknown-id"),
    "canopen": ("malformed", "unknown-node"),
    "serial": ("garbage", "malformed", "checksum"),
}

#: bus error classes that are one failure class (a malformed CAN frame of any kind)
_ERROR_CLASS = {"wrong-length": "malformed", "undecodable": "malformed", "boot-up": "reboot",
                "connect-failed": "disconnected", "not-sent": "disconnected"}
#: where a driver fails a device without reporting a bus error first: the cause from its text
_REASON_CLASS = (
    (re.compile(r"no heartbeat|heartbeat lost", re.I), "heartbeat"),
    (re.compile(r"rebooted|boot-up", re.I), "reboot"),
    (re.compile(r"drive fault|0x603F", re.I), "drive-fault"),
    (re.compile(r"\bEMCY\b"), "emcy"),
    (re.compile(r"SDO .*abort", re.I), "sdo-abort"),
    (re.compile(r"bus-off", re.I), "bus-off"),
    (re.compile(r"exception code (\d+)", re.I), "exception-{0}"),
    (re.compile(r"lost|disconnected|not connected|closed", re.I), "disconnected"),
    (re.compile(r"timed? ?out|no response|no answer", re.I), "timeout"),
)
#: what a failure with no known cause is (a test's or the host's ``fail``, another satellite)
REPORTED = "reported"


def failure_class(error_kind: str | None, reason: str) -> str:
    """The cause class of a failure: the class of the bus error the driver reported for the
    device (or its bus) just before it, if any (``timeout``, ``exception-6``, ``sdo-abort``,
    ``bus-off``, a malformed frame as ``malformed``, a boot-up as ``reboot``); else read from
    the failure's text (heartbeat lost, a drive fault...); else ``reported``."""
    if error_kind:
        return _ERROR_CLASS.get(error_kind, error_kind)
    for pattern, cls in _REASON_CLASS:
        m = pattern.search(reason)
        if m is not None:
            return cls.format(*m.groups())
    return REPORTED


def safe_class(why: str) -> str:
    """The safe-value reason class of ``why`` (an e-stop's reason is any other text)."""
    return why if why in SAFE_REASONS else "e-stop"


def is_axis(spec: DeviceSpec) -> bool:
    """True for a device a CiA 402 axis table became (its actuator or one of its sensors)."""
    return spec.address.get("profile") == "cia402"


def axis_of(spec: DeviceSpec) -> str:
    """The axis a CiA 402 device belongs to: the actuator's name (``x`` for ``x.state``)."""
    return spec.name if spec.direction == "actuator" else spec.name.rsplit(".", 1)[0]


def _nodes(bus: BusSpec) -> dict[int, Mapping[str, Any]]:
    nodes = bus.options.get("nodes", ())
    return {int(n["id"]): n for n in nodes if isinstance(n, Mapping) and "id" in n}


def _device_states(spec: DeviceSpec, bus: BusSpec | None, axis: bool) -> list[State]:
    kind = bus.kind if bus is not None else ""
    states = [State(StateClass.STATUS, s) for s in (STATUS_OK, STATUS_FAILED, STATUS_RECOVERED)]
    if spec.direction == "sensor" and spec.stale_after is not None:
        states.append(State(StateClass.STATUS, STATUS_STALE))
    causes = list(FAILURE_CAUSES.get(kind, ()))
    if kind == "canopen" and bus is not None:
        node = _nodes(bus).get(int(spec.address.get("node", -1)), {})
        causes += ["reboot", *(["heartbeat"] if node.get("heartbeat_timeout") else [])]
        causes += ["drive-fault"] if axis else ["emcy"]
        if spec.direction == "actuator" and not axis:
            causes.append("sdo-abort")
    elif not causes:
        causes = [REPORTED]     # memory, signal, the welding model: only what is reported
    states += [State(StateClass.FAILURE, c) for c in causes]
    if spec.direction == "actuator" and spec.safe_value is not None:
        states += [State(StateClass.SAFE, s) for s in SAFE_REASONS]
    if kind == "canopen":
        states += [State(StateClass.NMT, s) for s in NMT_STATES]
        states += [State(StateClass.EMCY, s) for s in EMCY_STATES]
    if axis:
        states += [State(StateClass.CIA402, s) for s in CIA402_STATES]
    return states


def device_subjects(devmap: DeviceMap) -> list[Subject]:
    """One subject per device of ``devmap`` (an axis and its sensors as one), with its
    catalogue."""
    buses = {b.name: b for b in devmap.buses}
    out: list[Subject] = []
    axes: dict[str, list[str]] = {}
    for spec in devmap.devices:
        if is_axis(spec):
            axes.setdefault(axis_of(spec), []).append(spec.name)
    for spec in devmap.devices:
        axis = is_axis(spec)
        if axis and spec.direction != "actuator":
            continue
        bus = buses.get(spec.bus)
        out.append(Subject(SubjectKind.DEVICE, spec.name, "axis" if axis else spec.direction,
                           spec.bus, bus.kind if bus is not None else "", spec.file,
                           tuple(_device_states(spec, bus, axis)),
                           tuple(axes.get(spec.name, [spec.name]))))
    return out


def bus_subjects(devmap: DeviceMap) -> list[Subject]:
    """One subject per bus of ``devmap`` that has states of its own (its state, the errors of
    its frames)."""
    out = []
    for bus in devmap.buses:
        states = [State(StateClass.BUS_STATE, s) for s in BUS_STATES.get(bus.kind, ())]
        states += [State(StateClass.BUS_ERRORS, s) for s in BUS_ERRORS.get(bus.kind, ())]
        if not states:
            continue
        out.append(Subject(SubjectKind.BUS, bus.name, bus.kind, bus.name, bus.kind, bus.file,
                           tuple(states)))
    return out


def task_subject(name: str, level: int, restart: str) -> Subject:
    """The subject of one task: it can end abnormally and be pre-empted; it can restart only
    with a restart policy (``restart`` other than ``never``)."""
    states = [State(StateClass.TASK, s) for s in TASK_STATES
              if s != "restart" or restart != "never"]
    return Subject(SubjectKind.TASK, name, f"level {level}", states=tuple(states))


def catalogue(devmap: DeviceMap, tasks: Iterable[tuple[str, int, str]] = ()) -> list[Subject]:
    """Every subject of a cell: its devices, its buses and its tasks (``(name, level,
    restart policy)``), each with what it can reach."""
    return [*device_subjects(devmap), *bus_subjects(devmap),
            *(task_subject(n, lvl, r) for n, lvl, r in tasks)]
