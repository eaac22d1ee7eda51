"""emergency - the emergency reaction under CAN load, and the memory soak, on real time.

One process, real time, a python-can ``virtual`` bus and chcos' real CAN driver (kind ``can``);
the system (tasks, device map, install) is :mod:`chcos.apps.bench.emergency_system`:

* four background sensors ``B0..B3`` (CAN ids 0x100..0x103) read by four level-1 driver tasks
  ``D0..D3``; each task writes its actuator ``M0..M3`` (ids 0x200..0x203) and sends a sensory
  message up on every fifth reading (the thesis' five-to-one fan-in);
* a light curtain ``LC`` (id 0x050, interrupt priority 99) read by the guard task ``G``, which
  reports every reading upward;
* the exception task ``X`` (level 3) hears every sensory message of every lower task through its
  tap at priority 99; on an intruder report it invokes the assassin ``K`` (level 2) on the
  priority-99 link X/K; ``K`` calls estop: every actuator is written its safe value (0) through
  Devtab.write, and the driver puts the frames on the bus (on K's step, by its fast path, when
  nothing of that actuator is outstanding); then K suspends ``D0..D3``.

A peer (one more python-can bus on the channel) sends the background traffic from a pacing
thread at ``rate`` frames/s and, from the measuring thread, one intruder frame per trial at a
seeded random moment; its listener thread drains the bus and notes when the safe-value frames
appear on it. Per trial the measured times are (``time.perf_counter``, one process):

* ``from_send``: peer's ``send()`` of the intruder frame -> the last safe value written in
  Devtab (the Devtab ``on_write`` hook, on the kernel thread, during K's step);
* ``from_driver``: the CAN driver handing the decoded intruder value to the Devtab (its reader
  thread) -> the same last safe value;
* ``on_wire``: peer's send -> the last safe-value frame received back by the peer (its listener
  thread, in this process: includes that thread's own wake-up, GIL hand-off included);
* ``stamped``: peer's send -> the bus's own time stamp of the last safe-value frame (python-can
  ``virtual`` stamps a frame with ``time.time()`` in the sender's ``send()``; both ends read on
  ``time.time()``): when the frame went on the bus, without the peer's receive delay.

As a side-by-side baseline under the same load and noise, every trial is followed by one
``raw_echo``: a frame sent on a second virtual channel to a bare Python thread that sends it
straight back, timed from send to the echo's arrival at the measuring thread (two thread
hand-offs, as many as ``from_send`` needs: bus -> driver thread -> kernel thread).

:func:`run_soak` (from :mod:`chcos.apps.bench.emergency_load`, with the traffic generator) runs the
same system at 10,000 frames/s without intruders and reads the resident size (VmRSS of
/proc/self/status) after a warm-up and at the end.
Errors: :class:`~chcos.errors.BusError` if the virtual bus cannot be opened, ConfigError for
bad parameters.
"""

from __future__ import annotations

import os
import random
import threading
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can

from chcos.apps.bench.emergency_load import (
    SoakResult,
    TrafficGenerator,
    channel_name,
    rss_kb,
    run_soak,
)
from chcos.apps.bench.emergency_system import (
    ACTUATORS,
    BACKGROUND,
    LC_ID,
    assassin,
    build,
    drive,
    guard,
    watch,
)
from chcos.errors import ConfigError
from chcos.system.affinity import pin_process

__all__ = [
    "ACTUATORS",
    "BACKGROUND",
    "EmergencyResult",
    "SoakResult",
    "TrafficGenerator",
    "assassin",
    "build",
    "drive",
    "guard",
    "rss_kb",
    "run_emergency",
    "run_soak",
    "watch",
]

class _HostProbe:
    """Stands between the CAN driver and the Devtab: stamps the hand-over of intruder values."""

    def __init__(self, host: Any, on_lc: Callable[[float], None]) -> None:
        self._host = host
        self._on_lc = on_lc

    def deliver(self, device: str, value: Any) -> None:
        """Stamp a non-zero light-curtain value, then hand it on (driver thread)."""
        if device == "LC" and value:
            self._on_lc(time.perf_counter())
        self._host.deliver(device, value)

    def deliver_now(self, device: str, value: Any) -> None:
        """As :meth:`deliver`, for a reading taken on the kernel thread."""
        if device == "LC" and value:
            self._on_lc(time.perf_counter())
        self._host.deliver_now(device, value)

    def deliver_many(self, readings: Sequence[tuple[str, Any]],
                     at: float | None = None) -> None:
        """The same for a batch of readings (the CAN driver hands a drain's frames over as
        one, with their receive time ``at``): stamped if an intruder value is among them, then
        handed on as one batch."""
        if any(device == "LC" and value for device, value in readings):
            self._on_lc(time.perf_counter())
        self._host.deliver_many(readings, at=at)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._host, name)


@dataclass
class EmergencyResult:
    """Per-trial times in seconds (see the module doc) and the run's conditions."""

    from_send: list[float] = field(default_factory=list)
    from_driver: list[float] = field(default_factory=list)
    on_wire: list[float] = field(default_factory=list)
    stamped: list[float] = field(default_factory=list)
    raw_echo: list[float] = field(default_factory=list)
    trials: int = 0
    failed: int = 0
    background_sent: int = 0
    background_seconds: float = 0.0
    frames_received_by_driver: int = 0
    #: the machine's load averages (1, 5, 15 min) at the start of the run, and its CPU count:
    #: the figure holds on a quiet machine, so it is always printed beside it
    load: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cpus: int = 0
    #: the CPUs the process was pinned to for the run (empty: not pinned)
    cpus_pinned: tuple[int, ...] = ()

    def load_text(self) -> str:
        """The machine's load as printed beside the figures."""
        return (f"load {self.load[0]:.2f} {self.load[1]:.2f} {self.load[2]:.2f} on "
                f"{self.cpus} CPUs")

    @property
    def background_rate(self) -> float:
        """Background frames per second actually sent."""
        return self.background_sent / self.background_seconds if self.background_seconds else 0.0


class _Trial:
    """The state of the trial being measured (written by three threads, read by one)."""

    def __init__(self, n_safe: int) -> None:
        self.n_safe = n_safe
        self.armed = False
        self.t_driver: float | None = None
        self.writes: list[float] = []
        self.wire: dict[int, float] = {}
        self.stamps: dict[int, float] = {}
        self.done = threading.Event()
        self.wire_done = threading.Event()

    def arm(self) -> None:
        self.t_driver = None
        self.writes = []
        self.wire = {}
        self.stamps = {}
        self.done.clear()
        self.wire_done.clear()
        self.armed = True


class _Echo:
    """A bare Python thread on its own virtual channel sending every frame straight back."""

    def __init__(self) -> None:
        channel = channel_name("echo")
        self.near = can.Bus(interface="virtual", channel=channel)
        self.far = can.Bus(interface="virtual", channel=channel)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="bench-echo", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            msg = self.far.recv(0.05)
            if msg is not None:
                self.far.send(msg)

    def ping(self, k: int) -> float | None:
        """Seconds from send to the echo's arrival; None if it did not come back in 1 s."""
        msg = can.Message(arbitration_id=0x7FF, is_extended_id=False,
                          data=k.to_bytes(4, "little"))
        t0 = time.perf_counter()
        self.near.send(msg)
        back = self.near.recv(1.0)
        return time.perf_counter() - t0 if back is not None else None

    def close(self) -> None:
        """Stop the echo thread and close both buses."""
        self._stop.set()
        self._thread.join(2.0)
        self.near.shutdown()
        self.far.shutdown()


def run_emergency(trials: int = 200, rate: float = 5000.0, *, seed: int = 7,
                  gap: tuple[float, float] = (0.01, 0.03),
                  cpus: Iterable[int] | None = None) -> EmergencyResult:
    """Run ``trials`` intruder trials under ``rate`` background frames/s, each followed by a
    raw echo (see the module doc). ``cpus``: the whole process (system, peer and echo alike) is
    pinned to these CPUs for the run, as ``system.cpus`` pins ``chcos run``, and given its
    former CPUs back after. Raises ConfigError for bad parameters or CPUs this process may not
    use, BusError if the bus cannot be opened."""
    if trials < 1 or not 0 < gap[0] <= gap[1]:
        raise ConfigError(f"emergency: need trials >= 1 and 0 < gap, got {trials}, {gap}")
    if cpus is None:
        return _run_emergency(trials, rate, seed, gap)
    former = pin_process(cpus, "emergency benchmark: cpus")
    try:
        res = _run_emergency(trials, rate, seed, gap)
    finally:
        pin_process(former, "emergency benchmark: the former CPUs")
    res.cpus_pinned = tuple(sorted(cpus))
    return res


def _run_emergency(trials: int, rate: float, seed: int,
                   gap: tuple[float, float]) -> EmergencyResult:
    channel = channel_name("emg")
    s = build(channel)
    n_safe = len(ACTUATORS)
    trial = _Trial(n_safe)
    k_entry = s.tsktab.get("K")
    kernel = s.kernel
    act_ids = {0x200 + i for i in range(n_safe)}

    def on_write(device: str, value: Any) -> None:
        if trial.armed and kernel.current is k_entry and value == 0.0:
            trial.writes.append(time.perf_counter())
            if len(trial.writes) == n_safe:
                trial.done.set()

    def on_frame(msg: can.Message, t: float) -> None:
        if (trial.armed and msg.arbitration_id in act_ids
                and int.from_bytes(msg.data[:4], "little") == 0):
            trial.wire.setdefault(msg.arbitration_id, t)
            trial.stamps.setdefault(msg.arbitration_id, msg.timestamp)
            if len(trial.wire) == n_safe:
                trial.wire_done.set()

    def on_lc(t: float) -> None:
        if trial.armed and trial.t_driver is None:
            trial.t_driver = t

    s.devtab.on_write.append(on_write)
    for drv in s.devtab.drivers:
        drv.host = _HostProbe(drv.host, on_lc)
    peer = can.Bus(interface="virtual", channel=channel)
    lock = threading.Lock()
    gen = TrafficGenerator(peer, rate, lock, on_frame)
    rng = random.Random(seed)
    res = EmergencyResult()
    echo = _Echo()
    res.load, res.cpus = os.getloadavg(), os.cpu_count() or 0
    s.start()
    gen.start()
    t_start = time.perf_counter()
    try:
        time.sleep(0.3)  # warm-up: traffic flowing, every task waiting on its input
        for i in range(trials):
            time.sleep(rng.uniform(*gap))
            trial.arm()
            frame = can.Message(arbitration_id=LC_ID, is_extended_id=False,
                                data=(i + 1).to_bytes(4, "little"))
            with lock:
                t_send = time.perf_counter()
                t_wall = time.time()
                peer.send(frame)
            ok = trial.done.wait(1.0) and trial.wire_done.wait(1.0)
            trial.armed = False
            res.trials += 1
            if not ok or trial.t_driver is None:
                res.failed += 1
            else:
                last = trial.writes[-1]
                res.from_send.append(last - t_send)
                res.from_driver.append(last - trial.t_driver)
                res.on_wire.append(max(trial.wire.values()) - t_send)
                res.stamped.append(max(trial.stamps.values()) - t_wall)
            for d in range(len(BACKGROUND)):
                s.execute(f"resume D{d}")
            time.sleep(rng.uniform(*gap))
            raw = echo.ping(i)
            if raw is not None:
                res.raw_echo.append(raw)
        res.background_seconds = time.perf_counter() - t_start
        res.background_sent = gen.sent
        res.frames_received_by_driver = sum(getattr(d, "received", 0) for d in s.devtab.drivers)
        return res
    finally:
        gen.stop()
        echo.close()
        s.shutdown()
        peer.shutdown()


def _pct(xs: list[float], q: float) -> str:
    """The ``q`` quantile of ``xs`` (nearest rank) in ms; "-" for none."""
    if not xs:
        return "-"
    s = sorted(xs)
    return f"{s[min(len(s) - 1, max(0, int(len(s) * q + 0.5) - 1))] * 1e3:.3f} ms"


def _p50_p99(xs: list[float]) -> str:
    return f"p50 {_pct(xs, 0.5)}, p99 {_pct(xs, 0.99)}"


def main(argv: list[str] | None = None) -> int:
    """``python -m chcos.apps.bench.emergency [--trials N] [--rate R] [--cpus 1]``: one run,
    the p50 and p99 of each measured time with the machine's load beside them."""
    import argparse
    import logging

    ap = argparse.ArgumentParser(description="emergency reaction p99 under CAN load")
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--rate", type=float, default=5000.0, help="background frames/s")
    ap.add_argument("--cpus", type=lambda v: [int(c) for c in v.split(",")], default=None,
                    help="pin the process to these CPUs for the run (e.g. 1, or 0,1)")
    args = ap.parse_args(argv)
    logging.getLogger("chcos").setLevel(logging.ERROR)  # one estop warning per trial
    r = run_emergency(args.trials, args.rate, cpus=args.cpus)
    pinned = (f", pinned to CPU(s) {', '.join(map(str, r.cpus_pinned))}" if r.cpus_pinned
              else "")
    print(f"emergency reaction, {r.trials} trials ({r.failed} failed) under "
          f"{r.background_rate:,.0f} background frames/s; machine {r.load_text()}{pinned}")
    print(f"  peer send -> last safe value on the wire: {_p50_p99(r.on_wire)} (target p99 "
          f"< 0.5 ms on a quiet machine)")
    print(f"  ... by the bus's time stamp of the frame : {_p50_p99(r.stamped)} (without "
          f"the peer's receive delay)")
    print(f"  peer send -> last safe value in Devtab  : {_p50_p99(r.from_send)}")
    print(f"  bare Python echo on the bus (baseline)  : {_p50_p99(r.raw_echo)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
