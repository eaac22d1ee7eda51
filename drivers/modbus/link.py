"""link - the supervision of a Modbus bus's link and of its units: what fails the devices,
what is a connection-level cause, when a connection is healthy, and the backoff of units that
stop answering. No I/O: the engines (:mod:`drivers.modbus.engine`) tell it what happened.

Connection-level causes (:class:`Link`): a connection that cannot be made, one the peer closes
or resets, a byte stream that is no Modbus any more, and - on ``modbus-tcp`` - requests that go
unanswered with nothing at all coming back on the connection: the first request after a connect
(a server that accepts connections but does not answer: frozen, SIGSTOPped), or
:data:`SILENT_REQUESTS` requests in a row. One request that always times out while the others
are answered is that request's devices' failure, not the connection's: the connection is kept.
A connect is not health: the devices recover (cause ``link``) once a request is answered - on
``modbus-rtu`` the devices of the unit that answered.

Units (:class:`Units`, ``modbus-rtu`` and a ``modbus-tcp`` gateway): a unit that does not answer
(after the bus's ``retries``) fails every device of that unit (cause ``unit``), is backed off
(:class:`drivers.codecs.modbus.UnitBackoff`) so the live units keep their rate, and - RTU -
is held quiet for one ``timeout`` before a different request goes to it (:meth:`Units.guard`),
so that its late answer is taken for nothing: RTU answers carry no transaction id.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from drivers.base import DriverHost
from drivers.codecs.modbus import Point, UnitBackoff
from drivers.health import Health

#: requests in a row without any answer on a TCP connection that make it lost
SILENT_REQUESTS = 2
#: health causes
LINK_CAUSE = "link"
UNIT_CAUSE = "unit"


class Link:
    """The state of one bus's connection (see the module doc)."""

    def __init__(self, host: DriverHost, bus: str, name: str, where: str, health: Health,
                 points: Mapping[str, Point], per_unit: bool) -> None:
        self._host = host
        self.bus = bus
        #: ``modbus-tcp bus mb`` - the start of every reason
        self.name = name
        #: ``127.0.0.1:502``, ``/dev/ttyUSB0``
        self.where = where
        self._health = health
        self._points = points
        self._per_unit = per_unit
        self.connected = False
        self.connects = 0
        self._answered = True
        self._units_answered: set[int] = set()
        self._silent = 0
        #: set once stop began: the first unanswered request ends the link
        self.stopping = False

    def up(self) -> None:
        """A connection was made (a port opened): counted, not yet health. On a serial line
        every device fails (cause ``link``) until its unit answers a request."""
        self.connected = True
        self.connects += 1
        if self.connects > 1:
            self._host.stat(self.bus, "reconnects")
        self._answered = False
        self._units_answered = set()
        self._silent = 0
        if self._per_unit:
            for device, p in self._points.items():
                self._health.fail(device, LINK_CAUSE, f"{self.name}: {self.where} is open, unit "
                                                      f"{p.unit} has not answered a request yet")

    def down(self, why: str) -> None:
        """The connection is lost or cannot be made: every device fails (cause ``link``); a
        loss of a connection that was up is a ``disconnected`` error."""
        was, self.connected = self.connected, False
        reason = f"{self.name}: {why}"
        for device in self._points:
            self._health.fail(device, LINK_CAUSE, reason)
        if was:
            self._host.error(self.bus, "disconnected", reason)

    def answered(self, unit: int) -> None:
        """Something came back from ``unit`` (data, an exception, even a garbled answer): the
        connection carries answers - on RTU for that unit's devices."""
        self._silent = 0
        if self._answered:
            return
        if self._per_unit:
            if unit in self._units_answered:
                return
            self._units_answered.add(unit)
            for device, p in self._points.items():
                if p.unit == unit:
                    self._health.clear(device, LINK_CAUSE, f"{self.name}: unit {unit} on "
                                                           f"{self.where} answered")
            self._answered = self._units_answered >= {p.unit for p in self._points.values()}
            return
        self._answered = True
        for device in self._points:
            self._health.clear(device, LINK_CAUSE, f"{self.name}: a request to {self.where} "
                                                   f"was answered")

    def unanswered(self) -> str:
        """A request got nothing back: why that loses the connection, or "" if it does not (a
        serial line's silence is its unit's; see the module doc)."""
        if self._per_unit:
            return ""
        self._silent += 1
        if not self._answered:
            return f"{self.where} accepted the connection but sent no response"
        if self.stopping:
            return f"{self.where} did not answer while the bus stops"
        if self._silent >= SILENT_REQUESTS:
            return f"{self.where} answered none of the last {self._silent} requests"
        return ""


class Units:
    """The units of one bus that can stop answering one by one (see the module doc)."""

    def __init__(self, name: str, health: Health, points: Mapping[str, Point], cap: int,
                 first: int, units: Iterable[int], guard: float) -> None:
        self.name = name
        self._health = health
        self._points = points
        self.backoff = UnitBackoff(cap, first, units)
        #: seconds a unit that missed a request is held quiet before a different request
        self.guard_time = guard
        self._quiet: dict[int, tuple[float, bytes]] = {}

    def due(self, unit: int) -> bool:
        """Whether a request to ``unit`` goes out now (a dead unit sits out some turns)."""
        return self.backoff.due(unit)

    def dead(self, unit: int) -> bool:
        """True while ``unit``'s last request went unanswered."""
        return self.backoff.dead(unit)

    def epoch(self, unit: int) -> int:
        """How many times ``unit`` stopped answering (read on any thread)."""
        return self.backoff.epoch(unit)

    def silent(self, unit: int, where: str, what: str, now: float, request: bytes) -> None:
        """``unit`` did not answer the request ``where`` (its bytes ``request``, sent until
        ``now``): every device of the unit fails (cause ``unit``), its later requests are
        thinned out and held behind the guard, and writes queued for it are not sent."""
        self.backoff.silent(unit)
        self._quiet[unit] = (now + self.guard_time, request)
        for device, q in self._points.items():
            if q.unit == unit:
                self._health.fail(device, UNIT_CAUSE, f"{where} (device {device}): {what}")

    def back(self, unit: int) -> None:
        """``unit`` answered: if it had stopped, its devices lose the cause ``unit``."""
        self._quiet.pop(unit, None)
        if not self.backoff.answered(unit):
            return
        for device, q in self._points.items():
            if q.unit == unit:
                self._health.clear(device, UNIT_CAUSE, f"{self.name}: unit {unit} answers again")

    def guard(self, unit: int, request: bytes, now: float) -> float:
        """Until when the line must stay quiet before ``request`` goes to ``unit``: after its
        missed request, one ``timeout`` for its late answer to come (and be thrown away) -
        unless this is that same request again, whose late answer would be its own. 0: no
        wait."""
        held = self._quiet.get(unit)
        if held is None:
            return 0.0
        until, missed = held
        if now >= until:
            del self._quiet[unit]
            return 0.0
        return 0.0 if missed == request else until
