#!/usr/bin/env python3
"""bench_north - does the OPC UA server disturb the control loops? Reaction latency (sensor
interrupt -> task -> actuator write) with no OPC UA server, and with the server and 10 OPC UA
client sessions subscribed to every device (in a separate process), measured side by side in
one run (alternating batches; the machine is noisy).

Eight sensors are fed at ``--rate`` readings/s each from a feeder thread (``Devtab.deliver``,
as a driver does); each task ``T<i>`` reads its sensor and writes the value to its actuator; the
latency is from the feeder's ``perf_counter`` stamp (the value itself) to the actuator write
(Devtab's ``on_write`` hook). Prints p50/p99/max per configuration and the notifications the
clients received.
Usage: python -m tools.bench_north [--seconds S] [--batches N] [--rate HZ] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.kernel.clock import RealClock
from chcos.north.opcua import OpcUaServer
from chcos.north.opcua_process import OpcUaProcess
from chcos.system.embedded import System
from chcos.user.context import TaskContext

N = 8
CLIENTS = """
import asyncio, sys
from asyncua import Client

class H:
    n = 0
    def datachange_notification(self, node, val, data):
        H.n += 1

async def main(url):
    clients = []
    for _ in range(10):
        c = Client(url, timeout=30)
        await c.connect()
        i = await c.get_namespace_index("urn:chcos")
        nodes = [c.get_node(f"ns={i};s=Devices.{p}{k}") for p in "SA" for k in range(N_DEVICES)]
        sub = await c.create_subscription(50, H())
        await sub.subscribe_data_change(nodes)
        clients.append(c)
    print("ready", flush=True)
    await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
    print(H.n, flush=True)
    for c in clients:
        await c.disconnect()

asyncio.run(main(sys.argv[1]))
""".replace("N_DEVICES", str(N))


async def echo(ctx: TaskContext, command: Any) -> None:
    """Copy every reading of the sensor to the actuator."""
    while True:
        _port, value = await ctx.read_any()
        ctx.write(ctx.outputs[0], value)


def build(workdir: Path) -> tuple[System, list[float]]:
    devs = [DeviceSpec(f"S{k}", "sensor", 0, "mem") for k in range(N)] + \
        [DeviceSpec(f"A{k}", "actuator", 0, "mem") for k in range(N)]
    s = System(DeviceMap((BusSpec("mem", "memory"),), tuple(devs)), clock=RealClock(),
               base_dir=workdir)
    s.execute("install -m0 sysfile")
    for k in range(N):
        s.execute(f"install -m0i1o1 --code=tools.bench_north:echo T{k} S{k} A{k}")
        s.execute(f"invoke T{k}")
    lat: list[float] = []

    def on_write(device: str, value: Any) -> None:
        lat.append(time.perf_counter() - value)

    s.devtab.on_write.append(on_write)
    return s, lat


def feed(s: System, seconds: float, rate: float) -> None:
    period = 1.0 / rate
    end = time.perf_counter() + seconds
    nxt = time.perf_counter()
    while nxt < end:
        for k in range(N):
            s.devtab.deliver(f"S{k}", time.perf_counter())
        nxt += period
        delay = nxt - time.perf_counter()
        if delay > 0:
            time.sleep(delay)


def pct(xs: list[float], q: float) -> float:
    ys = sorted(xs)
    return ys[min(len(ys) - 1, int(q * len(ys)))] * 1e3


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seconds", type=float, default=5.0, help="per batch")
    ap.add_argument("--batches", type=int, default=3)
    ap.add_argument("--rate", type=float, default=200.0, help="readings/s per sensor")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument("--switch", type=float, help="sys.setswitchinterval for the run (seconds)")
    args = ap.parse_args()
    if args.switch:
        sys.setswitchinterval(args.switch)
    with tempfile.TemporaryDirectory() as tmp:
        s, lat = build(Path(tmp))
        s.start()
        kinds: dict[str, Any] = {"with 10 clients, server in a process": OpcUaProcess,
                                 "with 10 clients, server on a thread": OpcUaServer}
        results: dict[str, list[float]] = {"without OPC UA": [], **{k: [] for k in kinds}}
        notes = 0
        try:
            for _ in range(args.batches):
                for name in results:
                    proc = None
                    if name in kinds:
                        server = kinds[name](s, "opc.tcp://127.0.0.1:0/chcos/").start()
                        proc = subprocess.Popen([sys.executable, "-c", CLIENTS, server.endpoint],
                                                stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                                stderr=subprocess.DEVNULL, text=True)
                        assert proc.stdout is not None and proc.stdin is not None
                        assert proc.stdout.readline().strip() == "ready"
                    lat.clear()
                    feed(s, args.seconds, args.rate)
                    results[name].extend(lat[N:])  # the first round warms up
                    if proc is not None:
                        assert proc.stdin is not None and proc.stdout is not None
                        proc.stdin.close()
                        notes += int(proc.stdout.readline() or 0)
                        proc.wait(30)
                        server.stop()
        finally:
            s.shutdown()
    out: dict[str, Any] = {}
    for name, xs in results.items():
        out[name] = {"n": len(xs), "p50_ms": pct(xs, 0.5), "p99_ms": pct(xs, 0.99),
                     "max_ms": max(xs) * 1e3, "mean_ms": statistics.fmean(xs) * 1e3}
        print(f"{name:24s} n={len(xs):6d}  p50 {out[name]['p50_ms']:.3f} ms  "
              f"p99 {out[name]['p99_ms']:.3f} ms  max {out[name]['max_ms']:.3f} ms")
    base = out["without OPC UA"]["p99_ms"]
    for k in kinds:
        print(f"p99 {k} / without: {out[k]['p99_ms'] / base:.2f}x")
    print(f"notifications received by the clients: {notes}")
    out["notifications"] = notes
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
