"""bench_direct_can - frames per CPU-second through chcos' direct CAN bus of virtual time
(:mod:`drivers.can_direct`) against python-can's ``virtual`` bus, side by side in one run.

Run: ``.venv/bin/python -m tools.bench_direct_can [--frames N] [--repeat R]``. Three sections,
each with python-can's virtual bus first (the baseline) and the direct bus second, the ratio
against the baseline; each figure the best of ``--repeat`` rounds (other processes' load only
slows a round down), counted in this process's CPU time (every thread), which such load disturbs
less than wall time:

* the bus alone: one 8-byte frame sent and taken by one receiver (virtual: ``recv(0)`` after
  each send, the deepcopy into the receiver's queue included; direct: the receiver callback);
* the raw CAN driver receiving: a peer sends N frames of a sensor message and the driver decodes
  each and hands the reading to a counting host (virtual: the driver's reader thread, the clock
  stopped until every frame is delivered; direct: inside the peer's send);
* the raw CAN driver sending: N commands through ``write_now`` (the kernel thread's fast path),
  each taken by the peer (virtual: drained by ``recv(0)``; direct: its callback).

Prints frames/CPU-s and frames/s per row; no target (issue 47 asks for the measurement).
"""

from __future__ import annotations

import argparse
import functools
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import can

from chcos.devices.spec import BusSpec, DeviceSpec
from drivers.can_direct import DirectBus
from drivers.can_raw import CanDriver


class Host:
    """A DriverHost that counts readings and writes (thread-safe enough: one adder)."""

    virtual_clock = True

    def __init__(self) -> None:
        self.readings = 0
        self.done = threading.Event()
        self.want = 0

    def deliver(self, device: str, value: Any) -> None:
        self.readings += 1
        if self.readings >= self.want:
            self.done.set()

    def deliver_many(self, readings: Sequence[tuple[str, Any]], at: float | None = None) -> None:
        self.readings += len(readings)
        if self.readings >= self.want:
            self.done.set()

    def deliver_now(self, device: str, value: Any) -> None:
        self.deliver(device, value)

    def fail(self, device: str, reason: str) -> None: ...
    def recover(self, device: str, reason: str = "") -> None: ...
    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None: ...
    def written(self, device: str, value: Any) -> None: ...
    def write_failed(self, device: str, value: Any, reason: str) -> None: ...
    def stat(self, bus: str, key: str, n: int = 1, device: str = "",
             error: bool = False) -> None: ...
    def every(self, period: float, fn: Callable[[], None]) -> None: ...
    def at(self, when: float, fn: Callable[[], None]) -> None: ...

    def now(self) -> float:
        return 0.0


def _specs(interface: str, channel: str) -> tuple[BusSpec, list[DeviceSpec]]:
    bus = BusSpec("can0", "can", {"interface": interface, "channel": channel})
    devs = [DeviceSpec("t", "sensor", 0, "can0",
                       {"id": 0x100, "start": 0, "length": 16, "dlc": 2}),
            DeviceSpec("v", "actuator", 0, "can0",
                       {"id": 0x200, "start": 0, "length": 16, "dlc": 2})]
    return bus, devs


def measure(fn: Callable[[], int]) -> tuple[float, float]:
    """(frames per CPU-second, frames per second) of one run of ``fn`` (returns frames)."""
    c0, w0 = time.process_time(), time.perf_counter()
    n = fn()
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return n / max(cpu, 1e-9), n / max(wall, 1e-9)


def bus_alone(interface: str, n: int, tag: str) -> int:
    a = can.Bus(interface=interface, channel=tag)
    b = can.Bus(interface=interface, channel=tag)
    frame = can.Message(arbitration_id=0x100, data=bytes(8), is_extended_id=False)
    try:
        if isinstance(b, DirectBus):
            got = [0]

            def take(msg: can.Message) -> None:
                got[0] += 1
            b.set_receiver(take)
            for _ in range(n):
                a.send(frame)
            assert got[0] == n
        else:
            for _ in range(n):
                a.send(frame)
                assert b.recv(0) is not None
    finally:
        a.shutdown()
        b.shutdown()
    return n


def driver_receive(interface: str, n: int, tag: str) -> int:
    bus, devs = _specs(interface, tag)
    host = Host()
    host.want = n
    drv = CanDriver(bus, devs, host)
    drv.start()
    peer = can.Bus(interface=interface, channel=tag)
    try:
        frames = [can.Message(arbitration_id=0x100, data=(k & 0xFFFF).to_bytes(2, "little"),
                              is_extended_id=False) for k in range(n)]
        for f in frames:
            peer.send(f)
        assert host.done.wait(60), f"{host.readings} of {n} delivered"
    finally:
        peer.shutdown()
        drv.stop()
    return n


def driver_send(interface: str, n: int, tag: str) -> int:
    bus, devs = _specs(interface, tag)
    host = Host()
    drv = CanDriver(bus, devs, host)
    drv.start()
    peer = can.Bus(interface=interface, channel=tag)
    got = [0]
    try:
        if isinstance(peer, DirectBus):
            def take(msg: can.Message) -> None:
                got[0] += 1
            peer.set_receiver(take)
            for k in range(n):
                assert drv.write_now("v", k & 0xFFFF)
        else:
            for k in range(n):
                assert drv.write_now("v", k & 0xFFFF)
                while peer.recv(0) is not None:
                    got[0] += 1
        while got[0] < n and peer.recv(1) is not None:
            got[0] += 1
        assert got[0] == n
    finally:
        peer.shutdown()
        drv.stop()
    return n


SECTIONS: list[tuple[str, Callable[[str, int, str], int]]] = [
    ("bus alone (send + take one frame)", bus_alone),
    ("raw CAN driver receiving (decode, hand to the host)", driver_receive),
    ("raw CAN driver sending (write_now, the peer takes it)", driver_send)]


def main(argv: Sequence[str] | None = None) -> int:
    """Run the benchmark; prints one table. Exit status 0."""
    ap = argparse.ArgumentParser(prog="python -m tools.bench_direct_can",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--frames", type=int, default=20000, help="frames per round (20000)")
    ap.add_argument("--repeat", type=int, default=3, help="rounds; the best counts (3)")
    args = ap.parse_args(argv)
    print(f"frames per round {args.frames}, best of {args.repeat} (CPU time of every thread)")
    print(f"{'section':<56} {'bus':<14} {'frames/CPU-s':>13} {'frames/s':>11} {'ratio':>7}")
    for title, fn in SECTIONS:
        best: dict[str, tuple[float, float]] = {}
        for r in range(args.repeat):
            for interface in ("virtual", "chcos-direct"):
                tag = f"bench-{fn.__name__}-{interface}-{r}"
                cpu, wall = measure(functools.partial(fn, interface, args.frames, tag))
                old = best.get(interface, (0.0, 0.0))
                best[interface] = (max(old[0], cpu), max(old[1], wall))
        base = best["virtual"][0]
        for interface in ("virtual", "chcos-direct"):
            cpu, wall = best[interface]
            print(f"{title:<56} {interface:<14} {cpu:>13,.0f} {wall:>11,.0f} "
                  f"{cpu / base:>6.2f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
