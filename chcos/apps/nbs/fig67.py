"""fig67 - the system of thesis figures 6.6/6.7 (section 6.4) run as an NBS hierarchy.

Section 6.4 compares CHC with the cross-coupled hierarchy on the figure 6.5 system without the
terminal task A4: A1+A2+A3 become H1/G1/M1, B1+B2 become H2/G2/M2, C1 becomes H3/G3/M3. Load
assumption: sensors S1, S2, S3 and the test file each deliver a value every 100 ms (10 Hz),
and five inputs at level n make one sensory output to level n+1.

Here the nine modules really run on an :class:`~chcos.apps.nbs.executor.NbsExecutor`:

* G1 polls the four inputs every cycle; each new value is one input, every ``fan_in`` inputs
  one output to G2. G2 and G3 count what the level below passed up the same way.
* M<n> keeps the level's world model (last input values, inputs seen) for H<n>.
* H1 reacts like A1 and A2: a new S1 or S2 value drives actuator M1, a new S3 value drives
  actuator M2 (device names as in figure 6.5; not to be confused with the world-model
  modules M1..M3). H2 and H3 run the Appendix-1 tables H2 and H3, idle (no command): they
  still execute every cycle, which is the point of the comparison.

:func:`run_fig67` runs it for a span of (virtual or real) time and returns what happened:
module executions, inputs produced/seen/lost, outputs per level, reaction latencies. Nothing
is computed from the thesis' figures (720/s, 51/s); everything is counted.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from chcos.apps.nbs.executor import (
    DEFAULT_PERIOD,
    CommonMemory,
    DeviceIO,
    Latency,
    Level,
    LevelContext,
    NbsExecutor,
    Sample,
    TableH,
)
from chcos.apps.nbs.scheduling import Cancellable, RunnableScheduler, Scheduler, VirtualScheduler
from chcos.apps.nbs.statetable import load_builtin
from chcos.errors import ConfigError

__all__ = [
    "ACTUATORS",
    "FAN_IN",
    "INPUT_RATE_HZ",
    "REACTIONS",
    "SENSORS",
    "FanInG",
    "Fig67Result",
    "SensorBank",
    "build_levels",
    "main",
    "run_fig67",
]

SENSORS = ("S1", "S2", "S3", "testfile")
"""The inputs of figure 6.6: three sensors and the test file read by A3."""
ACTUATORS = ("M1", "M2")
"""The actuators of figure 6.5 (A1 drives M1, A2 drives M2)."""
REACTIONS = {"M1": ("S1", "S2"), "M2": ("S3",)}
"""Which inputs each actuator reacts to (A1 reads S1 and S2, A2 reads S3)."""
FAN_IN = 5
"""Five inputs at level n make one sensory output to level n+1 (thesis 6.4)."""
INPUT_RATE_HZ = 10.0
"""Each input delivers a value every 100 ms (thesis 6.4)."""


class SensorBank:
    """Simulated devices for the run: every input gets a new value at ``rate_hz``.

    It offers the :class:`~chcos.apps.nbs.executor.DeviceIO` callables (with arrival stamps) and
    records
    actuator writes. Raises ConfigError for a rate that is not positive.
    """

    def __init__(
        self, scheduler: Scheduler, sensors: Sequence[str] = SENSORS, rate_hz: float = INPUT_RATE_HZ
    ) -> None:
        if not rate_hz > 0:
            raise ConfigError(f"fig67: input rate must be > 0 Hz, got {rate_hz!r}")
        self.scheduler = scheduler
        self.sensors = tuple(sensors)
        self.rate_hz = rate_hz
        self.produced = dict.fromkeys(self.sensors, 0)
        self.actuators: dict[str, object] = {}
        self.writes: list[tuple[float, str, object]] = []
        self._stamps: dict[str, float] = {}
        self._timer: Cancellable | None = None

    def start(self) -> None:
        """Start producing values (first ones one period from now)."""
        if self._timer is None:
            self._timer = self.scheduler.every(1.0 / self.rate_hz, self._produce)

    def stop(self) -> None:
        """Stop producing values."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _produce(self) -> None:
        now = self.scheduler.now()
        for s in self.sensors:
            self.produced[s] += 1
            self._stamps[s] = now

    def read(self, name: str) -> object | None:
        """The latest value of an input (its sample number), None before the first one."""
        if name not in self.produced:
            raise ConfigError(f"fig67: no sensor {name!r}; expected one of {self.sensors}")
        n = self.produced[name]
        return n if n else None

    def arrived(self, name: str) -> float | None:
        """When the latest value of an input became visible."""
        return self._stamps.get(name)

    def write(self, name: str, value: object) -> None:
        """Set an actuator and log the write."""
        self.actuators[name] = value
        self.writes.append((self.scheduler.now(), name, value))

    def io(self) -> DeviceIO:
        """The DeviceIO view of this bank."""
        return DeviceIO(read=self.read, write=self.write, arrived=self.arrived)


class FanInG:
    """A G module: counts inputs (sensor samples at level 1, outputs of G<n-1> above) and
    passes one output up for every ``fan_in`` of them (a counter in ``sensory/n``)."""

    def __init__(self, fan_in: int, sensors: Sequence[str] = ()) -> None:
        self.fan_in = fan_in
        self.sensors = tuple(sensors)
        self.inputs = 0
        self.outputs = 0
        self.seen = dict.fromkeys(self.sensors, 0)
        self.skipped = dict.fromkeys(self.sensors, 0)
        self._last: dict[str, int] = {}
        self._below = 0

    def __call__(self, ctx: LevelContext) -> None:
        fresh: list[Sample] = []
        if ctx.level == 1:
            for s in self.sensors:
                sample = ctx.poll(s)
                if sample is not None:
                    fresh.append(sample)
                    self.seen[s] += 1
                    if isinstance(sample.value, int):  # SensorBank values are sample numbers
                        self.skipped[s] += sample.value - self._last.get(s, 0) - 1
                        self._last[s] = sample.value
            arrived = len(fresh)
        else:
            below = ctx.mem.get(CommonMemory.sensory(ctx.level - 1), 0)
            assert isinstance(below, int)
            arrived, self._below = below - self._below, below
        ctx.values["fresh"] = fresh
        for _ in range(arrived):
            self.inputs += 1
            if self.inputs % self.fan_in == 0:
                self.outputs += 1
        ctx.mem.put(CommonMemory.sensory(ctx.level), self.outputs)


def _model(ctx: LevelContext) -> None:
    """An M module: keep the last value of every fresh input and the input count."""
    last = ctx.values.setdefault("last", {})
    assert isinstance(last, dict)
    fresh = ctx.values.get("fresh", [])
    assert isinstance(fresh, list)
    for sample in fresh:
        last[sample.sensor] = sample.value
    ctx.facts["input fresh"] = bool(fresh)


def _reflex_h1(ctx: LevelContext) -> None:
    """H1 as A1/A2: new S1/S2 -> write M1 from both; new S3 -> write M2."""
    fresh = ctx.values.get("fresh", [])
    last = ctx.values.get("last", {})
    assert isinstance(fresh, list) and isinstance(last, dict)
    names = {s.sensor for s in fresh}
    for actuator, inputs in REACTIONS.items():
        if names & set(inputs):
            ctx.write(actuator, tuple(last.get(i) for i in inputs))


def build_levels(fan_in: int = FAN_IN) -> tuple[list[Level], list[FanInG]]:
    """The three levels of figure 6.7 and their G modules (which hold the counts)."""
    gs = [FanInG(fan_in, SENSORS), FanInG(fan_in), FanInG(fan_in)]
    levels = [
        Level(g=gs[0], m=_model, h=_reflex_h1),
        Level(g=gs[1], m=_model, h=TableH(load_builtin("H2"))),
        Level(g=gs[2], m=_model, h=TableH(load_builtin("H3"))),
    ]
    return levels, gs


@dataclass(frozen=True)
class Fig67Result:
    """What one run of the figure 6.7 hierarchy did (all counted, nothing assumed)."""

    seconds: float
    period: float
    cycles: int
    executions: dict[str, int]
    inputs_produced: dict[str, int]
    inputs_seen: dict[str, int]
    inputs_lost: dict[str, int]
    outputs: dict[int, int]
    actuator_writes: int
    latencies: tuple[Latency, ...]

    @property
    def total_executions(self) -> int:
        """Module (FSM) executions in all."""
        return sum(self.executions.values())

    @property
    def executions_per_second(self) -> float:
        """FSM executions per second of run time."""
        return self.total_executions / self.seconds

    @property
    def lost(self) -> int:
        """Input values overwritten by a newer one before any poll saw them."""
        return sum(self.inputs_lost.values())

    @property
    def unpolled(self) -> int:
        """Input values produced too close to the end of the run to be polled (not lost)."""
        return sum(self.inputs_produced.values()) - sum(self.inputs_seen.values()) - self.lost

    @property
    def latency_mean(self) -> float | None:
        """Mean reaction latency in seconds (None without reactions)."""
        return statistics.fmean(x.seconds for x in self.latencies) if self.latencies else None

    @property
    def latency_max(self) -> float | None:
        """Worst reaction latency in seconds (None without reactions)."""
        return max(x.seconds for x in self.latencies) if self.latencies else None


def run_fig67(
    scheduler: RunnableScheduler,
    seconds: float,
    *,
    period: float = DEFAULT_PERIOD,
    input_rate_hz: float = INPUT_RATE_HZ,
    fan_in: int = FAN_IN,
) -> Fig67Result:
    """Run the figure 6.7 NBS hierarchy on ``scheduler`` for ``seconds`` and count.

    The executor cycles every ``period`` (28 ms by default; 1/80 s is the thesis' polling
    rate); inputs arrive at ``input_rate_hz``. Raises ConfigError for a non-positive duration,
    rate or fan-in, KernelError for a non-positive period.
    """
    if not seconds > 0:
        raise ConfigError(f"fig67: run time must be > 0 s, got {seconds!r}")
    if fan_in < 1:
        raise ConfigError(f"fig67: fan_in must be >= 1, got {fan_in!r}")
    bank = SensorBank(scheduler, SENSORS, input_rate_hz)
    levels, gs = build_levels(fan_in)
    ex = NbsExecutor(levels, bank.io(), scheduler, period=period, reactions=REACTIONS)
    bank.start()
    ex.start()
    try:
        scheduler.run_until(scheduler.now() + seconds)
    finally:
        ex.stop()
        bank.stop()
    return Fig67Result(
        seconds=seconds,
        period=period,
        cycles=ex.cycles,
        executions=ex.counts,
        inputs_produced=dict(bank.produced),
        inputs_seen=dict(gs[0].seen),
        inputs_lost=dict(gs[0].skipped),
        outputs={n: g.outputs for n, g in enumerate(gs, start=1)},
        actuator_writes=ex.writes,
        latencies=tuple(ex.latencies),
    )


def main(argv: Sequence[str] | None = None, out: Callable[[str], object] = print) -> int:
    """``python -m chcos.apps.nbs.fig67 [--seconds S] [--period P]``: one run on virtual time."""
    ap = argparse.ArgumentParser(
        prog="python -m chcos.apps.nbs.fig67", description="Run the figure 6.7 NBS hierarchy."
    )
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--period", type=float, default=DEFAULT_PERIOD)
    ap.add_argument("--rate", type=float, default=INPUT_RATE_HZ, help="input rate in Hz")
    ns = ap.parse_args(argv)
    r = run_fig67(VirtualScheduler(), ns.seconds, period=ns.period, input_rate_hz=ns.rate)
    out(f"cycles {r.cycles} in {r.seconds:g} s (period {r.period * 1000:g} ms)")
    out(f"FSM executions {r.total_executions} ({r.executions_per_second:.1f}/s)")
    out("  " + " ".join(f"{k}={v}" for k, v in r.executions.items()))
    seen = sum(r.inputs_seen.values())
    out(f"inputs seen {seen}, lost {r.lost}, not yet polled {r.unpolled}")
    out(f"sensory outputs per level {r.outputs}")
    if r.latency_mean is not None and r.latency_max is not None:
        out(
            f"reaction latency mean {r.latency_mean * 1000:.2f} ms, "
            f"max {r.latency_max * 1000:.2f} ms over {len(r.latencies)} reactions"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
