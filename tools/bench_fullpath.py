#!/usr/bin/env python3
"""bench_fullpath - sensor frame in -> driver task -> actuator frame out, on python-can's virtual
bus, beside the raw virtual-bus send+receive rate and a hand-written asyncio program doing the
same job, all measured in the same run.

The peer (a second python-can ``virtual`` bus on the same channel) keeps up to ``--window``
sensor frames unanswered; chcos decodes each one (raw CAN addressing, cantools underneath), the
driver task reads it from a queued link (every frame matters here) and writes an actuator frame
carrying the same value; the peer counts the answers. Each figure includes the peer's sending and
counting (the same peer code for every program). The hand-written alternatives are what an
integrator would write without chcos: asyncio, ``can.Notifier`` with an ``AsyncBufferedReader``,
decoding and encoding with cantools (and, second, with ``int.from_bytes`` instead of cantools),
sending straight from the coroutine; chcos' CAN driver sends from the task's thread as well (its
fast path; it prints how many frames took it). Pin it to one core with ``taskset -c 0``.
Beside the timed figures it counts the bytecode instructions each program executes per loop, in
every thread, by where the code lives (:func:`count_instructions`): a figure the machine's noise
does not move, which shows how much of a loop is chcos' own code and how much python-can's.
Targets (issue 3, issue 21): >= 20,000 loops/s, >= 0.25 (issue 21: >= 0.33) of the raw
virtual-bus rate, >= 1.0x the asyncio + can.Notifier + cantools program.
Each batch runs the programs in alternating short rounds (:func:`paired_batch`) and takes
each ratio as the median of the rounds' ratios.
Usage: python -m tools.bench_fullpath [--loops N] [--pairs P] [--window W] [--repeat R]
[--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import statistics
import sys
import tempfile
import threading
import time
import types
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can
import cantools
from cantools.database.can import Message as DbcMessage
from cantools.database.can import Signal as DbcSignal

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
    _counting[0] = True
    t0 = time.perf_counter()
    for _ in range(n):
        a.send(msg)
        b.recv(1.0)
    dt = time.perf_counter() - t0
    _counting[0] = False
    a.shutdown()
    b.shutdown()
    return n / dt


#: CPU seconds of this process per loop of the last run (peer included), from _peer_loops
last_cpu: list[float] = [0.0]
#: True from the peer's first frame to its last answer: what :func:`count_instructions` counts
_counting: list[bool] = [False]


def _peer_loops(n: int, window: int, channel: str) -> float:
    """The peer: keep up to ``window`` sensor frames unanswered, count the actuator frames;
    loops/s from the first frame sent to the ``n``-th answer (the process' CPU time per loop,
    peer included, goes to :data:`last_cpu`). Raises SystemExit if answers stop."""
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
    _counting[0] = True
    t0 = time.perf_counter()
    c0 = time.process_time()
    while sent < n:
        free.acquire()
        peer.send(can.Message(arbitration_id=0x101, data=sent.to_bytes(4, "little"),
                              is_extended_id=False))
        sent += 1
    done.wait(60)
    dt = time.perf_counter() - t0
    _counting[0] = False
    last_cpu[0] = (time.process_time() - c0) / n
    peer.shutdown()
    if answered != n:
        raise SystemExit(f"only {answered} of {n} loops answered")
    return n / dt


#: frames the chcos driver sent in the last run: (in all, of them on the fast path)
last_sent: list[tuple[int, int]] = [(0, 0)]


def full_path(n: int, window: int, channel: str) -> float:
    """Loops/s through chcos (the driver's frame counts go to :data:`last_sent`)."""
    tmp = Path(tempfile.mkdtemp())
    (tmp / "bench.toml").write_text(MAP.format(channel=channel))
    system = System([tmp / "bench.toml"], clock=RealClock(), machines=[0], base_dir=tmp)
    system.execute("install -m0i1o1 --queue=S=4096 --code=tools.bench_fullpath:echo E S A")
    system.invoke("E")
    system.start()
    try:
        return _peer_loops(n, window, channel)
    finally:
        drv = system.devtab.drivers[0]
        last_sent[0] = (getattr(drv, "sent", 0), getattr(drv, "sent_inline", 0))
        system.shutdown()


def _dbc() -> cantools.database.can.Database:
    """The two messages of the map above as a cantools database (what a DBC file would give)."""
    return cantools.database.can.Database([
        DbcMessage(0x101, "Sensor", 4, [DbcSignal("S", 0, 32)]),
        DbcMessage(0x201, "Actuator", 4, [DbcSignal("A", 0, 32)])])


def handwritten(n: int, window: int, channel: str, use_cantools: bool = True) -> float:
    """Loops/s of the hand-written alternative: asyncio + ``can.Notifier`` (+ cantools), one
    coroutine reading the sensor frame, decoding it and sending the actuator frame."""
    db = _dbc()
    sensor, actuator = db.get_message_by_frame_id(0x101), db.get_message_by_frame_id(0x201)
    started = threading.Event()
    stop: list[asyncio.AbstractEventLoop] = []

    async def program() -> None:
        bus = can.Bus(interface="virtual", channel=channel)
        reader = can.AsyncBufferedReader()
        # a short receive timeout: the notifier's thread ends within it at stop (with the
        # default 1 s each run's tear-down took a second); frames are taken as they come
        notifier = can.Notifier(bus, [reader], timeout=0.05, loop=asyncio.get_running_loop())
        stop.append(asyncio.get_running_loop())
        started.set()
        try:
            while True:
                m = await reader.get_message()
                if m.arbitration_id != 0x101:
                    continue
                if use_cantools:
                    decoded = sensor.decode(bytes(m.data), decode_containers=False)
                    assert isinstance(decoded, dict)
                    value = decoded["S"]
                    data = actuator.encode({"A": value})
                else:
                    data = bytes(m.data[:4])
                bus.send(can.Message(arbitration_id=0x201, data=data, is_extended_id=False))
        finally:
            notifier.stop()
            bus.shutdown()

    def run() -> None:
        with contextlib.suppress(asyncio.CancelledError, RuntimeError):
            asyncio.run(program())

    th = threading.Thread(target=run, daemon=True)
    th.start()
    started.wait(10)
    try:
        return _peer_loops(n, window, channel)
    finally:
        loop = stop[0]
        loop.call_soon_threadsafe(lambda: [t.cancel() for t in asyncio.all_tasks(loop)])
        th.join(10)


#: alternating short runs per batch (see :func:`paired_batch`)
PAIRS = 10
#: the programs of a batch, in the order each round runs them
PROGRAMS = ("raw", "chcos", "asyncio_cantools", "asyncio_bytes")


@dataclass
class Batch:
    """One batch of :func:`paired_batch`: each program's rate per round (frames/s for the raw
    bus, loops/s for the others) and CPU µs per loop (the whole process, peer included), in
    the order of the rounds."""

    rates: dict[str, list[float]] = field(default_factory=dict)
    cpu: dict[str, list[float]] = field(default_factory=dict)
    #: frames chcos' driver sent, and how many of them on its fast path
    sent: tuple[int, int] = (0, 0)

    def rate(self, program: str) -> float:
        """The median of ``program``'s rates over the rounds."""
        return statistics.median(self.rates[program])

    def ratio(self, a: str, b: str) -> float:
        """The median over the rounds of ``a``'s rate over ``b``'s in the same round."""
        return statistics.median(x / y for x, y in zip(self.rates[a], self.rates[b],
                                                       strict=True))


def paired_batch(loops: int, window: int = 64, pairs: int = PAIRS, tag: str = "",
                 programs: tuple[str, ...] = PROGRAMS[:3]) -> Batch:
    """``pairs`` rounds of ``loops // pairs`` loops each, every round running ``programs``
    in turn (the raw bus, chcos, the asyncio + cantools program, the program without
    cantools), each on a channel of its own; ratios are taken within a round and their median
    over the rounds is the batch's (:meth:`Batch.ratio`). Short alternating runs put a slow
    spell of the shared machine (it moves a whole 20,000-loop run by 20 % and more) on both
    sides of a round instead of on one side of the batch. Raises SystemExit if answers stop."""
    k = max(1, loops // pairs)
    b = Batch({p: [] for p in programs}, {p: [] for p in programs if p != "raw"})
    sent = inline = 0
    for i in range(pairs):
        name = f"{tag or os.getpid()}-{i}"
        for p in programs:
            if p == "raw":
                b.rates[p].append(raw_rate(k, f"bench-raw-{name}"))
                continue
            if p == "chcos":
                b.rates[p].append(full_path(k, window, f"bench-path-{name}"))
                sent, inline = sent + last_sent[0][0], inline + last_sent[0][1]
            else:
                b.rates[p].append(handwritten(k, window, f"bench-{p}-{name}",
                                              use_cantools=p == "asyncio_cantools"))
            b.cpu[p].append(last_cpu[0] * 1e6)
    b.sent = (sent, inline)
    return b


def _places() -> tuple[tuple[str, str], ...]:
    """Where an executed bytecode instruction's code lives, as (directory or file prefix, name),
    first match wins: chcos' own code (the ``chcos`` and ``drivers`` packages), this benchmark,
    the cantools and python-can packages, asyncio, and the standard library's modules
    python-can's virtual bus runs (its deepcopy per receiver, its queue, their locks). The
    prefixes are the imported packages' own directories, so a checkout directory that happens
    to be named ``chcos`` or ``can`` does not move code from one place to another."""
    import copy
    import copyreg
    import queue

    import chcos
    import drivers

    def pkg(mod: types.ModuleType) -> str:
        return os.path.dirname(os.path.realpath(mod.__file__ or "")) + os.sep

    def src(mod: types.ModuleType) -> str:
        return os.path.realpath(mod.__file__ or "")

    return ((pkg(chcos), "chcos"), (pkg(drivers), "chcos"), (src(sys.modules[__name__]), "bench"),
            (pkg(cantools), "cantools"), (pkg(can), "python-can"), (pkg(asyncio), "asyncio"),
            (src(copy), "python-can"), (src(copyreg), "python-can"), (src(queue), "python-can"))


def count_instructions(run: Callable[[int], float], n: int = 2000) -> dict[str, float]:
    """Bytecode instructions per loop of ``run(n)`` (:func:`full_path` or a :func:`handwritten`
    program, with a fixed window; per frame for :func:`raw_rate`), every thread of this process
    counted by an opcode tracer from the peer's first frame to its last answer (not the set-up),
    by where the code lives: ``chcos`` (chcos and its drivers), ``python-can`` (the package and
    the standard-library copy/queue code its virtual bus runs), ``cantools``, ``asyncio``,
    ``bench`` (the peer and the hand-written program's own lines) and ``other`` (threading,
    logging...). C code counts as the one call instruction that enters it. Deterministic, unlike
    a timed figure, up to how frames happen to batch; the tracer makes the run ~50x slower."""
    counts: Counter[str] = Counter()
    where: dict[str, str] = {}

    places = _places()

    def place(filename: str) -> str:
        real = os.path.realpath(filename)
        for prefix, name in places:
            if real.startswith(prefix):
                return name
        return "other"

    def tracer(frame: types.FrameType, event: str, arg: Any) -> Any:
        frame.f_trace_opcodes = True
        frame.f_trace_lines = False
        if event == "opcode" and _counting[0]:
            f = frame.f_code.co_filename
            key = where.get(f)
            if key is None:
                key = where[f] = place(f)
            counts[key] += 1
        return tracer

    threading.settrace(tracer)
    sys.settrace(tracer)
    try:
        run(n)
    finally:
        sys.settrace(None)
        threading.settrace(None)
    return {k: v / n for k, v in counts.items()}


def instruction_profile(window: int = 64, n: int = 2000) -> dict[str, dict[str, float]]:
    """:func:`count_instructions` of the raw bus (per frame), chcos' full path and the
    hand-written asyncio + cantools program (per loop), ``n`` each; a channel of their own."""
    tag = f"ops-{os.getpid()}"
    return {"raw": count_instructions(lambda k: raw_rate(k, f"{tag}-raw"), n),
            "chcos": count_instructions(lambda k: full_path(k, window, f"{tag}-path"), n),
            "asyncio_cantools": count_instructions(
                lambda k: handwritten(k, window, f"{tag}-hand"), n)}


def instruction_text(ops: dict[str, dict[str, float]]) -> str:
    """The lines :func:`main` prints for an :func:`instruction_profile`: each program's total
    and where it goes, and the count ratios that mirror the timed ones."""
    tot = {k: sum(v.values()) for k, v in ops.items()}

    def parts(k: str) -> str:
        return ", ".join(f"{name} {v:,.0f}" for name, v in
                         sorted(ops[k].items(), key=lambda kv: -kv[1]) if v >= 1)

    return (f"bytecode instructions (counted, every thread, peer included): raw bus "
            f"{tot['raw']:,.0f} per frame ({parts('raw')}); chcos {tot['chcos']:,.0f} per loop "
            f"({parts('chcos')}); asyncio + cantools program {tot['asyncio_cantools']:,.0f} per "
            f"loop ({parts('asyncio_cantools')}); by count chcos/raw "
            f"{tot['raw'] / tot['chcos']:.2f} (ceiling 0.5), chcos/program "
            f"{tot['asyncio_cantools'] / tot['chcos']:.2f}")


def _mmm(xs: list[float]) -> str:
    """min / median / max of per-run figures."""
    return f"{min(xs):,.2f} / {statistics.median(xs):,.2f} / {max(xs):,.2f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, default=40_000,
                    help="loops per program and batch, run in --pairs alternating rounds")
    ap.add_argument("--pairs", type=int, default=PAIRS)
    ap.add_argument("--window", type=int, default=64)
    ap.add_argument("--repeat", type=int, default=3, help="batches")
    ap.add_argument("--json")
    args = ap.parse_args()
    batches = [paired_batch(args.loops, args.window, args.pairs, f"{os.getpid()}-{r}",
                            PROGRAMS) for r in range(args.repeat)]

    def rates(p: str) -> list[float]:
        return [b.rate(p) for b in batches]

    def ratios(a: str, c: str) -> list[float]:
        return [b.ratio(a, c) for b in batches]

    def cpu(p: str) -> list[float]:
        return [statistics.median(b.cpu[p]) for b in batches]

    vs_raw, vs_hand = ratios("chcos", "raw"), ratios("chcos", "asyncio_cantools")
    vs_bytes = ratios("chcos", "asyncio_bytes")
    sent = [sum(b.sent[0] for b in batches), sum(b.sent[1] for b in batches)]
    print(f"cores allowed: {len(os.sched_getaffinity(0))}; {args.loops} loops per program "
          f"and batch in {args.pairs} alternating rounds, window {args.window}, "
          f"{args.repeat} batches; min / median / max over the batches of each batch's median")
    print(f"raw python-can virtual send+recv (one thread, frames)  : {_mmm(rates('raw'))}")
    print(f"chcos: reader thread, decode, kernel, task sending itself : {_mmm(rates('chcos'))}")
    print(f"asyncio + can.Notifier + cantools decode/encode         : "
          f"{_mmm(rates('asyncio_cantools'))}")
    print(f"asyncio + can.Notifier, bytes copied (no cantools)      : "
          f"{_mmm(rates('asyncio_bytes'))}")
    print("CPU time per loop, whole process (peer, threads, program), us: chcos "
          f"{_mmm(cpu('chcos'))}; asyncio+cantools {_mmm(cpu('asyncio_cantools'))}; "
          f"asyncio, no cantools {_mmm(cpu('asyncio_bytes'))}")
    print(f"chcos' actuator frames sent by the task's own thread (the CAN driver's fast "
          f"path): {sent[1]:,} of {sent[0]:,}; the rest by its writer thread")
    print(f"chcos / raw (the median round's)    : {_mmm(vs_raw)}")
    print(f"chcos / asyncio+Notifier+cantools   : {_mmm(vs_hand)}")
    print(f"chcos / asyncio+Notifier, no cantools: {_mmm(vs_bytes)}")
    med = statistics.median
    path = med(rates("chcos"))
    print(f"targets: >= 20,000 loops/s ({'met' if path >= 20_000 else 'MISSED'}), "
          f">= 0.33 of raw ({'met' if med(vs_raw) >= 0.33 else 'MISSED'}), "
          f">= 1.0x the hand-written asyncio + cantools program "
          f"({'met' if med(vs_hand) >= 1.0 else 'MISSED'}) (medians)")
    ops = instruction_profile(args.window)
    print(instruction_text(ops))
    if args.json:
        Path(args.json).write_text(json.dumps({
            "loops_per_s": path, "pairs": args.pairs,
            "batches": [{"rates": b.rates, "cpu_us_per_loop": b.cpu} for b in batches],
            "ratio_to_raw": vs_raw, "ratio_to_handwritten": vs_hand,
            "ratio_to_handwritten_no_cantools": vs_bytes, "instructions_per_loop": ops}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
