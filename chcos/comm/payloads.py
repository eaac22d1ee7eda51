"""payloads - the typed payloads of link messages between satellites, and their wire form.

Every value a :class:`chcos.comm.manager.CommManager` sends is one of the frozen dataclasses
here (a sensory value travels bare: it is the task's own data). :func:`to_wire` turns one into
the JSON value the codec carries (:mod:`chcos.comm.codec`), :func:`from_wire` checks what came
in and turns it back into its type, so nothing past this boundary reads ``{"op": ...}`` dicts.
The wire form is JSON objects with an ``op`` key, as before::

    COMMAND   {"op": "open", "command": ..., "wait": bool}       OpenRequest
              {"op": "close"}                                    CloseRequest
              {"op": "actuator", "device": str, "value": ...}    ActuatorCommand
              {"op": "estop", "reason": str, "from": int}        EmergencyStop
              {"op": "axis", "rid": int, "device": str, "call": str, "arg": number|null,
               "from": int}                                       AxisRequest
    REPLY     {"op": "open", "answer": "owner"|"queued"|"busy", "reason": str}  OpenReply
              {"op": "answer", "qid": int, "answer": ...}        QueryAnswer
              {"op": "axis", "rid": int, "result": {...}|null, "error": str}  AxisReply
    STATUS    {"device": str, "status": str, "reason": str, "from": int}  StatusChange
              {"op": "hello", "from": int, "ask": bool}          Hello
    COMPLETION/PREEMPTION {"status": str, "result": ..., "error": str}  Report
    QUERY     {"qid": int, "topic": str, "args": [...]}          Query
    ERROR     {"qid": int, "error": str}                         QueryFailed

:class:`OpenAnswer` is what the target's satellite answers an ``open`` from another satellite
(:meth:`chcos.messages.manager.MessageManager.remote_open`). Malformed input raises
:class:`chcos.errors.MessageError` naming the kind, the field and what was expected.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from chcos.comm.codec import MessageKind
from chcos.devices.entry import DeviceStatus
from chcos.errors import MessageError
from chcos.helpers import is_number
from chcos.tables.messages import LinkStatus

#: The device statuses a STATUS message may carry.
DEVICE_STATUSES = tuple(st.value for st in DeviceStatus)  # the texts Devtab statuses carry


class OpenOutcome(enum.Enum):
    """How the target's satellite took a remote ``open``."""

    OWNER = "owner"    # the caller owns the target now
    QUEUED = "queued"  # the caller waits in the target's queue
    BUSY = "busy"      # refused: held at a higher priority (``reason`` says by whom)


@dataclass(frozen=True)
class OpenAnswer:
    """The answer to a remote ``open``: its outcome and, for BUSY, why."""

    outcome: OpenOutcome
    reason: str = ""

    @classmethod
    def owner(cls) -> OpenAnswer:
        """The caller now owns the target."""
        return cls(OpenOutcome.OWNER)

    @classmethod
    def queued(cls) -> OpenAnswer:
        """The caller waits in the target's queue."""
        return cls(OpenOutcome.QUEUED)

    @classmethod
    def busy(cls, reason: str) -> OpenAnswer:
        """Refused; ``reason`` says why (the Busy error's text)."""
        return cls(OpenOutcome.BUSY, reason)


@dataclass(frozen=True)
class OpenRequest:
    """topen of a task on another satellite."""

    command: Any
    wait: bool


@dataclass(frozen=True)
class CloseRequest:
    """tclose of a task on another satellite."""


@dataclass(frozen=True)
class ActuatorCommand:
    """An actuator command to the device's satellite."""

    device: str
    value: Any


@dataclass(frozen=True)
class AxisRequest:
    """A command of a CiA 402 axis to the satellite hosting it, for a task of machine
    ``origin``: ``call`` is the engine's operation (:class:`drivers.codecs.cia402.Op` value),
    ``arg`` its argument; ``rid`` names the request in its :class:`AxisReply`."""

    rid: int
    device: str
    call: str
    arg: float | None
    origin: int


@dataclass(frozen=True)
class AxisReply:
    """What became of axis request ``rid``: the drive's result (a
    :func:`drivers.codecs.cia402.result_doc` object), or ``error``: why it was refused."""

    rid: int
    result: dict[str, Any] | None
    error: str = ""


@dataclass(frozen=True)
class EmergencyStop:
    """Emergency stop everywhere; ``origin`` is the machine that raised it."""

    reason: str
    origin: int


@dataclass(frozen=True)
class OpenReply:
    """The target's satellite answers an :class:`OpenRequest`."""

    answer: OpenAnswer


@dataclass(frozen=True)
class StatusChange:
    """A device of machine ``origin`` changed status (one of :data:`DEVICE_STATUSES`)."""

    device: str
    status: str
    reason: str
    origin: int


@dataclass(frozen=True)
class Report:
    """A completion or pre-emption on a link, for the caller's satellite."""

    status: LinkStatus
    result: Any = None
    error: str = ""


@dataclass(frozen=True)
class Query:
    """A world-model query ``qid`` about ``topic``."""

    qid: int
    topic: str
    args: list[Any] = field(default_factory=list)


@dataclass(frozen=True)
class QueryAnswer:
    """The world model's answer to query ``qid``."""

    qid: int
    answer: Any


@dataclass(frozen=True)
class QueryFailed:
    """Query ``qid`` could not be answered; ``error`` says why."""

    qid: int
    error: str


@dataclass(frozen=True)
class Hello:
    """Satellite ``origin`` is on the link (sealed, so a liveliness token alone does not make
    a satellite up); ``ask``: every satellite that hears it answers with its own."""

    origin: int
    ask: bool


Payload = (OpenRequest | CloseRequest | ActuatorCommand | EmergencyStop | OpenReply
           | StatusChange | Report | Query | QueryAnswer | QueryFailed | Hello | AxisRequest
           | AxisReply)

#: The message kind each payload type travels as.
KIND_OF: dict[type[Any], MessageKind] = {
    OpenRequest: MessageKind.COMMAND, CloseRequest: MessageKind.COMMAND,
    ActuatorCommand: MessageKind.COMMAND, EmergencyStop: MessageKind.COMMAND,
    OpenReply: MessageKind.REPLY, QueryAnswer: MessageKind.REPLY,
    StatusChange: MessageKind.STATUS, Query: MessageKind.QUERY, QueryFailed: MessageKind.ERROR,
    Hello: MessageKind.STATUS, AxisRequest: MessageKind.COMMAND, AxisReply: MessageKind.REPLY,
}


def to_wire(p: Payload) -> dict[str, Any]:
    """The JSON value that carries ``p`` (see the module doc)."""
    if isinstance(p, OpenRequest):
        return {"op": "open", "command": p.command, "wait": p.wait}
    if isinstance(p, CloseRequest):
        return {"op": "close"}
    if isinstance(p, ActuatorCommand):
        return {"op": "actuator", "device": p.device, "value": p.value}
    if isinstance(p, EmergencyStop):
        return {"op": "estop", "reason": p.reason, "from": p.origin}
    if isinstance(p, AxisRequest):
        return {"op": "axis", "rid": p.rid, "device": p.device, "call": p.call, "arg": p.arg,
                "from": p.origin}
    if isinstance(p, AxisReply):
        return {"op": "axis", "rid": p.rid, "result": p.result, "error": p.error}
    if isinstance(p, OpenReply):
        return {"op": "open", "answer": p.answer.outcome.value, "reason": p.answer.reason}
    if isinstance(p, QueryAnswer):
        return {"op": "answer", "qid": p.qid, "answer": p.answer}
    if isinstance(p, StatusChange):
        return {"device": p.device, "status": p.status, "reason": p.reason, "from": p.origin}
    if isinstance(p, Hello):
        return {"op": "hello", "from": p.origin, "ask": p.ask}
    if isinstance(p, Report):
        return {"status": p.status.value, "result": p.result, "error": p.error}
    if isinstance(p, Query):
        return {"qid": p.qid, "topic": p.topic, "args": list(p.args)}
    return {"qid": p.qid, "error": p.error}


def _get(kind: MessageKind, v: Mapping[str, Any], key: str, typ: type[Any] | tuple[type[Any], ...],
         what: str) -> Any:
    value = v.get(key)
    if not isinstance(value, typ) or (isinstance(value, bool) and typ is int):
        raise MessageError(f"{kind.name} message: {key!r}: expected {what}, got {value!r:.80}")
    return value


def from_wire(kind: MessageKind, value: Any) -> Payload:
    """The typed payload of a non-sensory message of ``kind`` carrying ``value``. Raises
    MessageError naming the kind and field if ``value`` is not what ``kind`` carries."""
    if not isinstance(value, Mapping):
        raise MessageError(f"{kind.name} message: expected a JSON object, got {value!r:.120}")
    v = value
    op = v.get("op")
    if kind is MessageKind.COMMAND:
        if op == "open":
            return OpenRequest(v.get("command"), bool(_get(kind, v, "wait", bool, "true/false")))
        if op == "close":
            return CloseRequest()
        if op == "actuator":
            if "value" not in v:
                raise MessageError("COMMAND message: 'value': expected the actuator's value")
            return ActuatorCommand(_get(kind, v, "device", str, "a device name"), v["value"])
        if op == "estop":
            return EmergencyStop(str(v.get("reason", "")), _get(kind, v, "from", int, "a machine"))
        if op == "axis":
            arg = v.get("arg")
            if arg is not None and (isinstance(arg, bool) or not isinstance(arg, int | float)
                                    or not math.isfinite(arg)):
                raise MessageError(f"COMMAND message: 'arg': expected a finite number or null, "
                                   f"got {arg!r:.40}")
            return AxisRequest(_get(kind, v, "rid", int, "a request id"),
                               _get(kind, v, "device", str, "a device name"),
                               _get(kind, v, "call", str, "an axis command"),
                               None if arg is None else float(arg),
                               _get(kind, v, "from", int, "a machine"))
        raise MessageError(f"COMMAND message: unknown op {op!r:.40}; expected open, close, "
                           "actuator, estop or axis")
    if kind is MessageKind.REPLY:
        if op == "open":
            try:
                outcome = OpenOutcome(v.get("answer"))
            except ValueError:
                raise MessageError(f"REPLY message: 'answer': expected owner, queued or busy, "
                                   f"got {v.get('answer')!r:.40}") from None
            return OpenReply(OpenAnswer(outcome, str(v.get("reason", ""))))
        if op == "answer":
            return QueryAnswer(_get(kind, v, "qid", int, "a query id"), v.get("answer"))
        if op == "axis":
            result = v.get("result")
            if result is not None and not isinstance(result, dict):
                raise MessageError(f"REPLY message: 'result': expected an axis result or null, "
                                   f"got {result!r:.80}")
            return AxisReply(_get(kind, v, "rid", int, "a request id"), result,
                             str(v.get("error") or ""))
        raise MessageError(f"REPLY message: unknown op {op!r:.40}; expected open, answer or "
                           "axis")
    if kind is MessageKind.STATUS:
        if op == "hello":
            return Hello(_get(kind, v, "from", int, "a machine"),
                         _get(kind, v, "ask", bool, "true/false"))
        status = v.get("status")
        if status not in DEVICE_STATUSES:
            raise MessageError(f"STATUS message: 'status': expected one of "
                               f"{', '.join(DEVICE_STATUSES)}, got {status!r:.40}")
        return StatusChange(_get(kind, v, "device", str, "a device name"), status,
                            _get(kind, v, "reason", str, "a text"),
                            _get(kind, v, "from", int, "a machine"))
    if kind in (MessageKind.COMPLETION, MessageKind.PREEMPTION):
        try:
            status_ = LinkStatus(v.get("status"))
        except ValueError:
            raise MessageError(f"{kind.name} message: 'status': expected a link status, got "
                               f"{v.get('status')!r:.40}") from None
        return Report(status_, v.get("result"), str(v.get("error") or ""))
    if kind is MessageKind.QUERY:
        args = v.get("args") or []
        if not isinstance(args, list):
            raise MessageError(f"QUERY message: 'args': expected a list, got {args!r:.80}")
        return Query(_get(kind, v, "qid", int, "a query id"),
                     _get(kind, v, "topic", str, "a topic"), args)
    if kind is MessageKind.ERROR:
        return QueryFailed(_get(kind, v, "qid", int, "a query id"),
                           _get(kind, v, "error", str, "a text"))
    raise MessageError(f"unexpected message kind {kind.name}")


def check_actuator_value(device: str, safe: Any, limits: tuple[Any, Any], value: Any) -> None:
    """Refuse an actuator command from the link whose type does not fit the actuator: a number
    (int or float, finite; bool only where the safe value is a bool) where the safe value or a
    limit is a number. Raises MessageError naming the device and the value."""
    numeric = any(is_number(x) for x in (safe, *limits))
    if isinstance(safe, bool):
        if not isinstance(value, bool):
            raise MessageError(f"actuator {device}: expected true or false, got {value!r:.80}")
    elif numeric:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise MessageError(f"actuator {device}: expected a number, got "
                               f"{type(value).__name__} {value!r:.80}")
        if not math.isfinite(value):
            raise MessageError(f"actuator {device}: expected a finite number, got {value!r}")
