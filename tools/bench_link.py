"""bench_link - figures for the chcos inter-satellite link (Zenoh on loopback, two processes).

First, without the link, what a seal costs by itself: microseconds per message to seal, to
open, and both (a sender's seal and a receiver's open of a 64 B and a 1 KiB payload), beside a
bare serialize of a link message of that size (:func:`chcos.comm.codec.encode` and
:func:`chcos.comm.codec.encode_batch`, what every put does anyway) measured in the same rounds;
each figure is CPU time of this thread (``time.thread_time``: what other processes' load does
not add to), the best of ``--rounds`` interleaved rounds, and the ratio seal+open / serialize is
the figure to compare between runs.

Then, in the same run, for the bare link and for the link as satellites use it (every payload
sealed: encrypted with AES-256-GCM, sender, run, sequence number and time stamp checked against
replays, see :mod:`chcos.comm.secret`):

* round-trip latency p50/p90/p99/max of a ping published by this process, echoed by a child
  process and received back, at ``--rate`` messages/s for ``--seconds`` (target: p99 < 1 ms);
  each ping is sealed and opened twice on the way (there and back);
* raw one-way throughput (messages/s, MB/s) of ``--count`` messages sent as fast as the link
  takes them (congestion control BLOCK, so nothing is dropped) for two payload sizes, with the
  sender's CPU time per message (all its threads: a figure a loaded machine does not distort
  as it does the wall-clock rates);

then the sealed figures beside the bare ones (ratio), and how long after ``kill -9`` of the
child its liveliness token is seen gone. With ``--pin`` this process and its child each run on
a CPU of their own, as pinned satellites.

Usage: ``python tools/bench_link.py [--rate 5000] [--seconds 5] [--count 200000] [--pin]
[--rounds 9] [--micro-only]``.
Only 127.0.0.1 is used, on free ports.
"""

from __future__ import annotations

import argparse
import os
import queue
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from chcos.comm import LinkConfig, MessageKind, Transport
from chcos.comm.codec import LinkMessage, encode, encode_batch
from chcos.comm.qos import band_of
from chcos.comm.secret import load_or_create
from chcos.helpers import free_ports
from chcos.system.affinity import pin_process

REPO = Path(__file__).resolve().parent.parent
PING = "bench/ping"
PONG = "bench/pong"
BULK = "bench/bulk"
COUNT = "bench/count"
ALIVE = "bench/alive/echo"
STAMP = struct.Struct(">QQ")  # sequence number, send time (perf_counter_ns of the sender)


def _link(listen: int, connect: int, secret: str | None, name: str) -> Transport:
    """A bare transport, or (``secret``: the path of a system secret) one sealing every
    payload as a satellite does."""
    if secret is None:
        return Transport(LinkConfig(listen, (connect,)))
    sealer = load_or_create(Path(secret), "bench").sealer("satellite", name)
    return Transport(LinkConfig(listen, (connect,)), sealer=sealer)


def echo_main(listen: int, connect: int, secret: str | None, cpu: int | None) -> int:
    """The child: echo pings back as pongs, count bulk messages, report counts on request."""
    if cpu is not None:
        pin_process([cpu], "bench_link echo")
    with _link(listen, connect, secret, "echo") as link:
        received = [0]
        lock = threading.Lock()

        def on_ping(_key: str, payload: bytes) -> None:
            link.publish(PONG, payload, priority=95, kind=MessageKind.REPLY)

        def on_bulk(_key: str, _payload: bytes) -> None:
            with lock:
                received[0] += 1

        def count(_payload: bytes) -> bytes:
            with lock:
                n, received[0] = received[0], 0
            return str(n).encode()

        link.subscribe(PING, on_ping)
        link.subscribe(BULK, on_bulk)
        link.serve(COUNT, count)
        link.announce(ALIVE)
        sys.stdin.read()  # until the parent closes our stdin (or kills us)
    return 0


def micro(secret: str, rounds: int, n: int = 5_000) -> dict[str, float]:
    """Seal, open and seal+open of one message (64 B and 1 KiB payloads) against a bare serialize
    of a link message of the same size, in us of this thread's CPU time per message, each the
    best of ``rounds`` interleaved rounds of ``n`` messages; prints them and returns them (keys
    ``"<what> <size>"`` and ``"ratio <size>"``: seal+open / serialize)."""
    keys = load_or_create(Path(secret), "bench")
    tx = keys.sealer("satellite", "m1")
    rx = keys.sealer("satellite", "m0")
    key = "chcos/bench/m/0/msg"
    stream = band_of(60)
    out: dict[str, float] = {}
    for size in (64, 1024):
        message = LinkMessage(MessageKind.SENSORY, "P", "R", 7, 60, 1, time.time_ns(),
                              "x" * (size - 40))
        payload = encode_batch([encode(message)])
        best = dict.fromkeys(("serialize", "seal", "open"), float("inf"))
        for _ in range(rounds):
            t0 = time.thread_time()
            for _ in range(n):
                encode_batch([encode(message)])
            t1 = time.thread_time()
            sealed = [tx.seal(key, payload, stream) for _ in range(n)]
            t2 = time.thread_time()
            for data in sealed:
                rx.open(key, data, 1)
            t3 = time.thread_time()
            for what, dt in (("serialize", t1 - t0), ("seal", t2 - t1), ("open", t3 - t2)):
                best[what] = min(best[what], dt / n * 1e6)
        both = best["seal"] + best["open"]
        ratio = both / best["serialize"]
        out.update({f"{w} {size}": v for w, v in best.items()})
        out[f"seal+open {size}"] = both
        out[f"ratio {size}"] = ratio
        print(f"seal {len(payload):>5} B: seal {best['seal']:.2f} us, open {best['open']:.2f} "
              f"us, seal+open {both:.2f} us/message; bare serialize {best['serialize']:.2f} "
              f"us (seal+open / serialize x{ratio:.2f}); thread CPU time, best of {rounds} rounds "
              f"of {n}")
    return out


def _percentile(sorted_values: list[float], p: float) -> float:
    index = min(len(sorted_values) - 1, max(0, round(p / 100 * (len(sorted_values) - 1))))
    return sorted_values[index]


def latency(link: Transport, rate: int, seconds: float) -> dict[str, float]:
    """Ping at ``rate``/s for ``seconds``; print round-trip percentiles and return them."""
    rtts: list[float] = []
    done = threading.Event()
    total = int(rate * seconds)

    def on_pong(_key: str, payload: bytes) -> None:
        now = time.perf_counter_ns()
        seq, sent = STAMP.unpack(payload)
        rtts.append((now - sent) / 1000.0)
        if seq == total - 1:
            done.set()

    sub = link.subscribe(PONG, on_pong)
    # warm up: the first messages pay for route and publisher set-up
    for i in range(200):
        link.publish(
            PING,
            STAMP.pack(10**9 + i, time.perf_counter_ns()),
            priority=95,
            kind=MessageKind.COMMAND,
        )
    time.sleep(0.5)
    rtts.clear()
    period = 1.0 / rate
    start = time.perf_counter()
    late = 0
    for seq in range(total):
        due = start + seq * period
        now = time.perf_counter()
        if due > now:  # sleep, never spin: a spinning thread holds the GIL from the callbacks
            time.sleep(due - now)
            now = time.perf_counter()
        if now - due > period:
            late += 1
        link.publish(
            PING, STAMP.pack(seq, time.perf_counter_ns()), priority=95, kind=MessageKind.COMMAND
        )
    sent_for = time.perf_counter() - start
    done.wait(5.0)
    sub.close()
    got = sorted(rtts)
    if not got:
        print("latency: no pong received")
        return {}
    print(
        f"round trip at {rate} msg/s for {seconds:g} s ({total} pings, sent in {sent_for:.2f} s, "
        f"{late} sent late, {total - len(got)} lost):"
    )
    print(
        f"  p50 {_percentile(got, 50):.1f} us   p90 {_percentile(got, 90):.1f} us   "
        f"p99 {_percentile(got, 99):.1f} us   p99.9 {_percentile(got, 99.9):.1f} us   "
        f"max {got[-1]:.1f} us   target p99 < 1000 us: "
        f"{'met' if _percentile(got, 99) < 1000 else 'NOT met'}"
    )
    return {"p50": _percentile(got, 50), "p99": _percentile(got, 99), "max": got[-1]}


def throughput(link: Transport, count: int, size: int) -> tuple[float, float]:
    """Send ``count`` messages of ``size`` bytes as fast as possible; print the rates and
    return the messages per second received and this process's CPU time per message sent
    (us; all its threads, so it holds on a loaded machine where wall-clock rates do not)."""
    payload = bytes(size)
    link.request(COUNT, timeout=5.0)  # reset the child's counter
    start = time.perf_counter()
    cpu = time.process_time()
    for _ in range(count):
        link.publish(BULK, payload, priority=30, kind=MessageKind.COMMAND)
    cpu_us = (time.process_time() - cpu) / count * 1e6
    sent = time.perf_counter() - start
    # the count request travels behind the bulk data on the same link, in order, but at a
    # higher priority: poll until everything arrived
    total = 0
    deadline = time.monotonic() + 30
    while total < count and time.monotonic() < deadline:
        total += int(link.request(COUNT, timeout=5.0, priority=0))
    elapsed = time.perf_counter() - start
    print(
        f"throughput {size:>5} B: {count} sent in {sent:.2f} s, {total} received in "
        f"{elapsed:.2f} s: {total / elapsed:,.0f} msg/s, {total * size / elapsed / 1e6:.1f} MB/s, "
        f"sender CPU {cpu_us:.1f} us/msg"
    )
    return total / elapsed, cpu_us


def kill_detection(link: Transport, child: subprocess.Popen[str]) -> None:
    """Kill -9 the child and print how long its token took to vanish."""
    gone = threading.Event()
    link.watch(ALIVE, lambda _k: None, lambda _k: gone.set())
    start = time.perf_counter()
    child.kill()
    seen = gone.wait(10.0)
    elapsed = (time.perf_counter() - start) * 1000
    child.wait(10)
    print(
        f"kill -9 of the echo process seen as a leave after {elapsed:.1f} ms"
        if seen
        else "kill -9: leave NOT seen within 10 s"
    )


def measure(secret: str | None, a: argparse.Namespace, last: bool) -> dict[str, float]:
    """One echo child and this process on a bare (``secret`` None) or sealed link: latency and
    throughput figures; ``last``: also kill the child and time the leave."""
    me, child_port = free_ports(2)
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    extra = (["--secret", secret] if secret else []) + (
        ["--cpu", str(_cpu(1))] if a.pin else [])
    with _link(me, child_port, secret, "bench") as link:
        joined: queue.Queue[str] = queue.Queue()
        watcher = link.watch(ALIVE, joined.put, lambda _k: None)
        child = subprocess.Popen(
            [sys.executable, __file__, "--echo", str(child_port), str(me), *extra],
            env=env,
            stdin=subprocess.PIPE,
            text=True,
        )
        try:
            joined.get(timeout=10)
            watcher.close()
            print("sealed link (AES-256-GCM, replay window, time stamps):" if secret
                  else "bare link (no seal):")
            figures = latency(link, a.rate, a.seconds)
            for size in (64, 1024):
                rate, cpu_us = throughput(link, a.count, size)
                figures[f"msg/s {size} B"] = rate
                figures[f"cpu {size} B"] = cpu_us
            if last:
                kill_detection(link, child)
        finally:
            if child.poll() is None:
                child.kill()
                child.wait(10)
    return figures


def _cpu(n: int) -> int:
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[n % len(cpus)]


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark (or, with ``--echo``, be its child)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    p.add_argument("--rate", type=int, default=5000)
    p.add_argument("--seconds", type=float, default=5.0)
    p.add_argument("--count", type=int, default=200_000)
    p.add_argument("--rounds", type=int, default=15,
                   help="rounds of the seal micro-benchmark (its figures: the best round)")
    p.add_argument("--micro-only", action="store_true",
                   help="only the seal micro-benchmark (no link)")
    p.add_argument("--pin", action="store_true",
                   help="this process and the echo child each on a CPU of their own")
    p.add_argument("--echo", nargs=2, type=int, metavar=("LISTEN", "CONNECT"), help="internal")
    p.add_argument("--secret", help="internal: the echo child seals with this secret")
    p.add_argument("--cpu", type=int, help="internal: the echo child's CPU")
    a = p.parse_args(argv)
    if a.echo is not None:
        return echo_main(a.echo[0], a.echo[1], a.secret, a.cpu)
    if a.pin:
        pin_process([_cpu(0)], "bench_link")
    load = ", ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"python {sys.version.split()[0]}, {os.cpu_count()} CPUs, load {load}, loopback TCP"
          f"{', pinned' if a.pin else ''}")
    with tempfile.TemporaryDirectory(prefix="chcos-bench-link-") as tmp:
        secret = str(Path(tmp) / "secret.json")
        load_or_create(Path(secret), "bench")
        micro(secret, a.rounds)
        if a.micro_only:
            return 0
        bare = measure(None, a, last=False)
        sealed = measure(secret, a, last=True)
    if bare and sealed and "p99" in bare and "p99" in sealed:
        print(f"sealed / bare, same run: p50 {sealed['p50']:.1f} / {bare['p50']:.1f} us "
              f"(x{sealed['p50'] / bare['p50']:.2f}), p99 {sealed['p99']:.1f} / "
              f"{bare['p99']:.1f} us (x{sealed['p99'] / bare['p99']:.2f}); sealed p99 < 1000 us: "
              f"{'met' if sealed['p99'] < 1000 else 'NOT met'}")
        for size in (64, 1024):
            k = f"msg/s {size} B"
            c = f"cpu {size} B"
            print(f"  throughput {size} B: {sealed[k]:,.0f} / {bare[k]:,.0f} msg/s "
                  f"(x{sealed[k] / bare[k]:.2f}); sender CPU {sealed[c]:.1f} / {bare[c]:.1f} "
                  f"us/msg (+{sealed[c] - bare[c]:.1f} us to seal)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
