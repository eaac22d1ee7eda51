"""emergency_load - background CAN traffic for the emergency benchmark, and its memory soak.

:class:`TrafficGenerator` sends paced background frames from a peer bus and drains what comes
back; :func:`run_soak` runs the benchmark's system (:mod:`chcos.apps.bench.emergency_system`) at
10,000 frames/s without intruders and reads the resident size (VmRSS of /proc/self/status) after a
warm-up and at the end. :mod:`chcos.apps.bench.emergency` (the reaction run) re-exports both.
Errors: :class:`~chcos.errors.BusError` if the virtual bus cannot be opened, ConfigError for bad
parameters.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import can

from chcos.apps.bench.emergency_system import BACKGROUND, build
from chcos.errors import ConfigError

__all__ = ["SoakResult", "TrafficGenerator", "channel_name", "rss_kb", "run_soak"]


def rss_kb() -> int:
    """This process' resident set size in kB (VmRSS of /proc/self/status); 0 if unknown."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


class TrafficGenerator:
    """A thread sending ``rate`` frames/s round-robin to the background sensors on ``bus``
    (paced on an absolute schedule, at most ``burst`` frames at a time), and a listener thread
    draining the peer's receive queue (an unread python-can virtual bus queue grows without
    bound) and calling ``on_frame(msg, t)`` for every frame. ``lock`` serialises sends with
    other senders on the same bus. Raises ConfigError for a negative rate."""

    def __init__(self, bus: can.BusABC, rate: float, lock: threading.Lock,
                 on_frame: Callable[[can.Message, float], None] | None = None,
                 burst: int = 20) -> None:
        if not rate >= 0:
            raise ConfigError(f"traffic rate must be >= 0 frames/s, got {rate!r}")
        self.bus = bus
        self.rate = rate
        self.lock = lock
        self.on_frame = on_frame
        self.burst = burst
        self.sent = 0
        self.received = 0
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._send_loop, name="bench-gen", daemon=True),
                         threading.Thread(target=self._recv_loop, name="bench-rx", daemon=True)]

    def start(self) -> None:
        """Start both threads."""
        for t in self._threads:
            t.start()

    def stop(self) -> None:
        """Stop both threads and wait for them."""
        self._stop.set()
        for t in self._threads:
            t.join(2.0)

    def _send_loop(self) -> None:
        t0 = time.perf_counter()
        n_ids = len(BACKGROUND)
        while not self._stop.is_set():
            due = int((time.perf_counter() - t0) * self.rate) - self.sent
            for _ in range(min(due, self.burst)):
                k = self.sent
                msg = can.Message(arbitration_id=0x100 + k % n_ids, is_extended_id=False,
                                  data=(k + 1).to_bytes(4, "little"))
                with self.lock:
                    self.bus.send(msg)
                self.sent += 1
            self._stop.wait(0.0005)

    def _recv_loop(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(0.05)
            if msg is None:
                continue
            t = time.perf_counter()
            self.received += 1
            if self.on_frame is not None:
                self.on_frame(msg, t)


def channel_name(tag: str) -> str:
    """A virtual channel name of this process no other run shares."""
    return f"chcos-bench-{tag}-{os.getpid()}-{time.monotonic_ns()}"


@dataclass
class SoakResult:
    """Resident size over a soak (kB) and what flowed meanwhile."""

    seconds: float
    rate: float
    rss_start_kb: int
    rss_end_kb: int
    rss_max_kb: int
    samples_kb: list[int]
    frames_sent: int
    frames_received_by_driver: int
    readings: int

    @property
    def growth_kb(self) -> int:
        """End minus start."""
        return self.rss_end_kb - self.rss_start_kb

    @property
    def achieved_rate(self) -> float:
        """Frames per second actually sent during the soak."""
        return self.frames_sent / self.seconds if self.seconds else 0.0


def run_soak(seconds: float = 60.0, rate: float = 10_000.0, *, warmup: float = 3.0
             ) -> SoakResult:
    """Run the emergency system at ``rate`` background frames/s for ``warmup`` + ``seconds``
    and sample VmRSS once a second; start is read after the warm-up. Raises ConfigError for a
    non-positive duration, BusError if the bus cannot be opened."""
    if not seconds > 0 or warmup < 0:
        raise ConfigError(f"soak: need seconds > 0 and warmup >= 0, got {seconds}, {warmup}")
    channel = channel_name("soak")
    s = build(channel)
    peer = can.Bus(interface="virtual", channel=channel)
    gen = TrafficGenerator(peer, rate, threading.Lock())
    s.start()
    gen.start()
    try:
        time.sleep(warmup)
        start_kb = rss_kb()
        sent0 = gen.sent
        recv0 = sum(getattr(d, "received", 0) for d in s.devtab.drivers)
        read0 = sum(s.devtab.get(b).readings for b in BACKGROUND)
        t0 = time.perf_counter()
        samples = [start_kb]
        while (left := t0 + seconds - time.perf_counter()) > 0:
            time.sleep(min(1.0, left))
            samples.append(rss_kb())
        dt = time.perf_counter() - t0
        end_kb = samples[-1]
        return SoakResult(
            seconds=dt, rate=rate, rss_start_kb=start_kb, rss_end_kb=end_kb,
            rss_max_kb=max(samples), samples_kb=samples, frames_sent=gen.sent - sent0,
            frames_received_by_driver=sum(getattr(d, "received", 0)
                                          for d in s.devtab.drivers) - recv0,
            readings=sum(s.devtab.get(b).readings for b in BACKGROUND) - read0)
    finally:
        gen.stop()
        s.shutdown()
        peer.shutdown()
