"""load - the load of thesis 6.4 and how its reactions are timed, for :mod:`chcos.apps.bench.fig66`.

:class:`Load` feeds S1, S2, S3 and ``testfile`` (the lines of the figure 6.5 example's test file,
replayed as a sensor) into a System's Devtab at ``rate_hz`` each, every input at its own seeded
phase, optionally with a seeded random delay per event (``jitter``) so that events fall at
random phases of the NBS cycle - from kernel timers (virtual or real time) or from a thread, as
a driver would. :class:`ReactionProbe` times each sensor event to the actuator command it
causes, through Devtab's ``on_write`` hook, the same for the CHC and the NBS system.
:func:`expected_rates` derives the executions a load implies from a topology (nothing is taken
from the thesis' figures). Errors: :class:`~chcos.errors.ConfigError` for a bad load or
topology.
"""

from __future__ import annotations

import random
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from typing import Any

from chcos.apps import fig65
from chcos.apps.fig65.common import FAN_IN
from chcos.apps.nbs import fig67
from chcos.errors import ConfigError
from chcos.system.embedded import System

INPUTS: tuple[str, ...] = fig67.SENSORS
"""The inputs of figure 6.6: S1, S2, S3 and the test file (as a sensor named ``testfile``)."""
INPUT_RATE_HZ = fig67.INPUT_RATE_HZ
"""Each input delivers a value every 100 ms (thesis 6.4)."""
REACTIONS: dict[str, tuple[str, ...]] = dict(fig67.REACTIONS)
"""Which inputs each actuator reacts to: M1 to S1 and S2 (task A1), M2 to S3 (task A2)."""

def expected_rates(topology: Mapping[str, Sequence[str]], input_rates: Mapping[str, Fraction],
                   fan_in: int = FAN_IN) -> dict[str, Fraction]:
    """Executions per second of every task that the load implies, exactly.

    Every sensory message makes its reader execute once; a task that executes ``r`` times a
    second sends ``r / fan_in`` messages a second upward (five inputs make one output). An input
    (sensor) ``s`` sends ``input_rates[s]``. Raises ConfigError for an unknown source, a cycle
    or a fan-in below 1.
    """
    if fan_in < 1:
        raise ConfigError(f"fan_in must be >= 1, got {fan_in}")
    rates: dict[str, Fraction] = {}

    def out_rate(src: str, stack: tuple[str, ...]) -> Fraction:
        if src in input_rates:
            return Fraction(input_rates[src])
        if src not in topology:
            raise ConfigError(f"source {src!r} is neither an input nor a task of the topology")
        return in_rate(src, stack) / fan_in

    def in_rate(task: str, stack: tuple[str, ...]) -> Fraction:
        if task in stack:
            raise ConfigError(f"topology has a cycle through {task}")
        if task not in rates:
            rates[task] = sum((out_rate(s, (*stack, task)) for s in topology[task]), Fraction(0))
        return rates[task]

    for task in topology:
        in_rate(task, ())
    return {t: rates[t] for t in topology}


def _testfile_values() -> list[float]:
    lines = (fig65.HERE / "testfile").read_text(encoding="utf-8").splitlines()
    return [float(ln) for ln in lines if ln.strip() and not ln.startswith("#")]


@dataclass
class Load:
    """The thesis' load: every input a value every ``1/rate_hz`` s at its own phase.

    Input ``i`` fires at ``start + phase[i] + k / rate_hz + u``, ``u`` uniform in
    ``[0, jitter)`` drawn per event from a generator seeded with ``seed`` (so a run is
    reproducible; ``jitter`` must be below one period so an input's events keep their order).
    Phases are drawn from the same seed, uniform over one period. Values: S1..S3 waveforms,
    the test file's lines in a loop. Raises ConfigError for a rate <= 0 or a bad jitter.
    """

    seed: int = 1
    rate_hz: float = INPUT_RATE_HZ
    jitter: float = 0.0
    inputs: tuple[str, ...] = INPUTS
    phases: dict[str, float] = field(default_factory=dict)
    injected: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ConfigError(f"load: rate must be > 0 Hz, got {self.rate_hz!r}")
        if not 0 <= self.jitter < 1.0 / self.rate_hz:
            raise ConfigError(f"load: jitter must be in [0, one period), got {self.jitter!r}")
        rng = random.Random(self.seed)
        period = 1.0 / self.rate_hz
        if not self.phases:
            self.phases = {s: rng.uniform(0.0, period) for s in self.inputs}
        self.injected = dict.fromkeys(self.inputs, 0)
        self._rngs = {s: random.Random(f"{self.seed}/{s}") for s in self.inputs}
        self._file = _testfile_values()

    @property
    def period(self) -> float:
        """Seconds between two values of one input."""
        return 1.0 / self.rate_hz

    def value(self, sensor: str, k: int) -> float:
        """The ``k``-th value of ``sensor``."""
        if sensor == "testfile":
            return self._file[k % len(self._file)]
        return 50.0 + 40.0 * ((k * 7 + len(sensor)) % 20 - 10) / 10.0

    def event_time(self, sensor: str, k: int, start: float) -> float:
        """When the ``k``-th event of ``sensor`` fires (draws its jitter: call once per k, in
        order)."""
        u = self._rngs[sensor].uniform(0.0, self.jitter) if self.jitter else 0.0
        return start + self.phases[sensor] + k * self.period + u

    def schedule(self, system: System, probe: ReactionProbe | None = None,
                 start: float | None = None) -> None:
        """Feed ``system`` from kernel timers (virtual or real time) from ``start`` (default
        now) on: each event stamps ``probe`` and injects into the Devtab as an interrupt."""
        kernel = system.kernel
        t0 = kernel.clock.now() if start is None else start
        devtab = system.devtab

        def chain(sensor: str) -> None:
            k = 0

            def fire() -> None:
                nonlocal k
                if probe is not None:
                    probe.event(sensor, probe.clock())
                devtab.inject(sensor, self.value(sensor, k))
                self.injected[sensor] += 1
                k += 1
                kernel.call_at(self.event_time(sensor, k, t0), fire)

            kernel.call_at(self.event_time(sensor, 0, t0), fire)

        for s in self.inputs:
            chain(s)

    def feed_thread(self, system: System, probe: ReactionProbe, seconds: float,
                    stop: threading.Event, after: Callable[[], None] | None = None
                    ) -> threading.Thread:
        """A started thread that feeds ``system`` on real time for ``seconds`` (as a driver
        thread does: each value is stamped with ``time.perf_counter()`` in ``probe`` and handed
        over with the thread-safe Devtab.inject); ``after()`` is called after each event."""
        def run() -> None:
            t0 = time.perf_counter() + 0.05
            nxt = {s: (self.event_time(s, 0, t0), 0) for s in self.inputs}
            end = t0 + seconds
            while not stop.is_set():
                sensor = min(nxt, key=lambda s: nxt[s][0])
                when, k = nxt[sensor]
                if when >= end:
                    return
                delay = when - time.perf_counter()
                if delay > 0 and stop.wait(delay):
                    return
                probe.event(sensor, time.perf_counter())
                system.devtab.inject(sensor, self.value(sensor, k))
                self.injected[sensor] += 1
                nxt[sensor] = (self.event_time(sensor, k + 1, t0), k + 1)
                if after is not None:
                    after()

        th = threading.Thread(target=run, name="fig66-feed", daemon=True)
        th.start()
        return th


class ReactionProbe:
    """Times each sensor event to the first later command of an actuator that reacts to it.

    ``event(sensor, t)`` is called when a value is handed to the system; the Devtab ``on_write``
    hook (:meth:`written`, installed by :meth:`install`) closes every pending event of the
    sensors the written actuator reacts to, with ``clock()`` as the write time (the kernel clock
    on virtual time, ``time.perf_counter`` on real time). Thread-safe.
    """

    def __init__(self, clock: Callable[[], float],
                 reactions: Mapping[str, Iterable[str]] = REACTIONS) -> None:
        self.clock = clock
        self._reacts: dict[str, tuple[str, ...]] = {}
        for actuator, sensors in reactions.items():
            for s in sensors:
                self._reacts[s] = (*self._reacts.get(s, ()), actuator)
        self._pending: dict[tuple[str, str], float] = {}
        self._lock = threading.Lock()
        self.samples: list[float] = []
        self.active = True

    def event(self, sensor: str, t: float) -> None:
        """A value of ``sensor`` was handed over at ``t``."""
        if not self.active:
            return
        with self._lock:
            for a in self._reacts.get(sensor, ()):
                self._pending.setdefault((sensor, a), t)

    def written(self, device: str, value: Any) -> None:
        """Devtab hook: actuator ``device`` was commanded now."""
        if not self.active:
            return
        now = self.clock()
        with self._lock:
            for key in [k for k in self._pending if k[1] == device]:
                self.samples.append(now - self._pending.pop(key))

    def install(self, system: System) -> None:
        """Listen to ``system``'s Devtab writes."""
        system.devtab.on_write.append(self.written)
