"""link - the supervision of a Modbus bus's link and of its units: what fails the devices,
what is a connection-level cause, when a connection is healthy, and the backoff of units that
stop answering. No I/O: the engines (:mod:`drivers.modbus.engine`) tell it what happened.

Connection-level causes (:class:`Link`): a connection that cannot be made, one the peer closes
or resets, a byte stream that is no Modbus any more, and - on ``modbus-tcp`` - requests that go
unanswered with nothing at all coming back on the connection: :data:`SILENT_REQUESTS` different
requests in a row (fewer on a bus that makes fewer), also right after a connect (a server that
accepts connections but does not answer: frozen, SIGSTOPped). A late answer shows the peer
there (:meth:`Link.alive`). One request that always times out while the others
are answered is that request's devices' failure, not the connection's: the connection is kept.
A connect is not health: the devices recover (cause ``link``) once a request is answered - on
``modbus-rtu`` the devices of the unit that answered.

Units (:class:`Units`, ``modbus-rtu`` and a ``modbus-tcp`` gateway): a unit that does not answer
(after the bus's ``retries``) fails every device of that unit (cause ``unit``), is backed off
(:class:`drivers.codecs.modbus.UnitBackoff`) so the live units keep their rate, and - RTU -
is held quiet for one ``timeout`` before a different request goes to it (:meth:`Units.guard`),
so that its late answer is taken for nothing: RTU answers carry no transaction id. A request
right after another unit's silence gets one try more before its own unit counts as silent
(:meth:`Units.extra_try`: slaves may still be deaf, waiting for the silent unit's answer).
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
                 points: Mapping[str, Point], per_unit: bool, distinct: int) -> None:
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
        #: unanswered requests in a row that lose the connection: SILENT_REQUESTS, or fewer
        #: on a bus that makes fewer different requests (nothing else could answer)
        self.silent_limit = max(1, min(SILENT_REQUESTS, distinct))
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
        if self._per_unit:       # a broadcast's devices: nothing ever answers for them
            for device, p in self._points.items():
                if p.broadcast:
                    self._health.clear(device, LINK_CAUSE, f"{self.name}: {self.where} is open")
                    continue
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
            self._answered = self._units_answered >= {p.unit for p in self._points.values()
                                                      if not p.broadcast}
            return
        self._answered = True
        for device in self._points:
            self._health.clear(device, LINK_CAUSE, f"{self.name}: a request to {self.where} "
                                                   f"was answered")

    @property
    def proven(self) -> bool:
        """True once a request was answered since the last connect."""
        return self._answered

    def alive(self) -> None:
        """Bytes came back on the connection that answer no outstanding request (a late
        answer): the peer is there, the silence streak ends."""
        self._silent = 0

    def unanswered(self) -> str:
        """A request got nothing back: why that loses the connection, or "" if it does not (a
        serial line's silence is its unit's; see the module doc)."""
        if self._per_unit:
            return ""
        self._silent += 1
        if self.stopping:
            return f"{self.where} did not answer while the bus stops"
        if self._silent < self.silent_limit:
            return ""
        if not self._answered:
            return f"{self.where} accepted the connection but sent no response"
        return f"{self.where} answered none of the last {self._silent} requests"


class Units:
    """The units of one bus that can stop answering one by one (see the module doc)."""

    def __init__(self, name: str, health: Health, points: Mapping[str, Point], cap: int,
                 first: int, units: Iterable[int], guard: float, line_guard: float = 0.0
                 ) -> None:
        self.name = name
        self._health = health
        self._points = points
        self.backoff = UnitBackoff(cap, first, units)
        #: seconds a unit that missed a request is held quiet before a different request
        self.guard_time = guard
        #: seconds the whole line is held quiet after a request nobody answered (its timeout
        #: passed): the other slaves may still be waiting for that answer
        self.line_guard = line_guard
        self._line_quiet_until = 0.0
        self._quiet: dict[int, tuple[float, bytes]] = {}
        #: the unit whose request went unanswered last, while nothing was answered since
        self._line_silent: int | None = None

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
        self._line_silent = unit
        self._line_quiet_until = now + self.line_guard
        self._quiet[unit] = (now + self.guard_time, request)
        for device, q in self._points.items():
            if q.unit == unit:
                self._health.fail(device, UNIT_CAUSE, f"{where} (device {device}): {what}")

    def back(self, unit: int) -> None:
        """``unit`` answered: if it had stopped, its devices lose the cause ``unit``."""
        self._quiet.pop(unit, None)
        self._line_silent = None
        if not self.backoff.answered(unit):
            return
        for device, q in self._points.items():
            if q.unit == unit:
                self._health.clear(device, UNIT_CAUSE, f"{self.name}: unit {unit} answers again")

    def extra_try(self, unit: int) -> bool:
        """Whether a request to ``unit`` gets one try beyond the bus's ``retries``: the last
        request on the line went unanswered by another unit, and slaves may still be waiting
        for that unit's answer (a stock libmodbus slave ignores the line for its response
        timeout, 0.5 s): a silence now would be theirs, not this unit's death."""
        return self._line_silent is not None and self._line_silent != unit

    def guard(self, unit: int, request: bytes, now: float) -> float:
        """Until when the line must stay quiet before ``request`` goes to ``unit``: after its
        missed request, one ``timeout`` for its late answer to come (and be thrown away) -
        unless this is that same request again, whose late answer would be its own - and after
        any unit's silence the line's guard (:attr:`line_guard`). 0: no wait."""
        line = self._line_quiet_until if now < self._line_quiet_until else 0.0
        held = self._quiet.get(unit)
        if held is None:
            return line
        until, missed = held
        if now >= until:
            del self._quiet[unit]
            return line
        return max(line, 0.0 if missed == request else until)
