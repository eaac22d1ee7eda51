#!/usr/bin/env python3
"""bench_core - task-to-task sensory message transfer through the chcos kernel, beside a minimal
priority-heap kernel, asyncio and heapq doing the same exchange in the same run.

Prints, measured side by side in one run on one core:
- messages/s delivered from a producer task to a consumer task (newest-wins link, the consumer
  at a higher priority so every message is read before the next is sent), with no instrument,
  and with an idle instrument installed (hooks present, doing nothing); also through
  ``read_any`` instead of ``read``;
- the same exchange on a minimal priority kernel (:func:`run_minimal`: coroutines stepped with
  ``send``, a ``heapq`` ready queue, a one-slot newest-wins port, a waiter woken by the put) -
  the floor for a pure-Python priority kernel - in alternating short runs beside chcos
  (:func:`paired_ratio`); and on asyncio with a ``Queue`` and with an
  ``Event`` plus a slot (the consumer awaits, the producer yields with ``sleep(0)``);
- the time of a bare ``heapq`` push and pop of the same count, and the ratio per message;
- the bytecode instructions each message costs in chcos and in the minimal kernel (counted with
  an opcode tracer over 2,000 messages: a figure the machine's load cannot move).
Targets (issue 2, issue 21): >= 300,000 messages/s; <= 12x the heapq push+pop time per message;
<= 1.5x the minimal heap kernel; >= 2x asyncio Queue / Event. Issue 40's guard: >= 500,000
messages/s, set when chcos (hand-inlined) measured 1,090,748 messages/s at 1.43x the minimal
kernel's time (table of 2026-11-25 01:45 UTC): the same guard on any host is chcos at most
:data:`GUARD_VS_MINIMAL` times the minimal kernel's time per message, measured beside it. Issue 40
gave the hand-inlining's margin (the old 1.5x target) to clarity; that guard replaces it.
With ``--where`` it only counts chcos' instructions per message, by function: where a message
goes.
Usage: python -m tools.bench_core [--messages N] [--repeat R] [--json FILE] [--where]
"""

from __future__ import annotations

import argparse
import asyncio
import heapq
import json
import statistics
import sys
import time
import types
from collections import Counter
from pathlib import Path
from typing import Any

from chcos.devices.spec import DeviceMap
from chcos.kernel.clock import VirtualClock
from chcos.kernel.instrument import Instrument
from chcos.system.embedded import System
from chcos.user.context import TaskContext

#: every figure is this process' CPU time: on a shared machine, time spent descheduled would
#: otherwise land on whichever side of the comparison happened to be running
_now = time.process_time


async def producer(ctx: TaskContext, n: int) -> None:
    """Send 0..n-1 upward, giving the processor back after each."""
    put = ctx.put
    checkpoint = ctx.checkpoint
    for i in range(n):
        put(i)
        await checkpoint()


async def consumer(ctx: TaskContext, box: list[int]) -> None:
    """Read until the last message arrives."""
    read = ctx.read
    last = box[0] - 1
    count = 0
    while True:
        v = await read(0)
        count += 1
        if v == last:
            box.append(count)
            return


async def consumer_any(ctx: TaskContext, box: list[int]) -> None:
    """Read with ``read_any`` until the last message arrives."""
    read_any = ctx.read_any
    last = box[0] - 1
    count = 0
    while True:
        _port, v = await read_any()
        count += 1
        if v == last:
            box.append(count)
            return


#: issue 40's guard as a ratio to the minimal kernel measured in the same run: 500,000 msg/s was
#: asked where chcos did 1,090,748 msg/s at 1.43x the minimal kernel (1.43 * 1,090,748 / 500,000)
GUARD_VS_MINIMAL = 3.1


def run_chcos(n: int, instrument: bool, any_port: bool = False,
              measure: Any = None) -> tuple[float, int]:
    """Seconds to move ``n`` messages, and how many the consumer received (``any_port``: the
    consumer reads with ``read_any``; ``measure(run)``, if given, runs the exchange instead of
    timing it)."""
    s = System(DeviceMap(), clock=VirtualClock(), machines=[0], base_dir=Path("."))
    if instrument:
        s.kernel.add_instrument(Instrument())
    s.execute("install -m0 --code=tools.bench_core:producer P")
    fn = "consumer_any" if any_port else "consumer"
    s.execute(f"install -m0i1 --code=tools.bench_core:{fn} C P")
    box = [n]
    s.invoke("C", box, priority=50)
    s.run()  # C now waits for its first message
    s.invoke("P", n, priority=10)
    if measure is not None:
        measure(s.run)
        return 0.0, box[1]
    t0 = _now()
    s.run()
    dt = _now() - t0
    return dt, box[1]


# ---- the minimal priority-heap kernel: the same exchange with nothing but what it needs -------
_MIN_YIELD = object()
_MIN_BLOCK = object()


class _MinTask:
    """A task of the minimal kernel: its coroutine, priority, and the value to send in."""

    __slots__ = ("coro", "prio", "value")

    def __init__(self, coro: Any, prio: int) -> None:
        self.coro = coro
        self.prio = prio
        self.value: Any = None


class _MinPort:
    """A one-slot newest-wins input port with one waiter."""

    __slots__ = ("fresh", "value", "waiter")

    def __init__(self) -> None:
        self.value: Any = None
        self.fresh = False
        self.waiter: _MinTask | None = None


class _MinKernel:
    """A priority kernel reduced to its floor: a heap of (-priority, sequence, task), coroutines
    stepped with ``send``, a put that stores into the port and readies its waiter."""

    def __init__(self) -> None:
        self.ready: list[tuple[int, int, _MinTask]] = []
        self.seq = 0

    def wake(self, t: _MinTask) -> None:
        self.seq += 1
        heapq.heappush(self.ready, (-t.prio, self.seq, t))

    def put(self, port: _MinPort, value: Any) -> None:
        port.value = value
        port.fresh = True
        w = port.waiter
        if w is not None:
            port.waiter = None
            self.wake(w)

    @types.coroutine
    def read(self, t: _MinTask, port: _MinPort) -> Any:
        if not port.fresh:
            port.waiter = t
            yield _MIN_BLOCK
        port.fresh = False
        return port.value

    @types.coroutine
    def checkpoint(self) -> Any:
        yield _MIN_YIELD

    def run(self) -> None:
        ready = self.ready
        pop, push = heapq.heappop, heapq.heappush
        while ready:
            _p, _s, t = pop(ready)
            try:
                trap = t.coro.send(None)
            except StopIteration:
                continue
            if trap is _MIN_YIELD:
                self.seq += 1
                push(ready, (-t.prio, self.seq, t))


def run_minimal(n: int, measure: Any = None) -> tuple[float, int]:
    """Seconds for the minimal heap kernel to move ``n`` messages producer -> consumer (the
    consumer at the higher priority), and how many the consumer received (``measure`` as in
    :func:`run_chcos`)."""
    k = _MinKernel()
    port = _MinPort()
    box: list[int] = []

    async def prod() -> None:
        put, checkpoint = k.put, k.checkpoint
        for i in range(n):
            put(port, i)
            await checkpoint()

    async def cons(t: _MinTask) -> None:
        read = k.read
        count = 0
        while True:
            v = await read(t, port)
            count += 1
            if v == n - 1:
                box.append(count)
                return

    c = _MinTask(None, 50)
    c.coro = cons(c)
    k.wake(c)
    k.run()  # C now waits for its first message
    k.wake(_MinTask(prod(), 10))
    if measure is not None:
        measure(k.run)
        return 0.0, box[0]
    t0 = _now()
    k.run()
    return _now() - t0, box[0]


#: alternating runs per batch in the comparison with the minimal kernel (see paired_ratio)
PAIRS = 10


def paired_ratio(n: int, pairs: int = PAIRS) -> tuple[float, float, float]:
    """chcos' time per message over the minimal heap kernel's, from ``pairs`` alternating runs
    of ``n // pairs`` messages each (chcos, minimal, chcos, minimal...): the median of the
    per-pair ratios, so that a slow spell of the shared machine (it moves a whole 300,000-message
    run of either by up to 2x) falls on both sides of a pair instead of on one side of the
    batch; and each side's seconds per message over all its runs. Raises AssertionError if a
    consumer misses a message."""
    k = max(1, n // pairs)
    ratios: list[float] = []
    tc = tm = 0.0
    for _ in range(pairs):
        a, got_a = run_chcos(k, False)
        b, got_b = run_minimal(k)
        assert got_a == k and got_b == k, f"delivered {got_a} / {got_b} of {k}"
        ratios.append(a / b)
        tc += a
        tm += b
    return statistics.median(ratios), tc / (k * pairs), tm / (k * pairs)


def count_instructions(runner: Any, n: int = 2000,
                       where: Counter[str] | None = None) -> float:
    """Bytecode instructions per message of ``runner(n, measure=...)`` (:func:`run_chcos` or
    :func:`run_minimal`), counted by an opcode tracer over the exchange only: every instruction
    executed in Python code, the kernel's, the tasks' and the baseline's alike (C code, such as
    ``heapq``, counts as the one call instruction that enters it). ``where``, if given, gets
    the instructions counted by function (``module.qualname``)."""
    count = 0

    def tracer(frame: types.FrameType, event: str, arg: Any) -> Any:
        nonlocal count
        frame.f_trace_opcodes = True
        frame.f_trace_lines = False
        if event == "opcode":
            count += 1
            if where is not None:
                code = frame.f_code
                where[f"{frame.f_globals.get('__name__')}.{code.co_qualname}"] += 1
        return tracer

    def measure(run: Any) -> None:
        sys.settrace(tracer)
        try:
            run()
        finally:
            sys.settrace(None)

    _dt, got = runner(n, measure=measure)
    assert got == n, f"delivered {got} of {n}"
    return count / n


def run_asyncio_queue(n: int) -> tuple[float, int]:
    """Seconds for asyncio to move ``n`` messages through a ``Queue`` (the producer yields with
    ``sleep(0)`` after each put), and how many the consumer received."""
    async def main() -> tuple[float, int]:
        q: asyncio.Queue[int] = asyncio.Queue()
        got: list[int] = []

        async def cons() -> None:
            get = q.get
            count = 0
            while True:
                v = await get()
                count += 1
                if v == n - 1:
                    got.append(count)
                    return

        task = asyncio.ensure_future(cons())
        await asyncio.sleep(0)
        t0 = _now()
        put, sleep = q.put_nowait, asyncio.sleep
        for i in range(n):
            put(i)
            await sleep(0)
        await task
        return _now() - t0, got[0]
    return asyncio.run(main())


def run_asyncio_event(n: int) -> tuple[float, int]:
    """Seconds for asyncio to move ``n`` messages through a one-slot newest-wins port signalled
    by an ``Event``, and how many the consumer received."""
    async def main() -> tuple[float, int]:
        ev = asyncio.Event()
        slot: list[int] = [0]
        got: list[int] = []

        async def cons() -> None:
            wait, clear = ev.wait, ev.clear
            count = 0
            while True:
                await wait()
                clear()
                v = slot[0]
                count += 1
                if v == n - 1:
                    got.append(count)
                    return

        task = asyncio.ensure_future(cons())
        await asyncio.sleep(0)
        t0 = _now()
        setev, sleep = ev.set, asyncio.sleep
        for i in range(n):
            slot[0] = i
            setev()
            await sleep(0)
        await task
        return _now() - t0, got[0]
    return asyncio.run(main())


def run_heapq(n: int) -> float:
    """Seconds for a bare heapq push of ``n`` entries (shaped as the ready queue's) and ``n``
    pops: "a bare heapq push and pop of the same count"."""
    h: list[tuple[int, int, Any]] = []
    push, pop = heapq.heappush, heapq.heappop
    t0 = _now()
    for i in range(n):
        push(h, (-(i % 100), i, None))
    for _ in range(n):
        pop(h)
    return _now() - t0


def run_heapq_pairs(n: int) -> float:
    """Seconds for ``n`` push+pop pairs on a one-entry heap (a stricter baseline)."""
    h: list[tuple[int, int, Any]] = [(-5, 0, None)]
    push, pop = heapq.heappush, heapq.heappop
    t0 = _now()
    for i in range(n):
        push(h, (-10, i, None))
        pop(h)
    return _now() - t0


def _mmm(xs: list[float]) -> str:
    """min / median / max of per-run figures."""
    return f"{min(xs):.3f} / {statistics.median(xs):.3f} / {max(xs):.3f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--messages", type=int, default=300_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", help="write the figures to this file")
    ap.add_argument("--where", action="store_true",
                    help="only count chcos' instructions per message, by function")
    args = ap.parse_args()
    if args.where:
        where: Counter[str] = Counter()
        n = 2000
        total = count_instructions(lambda k, measure: run_chcos(k, False, measure=measure), n,
                                   where)
        print(f"bytecode instructions per message: chcos {total:.0f}, by function:")
        for name, c in where.most_common():
            if c >= n / 2:
                print(f"  {c / n:6.1f}  {name}")
        return 0
    n = args.messages
    runs: dict[str, list[float]] = {}
    vs_min: list[float] = []
    for _ in range(args.repeat):  # interleaved, side by side: the machine is shared and noisy
        med_ratio, per_c, per_m = paired_ratio(n)
        vs_min.append(med_ratio)
        runs.setdefault("plain", []).append(per_c * n)
        runs.setdefault("minimal", []).append(per_m * n)
        for name, fn in (("idle_instrument", lambda: run_chcos(n, True)),
                         ("read_any", lambda: run_chcos(n, False, any_port=True)),
                         ("asyncio_queue", lambda: run_asyncio_queue(n)),
                         ("asyncio_event", lambda: run_asyncio_event(n)),
                         ("heapq", lambda: (run_heapq(n), n)),
                         ("heapq_pairs", lambda: (run_heapq_pairs(n), n))):
            dt, got = fn()
            assert got == n, f"{name}: delivered {got} of {n}"
            runs.setdefault(name, []).append(dt)
    best = {k: min(v) for k, v in runs.items()}
    us = {k: [dt / n * 1e6 for dt in v] for k, v in runs.items()}
    rate = n / best["plain"]
    rate_i = n / best["idle_instrument"]
    ratio = best["plain"] / best["heapq"]
    ratio_i = best["idle_instrument"] / best["heapq"]
    # per-run ratios: each run's chcos figure against the baseline measured beside it
    per_run = {b: [p / q for p, q in zip(runs["plain"], runs[b], strict=True)]
               for b in ("asyncio_queue", "asyncio_event", "heapq_pairs")}
    vs_q = [1 / r for r in per_run["asyncio_queue"]]
    vs_e = [1 / r for r in per_run["asyncio_event"]]
    any_ratio = [a / p for a, p in zip(runs["read_any"], runs["plain"], strict=True)]
    print(f"messages: {n}, {args.repeat} runs side by side; us/msg min / median / max")
    rows = (("chcos read, no instrument", "plain"), ("chcos read, idle instrument",
            "idle_instrument"), ("chcos read_any, no instrument", "read_any"),
            ("minimal heap kernel (same exchange)", "minimal"),
            ("asyncio Queue + sleep(0)", "asyncio_queue"),
            ("asyncio Event + slot + sleep(0)", "asyncio_event"),
            ("heapq push N, pop N (per pair)", "heapq"),
            ("heapq push+pop on a tiny heap", "heapq_pairs"))
    for label, key in rows:
        print(f"  {label:<38}: {_mmm(us[key])} us  ({n / best[key]:12,.0f} /s best)")
    print(f"chcos / minimal heap kernel        : {_mmm(vs_min)}x  (median of {PAIRS} "
          f"alternating pairs per batch; target <= 1.5x: "
          f"{'met' if statistics.median(vs_min) <= 1.5 else 'MISSED'}; issue 40's guard "
          f"<= {GUARD_VS_MINIMAL}x: "
          f"{'met' if statistics.median(vs_min) <= GUARD_VS_MINIMAL else 'MISSED'})")
    print(f"asyncio Queue / chcos (speed-up)   : {_mmm(vs_q)}x  (target >= 2x: "
          f"{'met' if statistics.median(vs_q) >= 2 else 'MISSED'})")
    print(f"asyncio Event / chcos (speed-up)   : {_mmm(vs_e)}x  (target >= 2x: "
          f"{'met' if statistics.median(vs_e) >= 2 else 'MISSED'})")
    print(f"chcos read_any / read              : {_mmm(any_ratio)}x")
    ops_c = count_instructions(lambda k, measure: run_chcos(k, False, measure=measure))
    ops_m = count_instructions(run_minimal)
    print(f"bytecode instructions per message  : chcos {ops_c:.0f}, minimal heap kernel "
          f"{ops_m:.0f}: {ops_c / ops_m:.2f}x (counted, not timed: the load cannot move it)")
    print(f"chcos / heapq push N pop N         : {ratio:.1f}x (idle instrument {ratio_i:.1f}x); "
          f"/ one push+pop pair on a tiny heap: {_mmm(per_run['heapq_pairs'])}x")
    print(f"targets: >= 300,000 msg/s ({'met' if min(rate, rate_i) >= 300_000 else 'MISSED'}); "
          f"<= 12x heapq ({'met' if max(ratio, ratio_i) <= 12 else 'MISSED'}); issue 40's guard "
          f">= 500,000 msg/s ({'met' if rate >= 500_000 else 'MISSED'}; the minimal kernel "
          f"{n / best['minimal']:,.0f} msg/s here)")
    if args.json:
        Path(args.json).write_text(json.dumps({"messages": n, "msg_per_s": rate,
                                               "msg_per_s_idle_instrument": rate_i,
                                               "ratio_to_heapq": ratio,
                                               "ratio_to_heapq_idle_instrument": ratio_i,
                                               "ratio_to_heapq_pairs":
                                                   best["plain"] / best["heapq_pairs"],
                                               "ratio_to_minimal_kernel": vs_min,
                                               "speedup_vs_asyncio_queue": vs_q,
                                               "speedup_vs_asyncio_event": vs_e,
                                               "read_any_over_read": any_ratio,
                                               "instructions_per_msg": {"chcos": ops_c,
                                                                        "minimal": ops_m},
                                               "us_per_msg": us}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
