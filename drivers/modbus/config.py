"""config - what a Modbus driver makes of its typed options and devices, once, at construction:
the points of its devices, the planned reads of each poll period (their request bytes built
once), the units no poll reads (probed instead), the units of the line and how a dead one is
backed off. The map's keys themselves are :mod:`drivers.codecs.modbus_options`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from chcos.devices.spec import DeviceSpec
from drivers.codecs.modbus import (
    BROADCAST,
    LineTiming,
    Point,
    ReadRequest,
    plan_reads,
)
from drivers.codecs.modbus_options import (
    ModbusOptions,
    RtuOptions,
    ServerKind,
    TcpOptions,
    WatchdogOptions,
    address_of,
    point_of,
)
from drivers.modbus.transactions import Request, read_request

DEFAULT_DEAD_UNIT_BACKOFF = 8   # poll periods, at least, between two tries of a dead unit
#: a dead unit's tries take at most 1/DEAD_UNIT_SHARE of an RTU line's time
DEAD_UNIT_SHARE = 20


@dataclass(frozen=True)
class PlannedRead:
    """One read of a poll and its request, built once."""

    read: ReadRequest
    request: Request


def planned(r: ReadRequest) -> PlannedRead:
    """``r`` with its request bytes."""
    return PlannedRead(r, read_request(r.unit, r.table, r.address, r.count, r.describe()))


def try_cost(o: ModbusOptions) -> float:
    """Seconds one try of a dead unit holds the line: ``timeout`` x (``retries`` + 1), and on
    a serial line the quiet kept after it (``line_guard``)."""
    guard = o.guard_after_silence() if isinstance(o, RtuOptions) else 0.0
    return o.timeout * (o.retries + 1) + guard


def share_turns(cost: float, period: float) -> int:
    """Poll periods per try of a dead unit that keep its tries (``cost`` s each, the time such
    a try holds the line) within a twentieth of the line's time."""
    return max(1, math.ceil((DEAD_UNIT_SHARE - 1) * cost / period - 1e-9))


def dead_unit_backoff(o: ModbusOptions) -> int:
    """The most poll periods between two tries of a unit that stopped answering: the bus's
    ``dead_unit_backoff``, else 8 - but never so few that the dead unit's tries take more than
    a twentieth of the line's time (the live units keep 95 % of their polls)."""
    if isinstance(o, RtuOptions) and o.dead_unit_backoff is not None:
        return o.dead_unit_backoff
    return max(DEFAULT_DEAD_UNIT_BACKOFF, share_turns(try_cost(o), o.sensor_period()))


def dead_unit_first(o: ModbusOptions) -> int:
    """The poll periods between the first two tries of a unit that stopped answering (later
    gaps double up to :func:`dead_unit_backoff`): as many as keep its tries within a twentieth
    of the line's time from its first miss on, so the live units keep their rate while the
    unit is backed off too; 1 (the next poll) when a try costs little beside the poll period.
    Never more than the cap."""
    return min(dead_unit_backoff(o), share_turns(try_cost(o), o.sensor_period()))


@dataclass(frozen=True)
class BusPlan:
    """What a Modbus driver does on its bus (see the module doc)."""

    options: TcpOptions | RtuOptions
    #: every device's point
    points: Mapping[str, Point]
    #: the reads of each poll period
    polls: Mapping[float, tuple[PlannedRead, ...]]
    #: the first actuator of each unit no poll reads (broadcast excepted): its liveness probe
    probed: tuple[Point, ...]
    #: the units of the bus that answer (broadcast excepted), the watchdog's too
    units: frozenset[int]
    #: TCP: one device or a gateway to units; None on a serial line
    server: ServerKind | None
    #: the serial line's timing (None on TCP)
    line: LineTiming | None

    @property
    def watchdog(self) -> WatchdogOptions | None:
        """The bus's watchdog register."""
        return self.options.watchdog

    @property
    def per_unit(self) -> bool:
        """True when units fail one by one (a serial line, a TCP gateway)."""
        return self.server != "device"

    @property
    def serial(self) -> bool:
        """True on a serial line."""
        return self.line is not None


def sensor_period(o: ModbusOptions, device: DeviceSpec) -> float:
    """Seconds between two polls of a sensor: its own ``poll_period``, else the bus's."""
    own = address_of(device).poll_period
    return own if own is not None else o.sensor_period()


def build_plan(options: TcpOptions | RtuOptions, devices: Sequence[DeviceSpec]) -> BusPlan:
    """The plan of a bus with ``options`` and valid ``devices``."""
    points = {d.name: point_of(d) for d in devices}
    by_period: dict[float, list[Point]] = {}
    for d in devices:
        if d.direction == "sensor":
            by_period.setdefault(sensor_period(options, d), []).append(points[d.name])
    polls = {period: tuple(planned(r) for r in plan_reads(pts))
             for period, pts in by_period.items()}
    read = {r.read.unit for plan in polls.values() for r in plan}
    probed: list[Point] = []
    for p in points.values():      # the first actuator of each unit no poll reads
        if p.unit not in read and not p.broadcast:
            read.add(p.unit)
            probed.append(p)
    units = {p.unit for p in points.values() if not p.broadcast}
    if options.watchdog is not None and options.watchdog.unit != BROADCAST:
        units.add(options.watchdog.unit)
    if isinstance(options, TcpOptions):
        server: ServerKind | None = options.server_kind(units)
        line = None
    else:
        server = None
        line = LineTiming(options.baudrate, options.bytesize, options.parity, options.stopbits)
    return BusPlan(options, points, polls, tuple(probed), frozenset(units), server, line)
