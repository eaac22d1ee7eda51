"""opcua_alarms - the OPC UA server's alarms (OffNormalAlarmType conditions), for
:mod:`chcos.north.opcua`.

ConditionId ``Alarms.<source>``, emitted by the Server object: a device that fails or goes stale
raises an active alarm with the device's node as SourceNode (:data:`HEALTH_SEVERITY`), cleared
when the device is healthy again; an e-stop and an abnormal completion raise one that stays
active until acknowledged. Every state change is an event with ActiveState, AckedState, Retain,
Severity and Message (:meth:`AlarmsMixin._tell`). ``Acknowledge(EventId, Comment)`` needs a
user whose role may ``invoke``; an outdated EventId answers BadEventIdUnknown.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass
from typing import Any

from chcos.north.opcua_methods import MethodsMixin, ua

log = logging.getLogger("chcos.north.opcua")
#: severity of the alarm raised by a device whose health became this status
HEALTH_SEVERITY = {"failed": 900, "stale": 700}


@dataclass
class Alarm:
    """One condition's state: ``key`` (``Devices.<name>``, ``Tasks.<name>`` or ``EStop``), its
    source node id text, severity, message, active and acknowledged flags, the EventId of its
    latest event and the comment and user of the last acknowledgement."""

    key: str
    source: str
    severity: int
    message: str
    active: bool = True
    acked: bool = False
    event_id: bytes = b""
    comment: str = ""
    user: str = ""

    @property
    def retain(self) -> bool:
        """A client must still show it: active or not yet acknowledged."""
        return self.active or not self.acked


class AlarmsMixin(MethodsMixin):
    """Raising, clearing, telling and acknowledging alarms, for
    :class:`chcos.north.opcua.OpcUaServer` (which supplies the address-space handles)."""

    alarms: dict[str, Alarm]
    _alarm_folder: Any
    _alarmgen: Any
    _idx: int

    async def _health_alarm(self, device: str, healthy: bool, status: str, cause: str) -> None:
        key = f"Devices.{device}"
        if healthy:
            a = self.alarms.get(key)
            if a is not None and a.active:
                a.active = False
                a.message = f"{device} {cause or 'healthy again'}"
                await self._tell(a)
        elif status in HEALTH_SEVERITY:
            await self._raise(key, key, HEALTH_SEVERITY[status],
                              f"{device} {status}" + (f": {cause}" if cause else ""))

    async def _raise(self, key: str, source: str, severity: int, message: str) -> None:
        """Raise (or raise again) the alarm ``key`` of source node ``source``."""
        if key not in self.alarms:
            await self._alarm_folder.add_object(ua.NodeId(f"Alarms.{key}", self._idx),
                                                self._qn(key))
        a = self.alarms[key] = Alarm(key, source, severity, message)
        await self._tell(a)

    async def _tell(self, a: Alarm, subscription_id: int | None = None) -> None:
        """Send the alarm's current state as an OffNormalAlarmType event. A fresh event object
        each time: asyncua keeps the last retained one per condition for ConditionRefresh."""
        ev = self._alarmgen.event = copy.copy(self._alarmgen.event)
        text = ua.LocalizedText
        ev.NodeId = ua.NodeId(f"Alarms.{a.key}", self._idx)
        ev.SourceNode = ua.NodeId(a.source, self._idx)
        ev.SourceName = a.key.split(".", 1)[-1]
        ev.ConditionName = a.key
        ev.ConditionClassId = ua.NodeId(ua.ObjectIds.BaseConditionClassType)
        ev.ConditionClassName = text("BaseConditionClass")
        ev.Message = text(a.message)
        ev.Severity = a.severity
        ev.LastSeverity = a.severity
        ev.Retain = a.retain
        ev.Quality = ua.StatusCode()
        ev.EnabledState = text("Enabled")
        setattr(ev, "EnabledState/Id", True)
        ev.ActiveState = text("Active" if a.active else "Inactive")
        setattr(ev, "ActiveState/Id", a.active)
        ev.AckedState = text("Acknowledged" if a.acked else "Unacknowledged")
        setattr(ev, "AckedState/Id", a.acked)
        ev.Comment = text(a.comment)
        ev.ClientUserId = a.user if a.acked else ""
        await self._alarmgen.trigger(subscription_id=subscription_id)
        eid = ev.EventId
        a.event_id = bytes(eid.Value if isinstance(eid, ua.Variant) else eid)
        if not a.retain:
            del self.alarms[a.key]

    async def _acknowledge(self, parent: ua.NodeId, event_id: Any, comment: Any) -> Any:
        """The Acknowledge method of a condition: operators and supervisors only."""
        who, account = self._user()
        if account is None or not account.may("invoke"):
            self._refusal(who, "acknowledge", f"acknowledge: {who} may not acknowledge alarms "
                          f"(role {account.role if account else 'anonymous'})")
            return ua.StatusCode(ua.StatusCodes.BadUserAccessDenied)
        key = str(parent.Identifier)
        a = self.alarms.get(key[len("Alarms."):]) if key.startswith("Alarms.") else None
        if a is None:
            return ua.StatusCode(ua.StatusCodes.BadConditionBranchAlreadyAcked
                                 if key.startswith("Alarms.") else ua.StatusCodes.BadNodeIdInvalid)
        eid = event_id.Value if isinstance(event_id, ua.Variant) else event_id
        if bytes(eid or b"") != a.event_id:
            return ua.StatusCode(ua.StatusCodes.BadEventIdUnknown)
        if a.acked:
            return ua.StatusCode(ua.StatusCodes.BadConditionBranchAlreadyAcked)
        c = comment.Value if isinstance(comment, ua.Variant) else comment
        a.acked, a.user = True, who
        a.comment = c.Text or "" if isinstance(c, ua.LocalizedText) else str(c or "")
        if a.key in ("EStop",) or a.key.startswith("Tasks."):
            a.active = False  # a latched alarm ends with its acknowledgement
        log.info("opcua: alarm %s acknowledged by %s", a.key, who)
        await self._tell(a)
        return []
