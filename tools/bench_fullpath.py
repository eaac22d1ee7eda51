#!/usr/bin/env python3
"""bench_fullpath - sensor frame in -> driver task -> actuator frame out, on python-can's virtual
bus, beside the raw virtual-bus send+receive rate measured in the same run.

The peer (a second python-can ``virtual`` bus on the same channel) keeps up to ``--window``
sensor frames unanswered; chcos decodes each one (raw CAN addressing), the driver task reads it
from a queued link (every frame matters here) and writes an actuator frame carrying the same
value; the peer counts the answers. Pin it to one core with ``taskset -c 0``.
Targets (issue 3): >= 20,000 loops/s and >= 0.25 of the raw virtual-bus rate.
Usage: python -m tools.bench_fullpath [--loops N] [--window W] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import can

from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext

MAP = """
[[bus]]
name = "can0"
kind = "can"
interface = "virtual"
channel = "{channel}"
poll = 0.05

[[device]]
name = "S"
direction = "sensor"
bus = "can0"
address = {{ id = 0x101, start = 0, length = 32, dlc = 4 }}

[[device]]
name = "A"
direction = "actuator"
bus = "can0"
address = {{ id = 0x201, start = 0, length = 32, dlc = 4 }}
"""


async def echo(ctx: TaskContext, cmd: Any) -> None:
    """The driver task: every sensor value straight back out on the actuator."""
    read, write = ctx.read, ctx.write
    while True:
        write("A", await read("S"))


def raw_rate(n: int, channel: str) -> float:
    """Frames/s for send + receive on python-can's virtual bus (one thread)."""
    a = can.Bus(interface="virtual", channel=channel)
    b = can.Bus(interface="virtual", channel=channel)
    msg = can.Message(arbitration_id=0x101, data=b"\x00\x00\x00\x01", is_extended_id=False)
    t0 = time.perf_counter()
    for _ in range(n):
        a.send(msg)
        b.recv(1.0)
    dt = time.perf_counter() - t0
    a.shutdown()
    b.shutdown()
    return n / dt


def full_path(n: int, window: int, channel: str) -> float:
    """Loops/s through chcos."""
    tmp = Path(tempfile.mkdtemp())
    (tmp / "bench.toml").write_text(MAP.format(channel=channel))
    system = System([tmp / "bench.toml"], clock=RealClock(), machines=[0], base_dir=tmp)
    system.execute("install -m0i1o1 --queue=S=4096 --code=tools.bench_fullpath:echo E S A")
    system.invoke("E")
    system.start()
    peer = can.Bus(interface="virtual", channel=channel, receive_own_messages=False)
    answered = 0
    sent = 0
    free = threading.Semaphore(window)
    done = threading.Event()

    def listen() -> None:
        nonlocal answered
        while answered < n:
            m = peer.recv(5.0)
            if m is None:
                break
            if m.arbitration_id == 0x201:
                answered += 1
                free.release()
        done.set()

    listener = threading.Thread(target=listen, daemon=True)
    listener.start()
    t0 = time.perf_counter()
    while sent < n:
        free.acquire()
        peer.send(can.Message(arbitration_id=0x101, data=sent.to_bytes(4, "little"),
                              is_extended_id=False))
        sent += 1
    done.wait(60)
    dt = time.perf_counter() - t0
    system.shutdown()
    peer.shutdown()
    if answered != n:
        raise SystemExit(f"only {answered} of {n} loops answered")
    return n / dt


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=20_000)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--json")
    args = ap.parse_args()
    raw = path = 0.0
    for r in range(args.repeat):  # interleaved, best of R
        raw = max(raw, raw_rate(args.loops, f"bench-raw-{os.getpid()}-{r}"))
        path = max(path, full_path(args.loops, args.window, f"bench-path-{os.getpid()}-{r}"))
    print(f"cores allowed: {len(os.sched_getaffinity(0))}")
    print(f"raw python-can virtual send+recv : {raw:10,.0f} frames/s")
    print(f"chcos full path (frame->task->frame): {path:10,.0f} loops/s  "
          f"= {path / raw:.2f} of raw")
    print(f"targets: >= 20,000 loops/s ({'met' if path >= 20_000 else 'MISSED'}), "
          f">= 0.25 of raw ({'met' if path / raw >= 0.25 else 'MISSED'})")
    if args.json:
        Path(args.json).write_text(json.dumps({"raw_frames_per_s": raw, "loops_per_s": path,
                                               "ratio": path / raw}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
