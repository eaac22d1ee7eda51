"""executor - the NBS cyclic executor: every level's G, M and H module stepped every cycle.

This is the baseline chcos is compared against (thesis 3.8, 4.1, 4.3.1): one sensory (G),
world-model (M) and command (H) module per level, *all* executed every ``period`` seconds
(28 ms in the NBS design) whether or not their inputs changed, exchanging data through common
memory. Each cycle runs the levels bottom-up and, inside a level, G then M then H; a module
sees what earlier modules wrote in the same cycle and what later ones wrote the cycle before
(so a command travels down one level per cycle and a report is read fresh by the level above).

Narrow interfaces, supplied by the chcos kernel and its Devtab (or by tests):

* :class:`~chcos.apps.nbs.scheduling.Scheduler` - ``now()`` and ``every(period, fn)`` on
  virtual or real time; :class:`~chcos.apps.nbs.scheduling.VirtualScheduler` is a
  deterministic one (virtual clock and timer heap). Both are in
  :mod:`chcos.apps.nbs.scheduling`.
* :class:`DeviceIO` - ``read(name) -> value | None`` for sensors, ``write(name, value)`` for
  actuators, and optionally ``arrived(name) -> time | None``, when the current value of a
  sensor became visible (the Devtab's time stamp). Without it, a sample is "new" when its
  value differs from the last one polled, and it counts as visible when it was polled.

Common-memory conventions for level ``n`` (see :class:`CommonMemory`): ``cmd/n`` the
:class:`Order` for H<n>, ``report/n`` the :class:`Report` of H<n>, ``facts/n`` and
``values/n`` the fact and value maps G<n>/M<n> give H<n>, ``sensory/n`` what G<n> passes up.

Measurements: executions per module (``"G1"``, ``"M1"``, ``"H1"``, ...), cycles run, and the
reaction latency between a sensor value becoming visible and the first write, after it was
polled, to an actuator that the ``reactions`` map says reacts to that sensor.

Errors: a module that raises stops the cycle and the exception propagates to the scheduler;
:class:`~chcos.errors.KernelError` for misuse (bad period, starting twice, unknown level).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass

from chcos.apps.nbs.scheduling import Cancellable, Scheduler
from chcos.apps.nbs.statetable import Call, Facts, Machine, StateTable
from chcos.errors import KernelError

__all__ = [
    "DEFAULT_PERIOD",
    "CommonMemory",
    "DeviceIO",
    "Latency",
    "Level",
    "LevelContext",
    "Module",
    "NbsExecutor",
    "Order",
    "Report",
    "Sample",
    "Scheduler",
    "TableH",
]

DEFAULT_PERIOD = 0.028
"""The NBS cycle: every FSM samples its inputs and computes its outputs once per 28 ms."""



# --------------------------------------------------------------------------- devices, memory


@dataclass(frozen=True)
class DeviceIO:
    """How the executor reaches devices (the kernel's Devtab provides these callables)."""

    read: Callable[[str], object | None]
    write: Callable[[str, object], None]
    arrived: Callable[[str], float | None] | None = None


@dataclass(frozen=True)
class Sample:
    """A new sensor value returned by :meth:`LevelContext.poll`, with when it became visible."""

    sensor: str
    value: object
    visible: float


@dataclass(frozen=True)
class Latency:
    """One measured reaction: a sensor value visible at ``visible``, the reacting actuator
    written at ``written``."""

    sensor: str
    actuator: str
    visible: float
    written: float

    @property
    def seconds(self) -> float:
        """The reaction latency."""
        return self.written - self.visible


@dataclass(frozen=True)
class Order:
    """A command in common memory for an H module; ``serial`` changes with each new activation."""

    call: Call
    serial: int


@dataclass(frozen=True)
class Report:
    """An H module's report in common memory, tagged with the serial of the order it answers."""

    text: str | None
    serial: int


class CommonMemory:
    """The NBS common memory: named slots every module may read and write.

    Each slot remembers when it was last written. Key helpers name the per-level slots.
    """

    def __init__(self, clock: Callable[[], float]) -> None:
        self._clock = clock
        self._slots: dict[str, object] = {}
        self._stamps: dict[str, float] = {}

    @staticmethod
    def cmd(level: int) -> str:
        """Slot of the order for H<level>."""
        return f"cmd/{level}"

    @staticmethod
    def report(level: int) -> str:
        """Slot of H<level>'s report up."""
        return f"report/{level}"

    @staticmethod
    def facts(level: int) -> str:
        """Slot of the fact map G<level>/M<level> give H<level>."""
        return f"facts/{level}"

    @staticmethod
    def values(level: int) -> str:
        """Slot of the value map G<level>/M<level> give H<level>."""
        return f"values/{level}"

    @staticmethod
    def sensory(level: int) -> str:
        """Slot of what G<level> passes up to G<level+1>."""
        return f"sensory/{level}"

    def put(self, key: str, value: object) -> None:
        """Write a slot."""
        self._slots[key] = value
        self._stamps[key] = self._clock()

    def get(self, key: str, default: object = None) -> object:
        """Read a slot (``default`` if never written)."""
        return self._slots.get(key, default)

    def written_at(self, key: str) -> float | None:
        """When a slot was last written (None if never)."""
        return self._stamps.get(key)

    def __contains__(self, key: object) -> bool:
        return key in self._slots


# --------------------------------------------------------------------------- levels


class LevelContext:
    """What a module sees while it runs: its level, the clock, common memory and devices.

    ``facts`` and ``values`` are this level's mutable maps for H (G and M fill them).
    """

    def __init__(self, executor: NbsExecutor, level: int) -> None:
        self._ex = executor
        self.level = level
        self.mem = executor.memory
        self.facts: dict[str, bool | Callable[[], bool]] = {}
        self.values: dict[str, object] = {}
        self.mem.put(CommonMemory.facts(level), self.facts)
        self.mem.put(CommonMemory.values(level), self.values)

    @property
    def now(self) -> float:
        """Current time from the scheduler."""
        return self._ex.scheduler.now()

    @property
    def top(self) -> bool:
        """True for the highest level."""
        return self.level == len(self._ex.levels)

    def read(self, sensor: str) -> object | None:
        """Current value of a sensor (None when it has none), without marking it polled."""
        return self._ex.io.read(sensor)

    def poll(self, sensor: str) -> Sample | None:
        """The sensor's value if it is new since this executor last polled it, else None."""
        return self._ex._poll(sensor)

    def write(self, actuator: str, value: object) -> None:
        """Write an actuator and record reaction latencies for pending sensor values."""
        self._ex._write(actuator, value)


Module = Callable[[LevelContext], None]
"""A G, M or H module: called once per cycle with its level's context."""


@dataclass(frozen=True)
class Level:
    """One level of the hierarchy: its sensory (G), world-model (M) and command (H) modules."""

    g: Module
    m: Module
    h: Module


class TableH:
    """An H module run from a state table (Appendix 1), as a :data:`Module`.

    Each cycle: accept a new order from ``cmd/n`` (a new serial starts the command), step the
    machine on the level's facts and values and on the report of H<n-1> (shown as None until
    H<n-1> answers an order of the current activation), write a new or standing lower order
    to ``cmd/n-1`` and the report to ``report/n``. At level 1 there is no H below: the lower
    report is always None (level-0 reports such as "arrived" come from G1/M1 as facts) and
    ``actuate(call, ctx)`` is called for every lower command issued, every cycle it is issued
    (an NBS command is executed each cycle it stands); the order is still put in ``cmd/0`` so
    it can be inspected. Raises StateTableError (from the machine) when the table cannot run.
    """

    def __init__(
        self,
        table: StateTable,
        actuate: Callable[[Call, LevelContext], None] | None = None,
    ) -> None:
        self.machine = Machine(table)
        self.actuate = actuate
        self._running: int | None = None
        self._issued: int | None = None
        self._serials = itertools.count(1)

    def __call__(self, ctx: LevelContext) -> None:
        n, mem = ctx.level, ctx.mem
        order = mem.get(CommonMemory.cmd(n))
        if isinstance(order, Order) and order.serial != self._running:
            self.machine.start(order.call.name, order.call.args, ctx.values)
            self._running = order.serial
            self._issued = None
        report: str | None = None
        below = mem.get(CommonMemory.report(n - 1))
        if isinstance(below, Report) and self._issued is not None and below.serial == self._issued:
            report = below.text
        facts: Facts = ctx.facts
        step = self.machine.step(facts, report, ctx.values)
        if step.lower is not None:
            if step.lower_new or self._issued is None:
                self._issued = next(self._serials)
            mem.put(CommonMemory.cmd(n - 1), Order(step.lower, self._issued))
            if self.actuate is not None:
                self.actuate(step.lower, ctx)
        if self._running is not None:
            mem.put(CommonMemory.report(n), Report(step.report, self._running))


# --------------------------------------------------------------------------- executor


class NbsExecutor:
    """Runs a cross-coupled hierarchy: every module of every level, every cycle.

    ``levels[0]`` is level 1. ``reactions`` maps an actuator to the sensors it reacts to (for
    latency measurement). Raises KernelError for an empty hierarchy or a period <= 0.
    """

    def __init__(
        self,
        levels: Sequence[Level],
        io: DeviceIO,
        scheduler: Scheduler,
        *,
        period: float = DEFAULT_PERIOD,
        reactions: Mapping[str, Iterable[str]] | None = None,
    ) -> None:
        if not levels:
            raise KernelError("NbsExecutor: a hierarchy needs at least one level")
        if not period > 0:
            raise KernelError(f"NbsExecutor: period must be > 0 s, got {period!r}")
        self.levels = tuple(levels)
        self.io = io
        self.scheduler = scheduler
        self.period = period
        self.memory = CommonMemory(scheduler.now)
        self.cycles = 0
        self.latencies: list[Latency] = []
        self._counts = {f"{k}{n}": 0 for n in range(1, len(levels) + 1) for k in "GMH"}
        self._contexts = [LevelContext(self, n) for n in range(1, len(levels) + 1)]
        self._reacts_to: dict[str, set[str]] = {}
        for actuator, sensors in (reactions or {}).items():
            for sensor in sensors:
                self._reacts_to.setdefault(sensor, set()).add(actuator)
        self._pending: dict[tuple[str, str], float] = {}
        self._last_seen: dict[str, tuple[object, float | None]] = {}
        self._timer: Cancellable | None = None
        self._serials = itertools.count(1)
        self.writes = 0

    # -- running
    def start(self) -> None:
        """Arm the cycle timer on the scheduler. Raises KernelError if already started."""
        if self._timer is not None:
            raise KernelError("NbsExecutor.start: already started")
        self._timer = self.scheduler.every(self.period, self.cycle)

    def stop(self) -> None:
        """Disarm the cycle timer (a stopped executor can be started again)."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def cycle(self) -> None:
        """Run one cycle: levels bottom-up, G then M then H in each."""
        self.cycles += 1
        for ctx, level in zip(self._contexts, self.levels, strict=True):
            n = ctx.level
            level.g(ctx)
            self._counts[f"G{n}"] += 1
            level.m(ctx)
            self._counts[f"M{n}"] += 1
            level.h(ctx)
            self._counts[f"H{n}"] += 1

    # -- operator
    def command(self, name: str, *args: object) -> int:
        """Give the top level a command (as the level above it would); returns its serial."""
        serial = next(self._serials)
        self.memory.put(CommonMemory.cmd(len(self.levels)), Order(Call(name, args), serial))
        return serial

    def report(self, level: int | None = None) -> str | None:
        """The standing report of H<level> (default: the top level)."""
        n = len(self.levels) if level is None else level
        if not 1 <= n <= len(self.levels):
            raise KernelError(f"NbsExecutor.report: no level {n} (levels 1..{len(self.levels)})")
        rep = self.memory.get(CommonMemory.report(n))
        return rep.text if isinstance(rep, Report) else None

    def context(self, level: int) -> LevelContext:
        """The context of level ``level`` (1-based). Raises KernelError for an unknown level."""
        if not 1 <= level <= len(self.levels):
            raise KernelError(
                f"NbsExecutor.context: no level {level} (levels 1..{len(self.levels)})"
            )
        return self._contexts[level - 1]

    # -- measurements
    @property
    def counts(self) -> dict[str, int]:
        """Executions per module, keyed ``"G1"``, ``"M1"``, ``"H1"``, ... (a copy)."""
        return dict(self._counts)

    @property
    def executions(self) -> int:
        """Total module executions."""
        return sum(self._counts.values())

    # -- device plumbing
    def _poll(self, sensor: str) -> Sample | None:
        value = self.io.read(sensor)
        if value is None:
            return None
        stamp = self.io.arrived(sensor) if self.io.arrived is not None else None
        last = self._last_seen.get(sensor)
        if last is not None:
            if stamp is not None and last[1] == stamp:
                return None
            if stamp is None and last[0] == value:
                return None
        self._last_seen[sensor] = (value, stamp)
        visible = stamp if stamp is not None else self.scheduler.now()
        for actuator in self._reacts_to.get(sensor, ()):
            self._pending.setdefault((sensor, actuator), visible)
        return Sample(sensor, value, visible)

    def _write(self, actuator: str, value: object) -> None:
        self.io.write(actuator, value)
        self.writes += 1
        now = self.scheduler.now()
        for key in [k for k in self._pending if k[1] == actuator]:
            self.latencies.append(Latency(key[0], actuator, self._pending.pop(key), now))
