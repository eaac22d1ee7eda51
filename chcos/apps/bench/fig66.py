"""fig66 - the figure 6.6 system (figure 6.5 without A4) as CHC and as the NBS baseline.

Thesis 6.4 compares the two designs on this system under one load: S1, S2, S3 and the test file
each deliver a value every 100 ms, and five inputs at level n make one output at level n+1.

* CHC: the tasks of figure 6.5 without the terminal task A4, installed with the thesis' script
  (:data:`INSTALL`): A1 (S1, S2 -> M1), A2 (S3 -> M2), A3 (the test file), B1 (A1, A2), B2 (A2,
  A3), C1 (B1, B2). A1, A2, B1, B2 are the figure 6.5 example's code; A3 condenses the test-file
  readings like any driver task; C1 is the example's C1 without A4.
* NBS: the nine-FSM hierarchy of figure 6.7 (:func:`chcos.apps.nbs.fig67.build_levels`) run by
  :mod:`chcos.apps.nbs.adapter` on a System with the same device map.

Both get their inputs the same way (:class:`~chcos.apps.bench.load.Load`) and have their
reactions timed the same way (:class:`~chcos.apps.bench.load.ReactionProbe`), both in
:mod:`chcos.apps.bench.load` with :func:`~chcos.apps.bench.load.expected_rates` (re-exported
here). Errors: :class:`~chcos.errors.ConfigError` for a bad load or window,
plus whatever the System raises while it is built (InstallError, BusError).
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.apps.bench.load import (
    INPUT_RATE_HZ,
    INPUTS,
    REACTIONS,
    Load,
    ReactionProbe,
    expected_rates,
)
from chcos.apps.fig65.common import FAN_IN, condense
from chcos.apps.nbs import fig67
from chcos.apps.nbs.adapter import attach
from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ConfigError
from chcos.kernel.clock import Clock, RealClock, VirtualClock
from chcos.kernel.instrument import Counters
from chcos.system.embedded import System
from chcos.tables.messages import EndpointKind, LinkType
from chcos.user.context import TaskContext

__all__ = [
    "FAN_IN",
    "INPUTS",
    "INPUT_RATE_HZ",
    "INSTALL",
    "REACTIONS",
    "TOPOLOGY",
    "CountResult",
    "Load",
    "ReactionProbe",
    "build_chcos",
    "build_nbs_system",
    "count_chcos",
    "count_nbs",
    "devmap",
    "expected_rates",
    "file_driver",
    "latency_chcos_real",
    "latency_chcos_virtual",
    "latency_nbs_virtual",
    "top",
]

TOPOLOGY: dict[str, tuple[str, ...]] = {
    "A1": ("S1", "S2"),
    "A2": ("S3",),
    "A3": ("testfile",),
    "B1": ("A1", "A2"),
    "B2": ("A2", "A3"),
    "C1": ("B1", "B2"),
}
"""Each task of figure 6.6 and the sources of its sensory messages (the install script's inputs)."""

_M = "chcos.apps.bench.fig66"
_EX = "chcos.apps.fig65"
INSTALL: tuple[str, ...] = (
    "install -m0 sysfile",
    "install -m1 sysfile",
    "install -m2 sysfile",
    f"install -m0i2o1 --code={_EX}.A1:main A1 S1 S2 M1",
    f"install -m1i1o1 --code={_EX}.A2:main A2 S3 M2",
    f"install -m2i1 --code={_M}:file_driver A3 testfile",
    f"install -m0i2o3 --code={_EX}.B1:main B1 A1 A2 A1 A2 A3",
    f"install -m1i2o1 --code={_EX}.B2:main B2 A2 A3 A3",
    f"install -m2i2o2 --code={_M}:top C1 B1 B2 B1 B2",
    "setpri -9 C1 B1",
)
"""The thesis' install script for figure 6.5 (section 6.3) without A4 and its links."""


# --------------------------------------------------------------------------- tasks


async def file_driver(ctx: TaskContext, command: Any) -> None:
    """A3: condense the test-file readings (sensor ``testfile``) five to one, upward."""
    await condense(ctx)


async def top(ctx: TaskContext, command: Any) -> None:
    """C1 without the terminal task A4: take B1 and B2, then condense what they report."""
    await ctx.invoke("B1", {"mode": "run"})
    await ctx.invoke("B2", {"mode": "run"}, wait=False)
    await condense(ctx)


def devmap(inputs: Sequence[str] = INPUTS) -> DeviceMap:
    """The devices of figure 6.6 on one in-memory bus: S1, S2, M1 on machine 0, S3, M2 on
    machine 1, the test file on machine 2; actuators with limits +-100 and safe value 0."""
    bus = BusSpec("fig66", "memory", {"history": 4})
    machine = {"S1": 0, "S2": 0, "S3": 1, "testfile": 2, "M1": 0, "M2": 1}
    devs = [DeviceSpec(s, "sensor", machine.get(s, 0), "fig66") for s in inputs]
    devs += [DeviceSpec(a, "actuator", machine[a], "fig66", limits=(-100.0, 100.0),
                        safe_value=0.0) for a in ("M1", "M2")]
    return DeviceMap((bus,), tuple(devs))


# --------------------------------------------------------------------------- the systems


def build_chcos(clock: Clock, workdir: Path | None = None) -> System:
    """The CHC system of figure 6.6 on ``clock``, installed and C1 invoked by the host (nothing
    has run yet). Raises InstallError or BusError if it cannot be built."""
    s = System(devmap(), clock=clock, base_dir=workdir or Path.cwd())
    for line in INSTALL:
        s.execute(line)
    s.invoke("C1")
    return s


def build_nbs_system(clock: Clock) -> System:
    """A System with figure 6.6's devices (machines 0..2 booted) and no tasks: the NBS side."""
    return System(devmap(), clock=clock, machines=[0, 1, 2], base_dir=Path.cwd())


@dataclass(frozen=True)
class CountResult:
    """Executions counted in a measurement window of a virtual-time run."""

    system: str
    seconds: float
    executions: dict[str, int]
    messages: int
    inputs: int

    @property
    def total(self) -> int:
        """All executions in the window."""
        return sum(self.executions.values())

    @property
    def per_second(self) -> float:
        """Executions per second of the window."""
        return self.total / self.seconds

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready."""
        return {"system": self.system, "seconds": self.seconds, "executions": self.executions,
                "total": self.total, "per_second": self.per_second, "messages": self.messages,
                "inputs": self.inputs}


def _check_window(warmup: float, seconds: float) -> None:
    if not (warmup >= 0 and seconds > 0):
        raise ConfigError(f"window: warm-up must be >= 0 and length > 0 s, "
                          f"got {warmup!r}, {seconds!r}")


def _task_messages(system: System) -> int:
    return sum(lk.delivered for lk in system.msgtab
               if lk.type is LinkType.SENSORY and lk.dst_kind is EndpointKind.TASK)


def count_chcos(seconds: float, *, warmup: float = 2.5, seed: int = 1) -> CountResult:
    """Run the CHC figure 6.6 system on virtual time and count, in the window
    ``[warmup, warmup + seconds)``: kernel steps (task executions) per task, sensory messages
    the tasks took, inputs injected. Raises ConfigError for a bad window."""
    _check_window(warmup, seconds)
    s = build_chcos(VirtualClock())
    counters = Counters()
    s.kernel.add_instrument(counters)
    load = Load(seed=seed)
    load.schedule(s, start=0.0)
    try:
        s.run(until=warmup)
        steps0, msgs0 = dict(counters.steps), _task_messages(s)
        inj0 = sum(load.injected.values())
        s.run(until=warmup + seconds)
        steps = {t: counters.steps[t] - steps0.get(t, 0) for t in TOPOLOGY}
        return CountResult("chcos", seconds, steps, _task_messages(s) - msgs0,
                           sum(load.injected.values()) - inj0)
    finally:
        s.shutdown()


def count_nbs(seconds: float, period: float, *, warmup: float = 2.5, seed: int = 1
              ) -> tuple[CountResult, dict[str, int]]:
    """Run the NBS figure 6.7 hierarchy on a System (virtual time) under the same load and
    count module executions in the window; also returns inputs seen and lost by G1 over the
    whole run. Raises ConfigError for a bad window, KernelError for a bad period."""
    _check_window(warmup, seconds)
    s = build_nbs_system(VirtualClock())
    levels, gs = fig67.build_levels()
    nbs = attach(s.kernel, s.devtab, levels, period=period, reactions=REACTIONS)
    load = Load(seed=seed)
    load.schedule(s, start=0.0)
    nbs.start()
    try:
        nbs.scheduler.run_until(warmup)
        ex0, inj0 = dict(nbs.executor.counts), sum(load.injected.values())
        nbs.scheduler.run_until(warmup + seconds)
        counts = {k: v - ex0[k] for k, v in nbs.executor.counts.items()}
        seen = sum(gs[0].seen.values())
        injected = sum(load.injected.values())
        # a value injected after the last cycle is not lost, only not polled yet
        last_cycle = nbs.executor.cycles * period
        late = sum(1 for sn in INPUTS for k in range(load.injected[sn])
                   if load.phases[sn] + k * load.period > last_cycle)
        extra = {"inputs_injected": injected, "inputs_seen": seen,
                 "inputs_lost": injected - late - seen, "cycles": nbs.executor.cycles}
        return (CountResult(f"nbs@{period * 1000:g}ms", seconds, counts, 0, injected - inj0),
                extra)
    finally:
        nbs.stop()
        s.shutdown()


# --------------------------------------------------------------------------- latency runs


def latency_chcos_virtual(seconds: float, *, seed: int = 1, jitter: float = 0.028
                          ) -> list[float]:
    """Reaction latencies (s) of the CHC system on virtual time: processing costs no virtual
    time, so these are the design's latencies (reaction at event time). Raises ConfigError."""
    s = build_chcos(VirtualClock())
    probe = ReactionProbe(s.kernel.clock.now)
    probe.install(s)
    Load(seed=seed, jitter=jitter).schedule(s, probe, start=0.0)
    try:
        s.run(until=seconds)
        probe.active = False
        return probe.samples
    finally:
        s.shutdown()


def latency_nbs_virtual(seconds: float, period: float, *, seed: int = 1, jitter: float = 0.028
                        ) -> tuple[list[float], list[float]]:
    """Reaction latencies (s) of the NBS executor on virtual time under the same load, as
    measured by the probe and as measured by the executor itself (they must agree).
    Raises ConfigError, KernelError."""
    s = build_nbs_system(VirtualClock())
    levels, _ = fig67.build_levels()
    nbs = attach(s.kernel, s.devtab, levels, period=period, reactions=REACTIONS)
    probe = ReactionProbe(s.kernel.clock.now)
    probe.install(s)
    Load(seed=seed, jitter=jitter).schedule(s, probe, start=0.0)
    nbs.start()
    try:
        nbs.scheduler.run_until(seconds)
        probe.active = False
        return probe.samples, [x.seconds for x in nbs.executor.latencies]
    finally:
        nbs.stop()
        s.shutdown()


def latency_chcos_real(seconds: float, *, seed: int = 1, jitter: float = 0.028
                       ) -> tuple[list[float], list[float]]:
    """Reaction latencies (s) of the CHC system on real time in this process: a feeder thread
    hands each value to the Devtab (as a driver thread does) and stamps it with
    ``time.perf_counter()``; the actuator write is stamped on the kernel thread. This is chcos'
    true processing latency (interrupt queue, wake-up, scheduling, the task, Devtab.write).

    Also returns a side-by-side baseline from the same run: after every event the feeder hands
    a time stamp to a bare Python thread blocked on a ``queue.SimpleQueue`` (one thread
    hand-off, the least any interrupt-driven Python reaction costs)."""
    s = build_chcos(RealClock())
    probe = ReactionProbe(time.perf_counter)
    probe.install(s)
    stop = threading.Event()
    box: queue.SimpleQueue[float | None] = queue.SimpleQueue()
    raw: list[float] = []

    def waiter() -> None:
        while (t := box.get()) is not None:
            raw.append(time.perf_counter() - t)

    w = threading.Thread(target=waiter, name="fig66-raw", daemon=True)
    w.start()

    def handoff() -> None:
        time.sleep(0.002)  # after chcos has reacted: the two never compete
        box.put(time.perf_counter())

    s.start()
    try:
        th = Load(seed=seed, jitter=jitter).feed_thread(s, probe, seconds, stop, handoff)
        th.join(seconds + 5.0)
        time.sleep(0.05)
        probe.active = False
        return probe.samples, raw
    finally:
        stop.set()
        box.put(None)
        w.join(2.0)
        s.shutdown()
