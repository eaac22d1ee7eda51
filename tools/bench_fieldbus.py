"""bench_fieldbus - the field-bus drivers' read rates against the libraries' own, side by side.

Run: ``.venv/bin/python -m tools.bench_fieldbus [--reads N] [--sensors K] [--repeat R]
[--connections C] [--json FILE]``. Every figure is labelled with what it includes; each
section's first row is its baseline, measured in the same run, and every ratio is against it.
Each figure is the best of
``--repeat`` rounds that run the section's programs in turn (load from other processes only ever
slows a run down); beside the rate, this process's CPU time per read (all threads), which such
load disturbs far less.

* Modbus TCP, K sensors (default 8) one request each, against ``chcos sim modbus`` in a child
  process: an asyncio program polling pymodbus's client in sequence (the baseline); chcos end to
  end (a System on the real clock with a ``modbus-tcp`` device map, the kernel polling, the
  driver's thread, a task taking every reading from queued links; target >= 0.95); the driver
  alone with a counting host; the same reads by hand over C pymodbus clients outstanding at once;
  chcos end to end with ``connections = C`` (target: beats the sequential baseline).
* CANopen: canopen's own ``sdo.upload`` back to back from the simulated servo drive on python-can's
  ``virtual`` bus, each value decoded by its data type as the driver does (the baseline), vs
  :class:`drivers.canopen_node.CanopenDriver` SDO-polling the same objects for a counting host
  that ticks every sensor due and waits in ``settle`` each cycle, as the kernel does before it
  moves its clock (target >= 0.9 with K objects); and with K objects chcos end to end, as for
  Modbus (a System on the real clock with a ``canopen`` device map, the kernel polling, the
  driver's worker and reader threads, a task taking every reading from queued links; target
  >= 0.9).

With 1 sensor per tick a driver-only figure is bounded by the two thread hand-offs a tick costs
(kernel -> I/O thread -> kernel). Exit status 0 when every target is met, 1 otherwise.
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import importlib
import json
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, ClassVar

import canopen
from pymodbus.client import AsyncModbusTcpClient

from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave
from chcos.devices.spec import BusSpec, DeviceSpec
from chcos.errors import SensorFailure
from chcos.helpers import free_port
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext
from drivers.canopen_node import CanopenDriver
from drivers.modbus import ModbusTcpDriver

TARGET = 0.9   # canopen driver / canopen alone (issue 21)


class CountingHost:
    """A DriverHost that counts deliveries and lets the benchmark run the ``every`` and ``at``
    callbacks."""

    def __init__(self) -> None:
        self.cond = threading.Condition()
        self.delivered = 0
        self.failures: list[str] = []
        self.callbacks: list[Callable[[], None]] = []
        self.once: list[Callable[[], None]] = []

    def deliver(self, device: str, value: Any) -> None:
        with self.cond:
            self.delivered += 1
            self.cond.notify_all()

    deliver_now = deliver  # (no kernel thread here: the same)

    def deliver_many(self, readings: Sequence[tuple[str, Any]],
                     at: float | None = None) -> None:
        """A poll's readings together, as Devtab takes them (one hand-over per poll; the
        receive time ``at`` does not matter to the rate)."""
        with self.cond:
            self.delivered += len(readings)
            self.cond.notify_all()

    def fail(self, device: str, reason: str) -> None:
        self.failures.append(f"{device}: {reason}")

    def recover(self, device: str, reason: str = "") -> None:
        """Recoveries do not matter to the rate."""

    def error(self, bus: str, kind: str, detail: str, device: str = "") -> None:
        self.failures.append(f"{bus} {kind}: {detail}")

    def written(self, device: str, value: Any) -> None:
        """Write confirmations do not matter to the rate."""

    def write_failed(self, device: str, value: Any, reason: str) -> None:
        self.failures.append(f"{device}: write {value!r} failed: {reason}")

    def stat(self, bus: str, key: str, n: int = 1, device: str = "", error: bool = False
             ) -> None:
        """Counters do not matter to the rate."""

    def every(self, period: float, fn: Callable[[], None]) -> None:
        self.callbacks.append(fn)

    def at(self, when: float, fn: Callable[[], None]) -> None:
        """A paced poll armed: run at the next tick, whatever ``when`` says (the benchmark
        ticks as fast as the driver settles)."""
        with self.cond:
            self.once.append(fn)

    def now(self) -> float:
        return time.monotonic()

    def tick(self) -> None:
        with self.cond:
            once, self.once = self.once, []
        for fn in [*self.callbacks, *once]:
            fn()

    def wait_delivered(self, n: int, timeout: float) -> bool:
        with self.cond:
            return self.cond.wait_for(lambda: self.delivered >= n, timeout)


class Figure(float):
    """A rate (reads/s) that also carries this process's CPU time per read (µs, every thread:
    the client side's cost, which load from other processes disturbs far less than the rate)."""

    cpu_us: float = float("nan")


def figure(reads: int, seconds: float, cpu_seconds: float) -> Figure:
    f = Figure(rate(reads, seconds))
    f.cpu_us = cpu_seconds / reads * 1e6 if reads else float("nan")
    return f


def best_each(repeat: int, runs: Sequence[Callable[[], float]]) -> list[tuple[float, float]]:
    """For each of ``runs`` over ``repeat`` rounds that run them in turn: the best rate and the
    least CPU time per read (µs; nan if the run does not measure it)."""
    best = [0.0] * len(runs)
    cpu = [float("inf")] * len(runs)
    for _ in range(max(1, repeat)):
        for i, run in enumerate(runs):
            got = run()
            best[i] = max(best[i], got)
            cpu[i] = min(cpu[i], getattr(got, "cpu_us", float("nan")))
    return list(zip(best, cpu, strict=True))


def rate(n: int, seconds: float) -> float:
    return n / seconds if seconds > 0 else float("inf")


# -- Modbus -------------------------------------------------------------------------------------

#: Holding-register addresses of the benchmark's sensors: gaps between them, one request each.
MODBUS_ADDRESSES = (0, 2, 4, 6, 8, 10, 12, 14)
#: SDO objects of the servo drive that no PDO maps, one per benchmark sensor.
SDO_OBJECTS = (0x606C, 0x6041, 0x2000, 0x6081, 0x1000, 0x1001, 0x1017, 0x6040)


def modbus_library(port: int, sensors: int, cycles: int) -> float:
    """pymodbus's own back-to-back reads per second (the same reads a driver cycle makes)."""
    addresses = MODBUS_ADDRESSES[:sensors]

    async def run() -> float:
        client = AsyncModbusTcpClient("127.0.0.1", port=port, reconnect_delay=0, timeout=1)
        await client.connect()
        await client.read_holding_registers(0, count=1, device_id=1)
        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(cycles):
            for a in addresses:
                resp = await client.read_holding_registers(a, count=1, device_id=1)
                if resp.isError():
                    raise RuntimeError(f"modbus library read failed: {resp}")
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        client.close()
        return figure(cycles * len(addresses), dt, cpu)

    return asyncio.run(run())


def drive(driver: Any, host: CountingHost, cycles: int) -> float:
    """Start ``driver``, then ``cycles`` times: tick the host (every sensor due) and settle, as a
    kernel stepping its clock does; readings delivered per second."""
    driver.start()
    try:
        host.tick()
        driver.settle(5.0)
        start = host.delivered
        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(cycles):
            host.tick()
            if not driver.settle(5.0):
                raise RuntimeError(f"{driver.kind} driver did not settle")
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        got = host.delivered - start
    finally:
        driver.stop()
    if host.failures:
        raise RuntimeError(f"{driver.kind} driver bench: {host.failures[:3]}")
    return figure(got, dt, cpu)


def modbus_driver(port: int, sensors: int, cycles: int) -> float:
    """Reads per second delivered to a host by ModbusTcpDriver polling ``sensors`` registers."""
    bus = BusSpec(name="bench", kind="modbus-tcp",
                  options={"host": "127.0.0.1", "port": port, "timeout": 1.0})
    devs = [DeviceSpec(name=f"r{a}", direction="sensor", machine=0, bus="bench",
                       address={"table": "holding", "address": a})
            for a in MODBUS_ADDRESSES[:sensors]]
    host = CountingHost()
    return drive(ModbusTcpDriver(bus, devs, host), host, cycles)


MODBUS_MAP = """
[[bus]]
name = "plc"
kind = "modbus-tcp"
host = "127.0.0.1"
port = {port}
timeout = 1.0
poll_period = {period}
{connections}
"""
MODBUS_SENSOR = """
[[device]]
name = "r{a}"
direction = "sensor"
bus = "plc"
address = {{ table = "holding", address = {a} }}
"""


class _Count:
    """What the benchmark's reader task counts: readings taken, and when it has ``target``."""

    target = 0
    taken = 0
    done = threading.Event()
    failures: ClassVar[list[str]] = []


async def reader(ctx: TaskContext, cmd: Any) -> None:
    """The end-to-end benchmark's task: takes every reading of its sensors (queued links, so
    each poll's readings all count) until it has the benchmark's target."""
    read_any = ctx.read_any
    while True:
        try:
            await read_any()
        except SensorFailure as exc:     # counted and reported by the benchmark
            _Count.failures.append(str(exc))
            await ctx.sleep(0.01)
            continue
        _Count.taken += 1
        if _Count.taken == _Count.target:
            _Count.done.set()


def end_to_end(devmap: str, names: Sequence[str], cycles: int, what: str) -> Figure:
    """Readings per second a chcos task takes end to end from the sensors ``names`` of the
    device map ``devmap`` (TOML text): a System on the real clock, the kernel polling them, the
    driver's threads reading them and delivering into the kernel, the task taking every reading
    from queued links, ``cycles`` readings of each."""
    # the task runs in tools.bench_fieldbus as chcos imports it, which is not this module when
    # it runs as ``python -m tools.bench_fieldbus`` (then this is __main__)
    count: Any = importlib.import_module("tools.bench_fieldbus")._Count
    tmp = Path(tempfile.mkdtemp(prefix="bench-fieldbus-"))
    (tmp / "bench.toml").write_text(devmap)
    warm = 2 * len(names)
    count.taken, count.target, count.done = 0, warm, threading.Event()
    count.failures = []
    system = System([tmp / "bench.toml"], clock=RealClock(), machines=[0], base_dir=tmp)
    queues = " ".join(f"--queue={name}=4096" for name in names)
    system.execute(f"install -m0i{len(names)} {queues} --code=tools.bench_fieldbus:reader R "
                   f"{' '.join(names)}")
    system.invoke("R")
    runner = threading.Thread(target=system.start, daemon=True)
    try:
        runner.start()
        if not count.done.wait(10.0):
            raise RuntimeError(f"{what} end-to-end bench: no readings within 10 s; sensor "
                               f"failures: {count.failures[:3]}")
        done = count.done = threading.Event()
        count.target = warm + cycles * len(names)
        c0, t0 = time.process_time(), time.perf_counter()
        if not done.wait(120.0):
            raise RuntimeError(f"{what} end-to-end bench: {count.taken} of {count.target} "
                               f"readings in 120 s; sensor failures: {count.failures[:3]}")
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
    finally:
        system.shutdown()
        runner.join(10.0)
    if count.failures:
        raise RuntimeError(f"{what} end-to-end bench: {len(count.failures)} sensor failures, "
                           f"first: {count.failures[0]}")
    return figure(cycles * len(names), dt, cpu)


def modbus_chcos(port: int, sensors: int, cycles: int, connections: int = 1,
                 period: float = 0.0005) -> float:
    """Readings per second a chcos task takes end to end (:func:`end_to_end`) from a
    ``modbus-tcp`` device map of ``sensors`` holding registers (one request each), polled every
    ``period`` s (a poll is queued at most once, so the driver runs back to back) over
    ``connections`` TCP connections."""
    addresses = MODBUS_ADDRESSES[:sensors]
    devmap = (MODBUS_MAP.format(port=port, period=period,
                                connections=(f"connections = {connections}" if connections > 1
                                             else ""))
              + "".join(MODBUS_SENSOR.format(a=a) for a in addresses))
    return end_to_end(devmap, [f"r{a}" for a in addresses], cycles,
                      f"modbus ({connections} connection(s))")


def modbus_parallel_library(port: int, sensors: int, cycles: int, connections: int) -> float:
    """An asyncio program's reads per second with the same requests spread over
    ``connections`` pymodbus clients, all outstanding at once (what chcos' parallel poll does,
    written by hand)."""
    addresses = MODBUS_ADDRESSES[:sensors]

    async def run() -> float:
        clients = [AsyncModbusTcpClient("127.0.0.1", port=port, reconnect_delay=0, timeout=1)
                   for _ in range(connections)]
        for c in clients:
            await c.connect()
            await c.read_holding_registers(0, count=1, device_id=1)
        n = len(clients)

        async def share(i: int) -> None:
            for a in addresses[i::n]:
                resp = await clients[i].read_holding_registers(a, count=1, device_id=1)
                if resp.isError():
                    raise RuntimeError(f"modbus library read failed: {resp}")

        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(cycles):
            await asyncio.gather(*(share(i) for i in range(n)))
        dt, cpu = time.perf_counter() - t0, time.process_time() - c0
        for c in clients:
            c.close()
        return figure(cycles * len(addresses), dt, cpu)

    return asyncio.run(run())


class ModbusServerProcess:
    """``chcos sim modbus`` in a child process, as a real device would be: the driver and the
    library are measured without the server competing for this process's GIL."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.proc: subprocess.Popen[str] | None = None

    def __enter__(self) -> ModbusServerProcess:
        code = f"from chcos.apps.sim.modbus_server import main; main(['--port', '{self.port}'])"
        self.proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE,
                                     text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()         # printed once the port is bound
        if "server on" not in line:
            self.proc.kill()
            raise RuntimeError(f"modbus sim server did not start: {line!r}")
        return self

    def __exit__(self, *exc: object) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=10)


# -- CANopen ------------------------------------------------------------------------------------

def canopen_library(channel: str, sensors: int, cycles: int) -> float:
    """canopen's own back-to-back SDO uploads per second, each decoded by its object's data
    type (the driver's job too: it delivers numbers)."""
    objects = SDO_OBJECTS[:sensors]
    network: Any = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=channel)
    try:
        node = network.add_node(5, str(SERVO_EDS))
        node.sdo.upload(0x606C, 0)
        upload = node.sdo.upload
        reads = [(index, node.object_dictionary.get_variable(index, 0).decode_raw)
                 for index in objects]
        c0, t0 = time.process_time(), time.perf_counter()
        for _ in range(cycles):
            for index, decode in reads:
                decode(upload(index, 0))
        return figure(cycles * len(objects), time.perf_counter() - t0, time.process_time() - c0)
    finally:
        network.disconnect()


def canopen_driver(channel: str, sensors: int, cycles: int) -> float:
    """SDO reads per second delivered to a host by CanopenDriver polling ``sensors`` objects."""
    bus = BusSpec(name="bench", kind="canopen",
                  options={"interface": "virtual", "channel": channel,
                           "nodes": [{"id": 5, "eds": str(SERVO_EDS), "nmt_start": False}]})
    devs = [DeviceSpec(name=f"o{index:04X}", direction="sensor", machine=0, bus="bench",
                       address={"node": 5, "index": index}) for index in SDO_OBJECTS[:sensors]]
    host = CountingHost()
    return drive(CanopenDriver(bus, devs, host), host, cycles)


CANOPEN_MAP = """
[[bus]]
name = "drive"
kind = "canopen"
interface = "virtual"
channel = "{channel}"
poll_period = {period}
nodes = [{{ id = 5, eds = "{eds}", nmt_start = false }}]
"""
CANOPEN_SENSOR = """
[[device]]
name = "o{index:04X}"
direction = "sensor"
bus = "drive"
address = {{ node = 5, index = {index} }}
"""


def canopen_chcos(channel: str, sensors: int, cycles: int, period: float = 0.0005) -> float:
    """SDO readings per second a chcos task takes end to end (:func:`end_to_end`) from a
    ``canopen`` device map of ``sensors`` objects of the simulated drive, polled every
    ``period`` s (back to back, as :func:`modbus_chcos`)."""
    objects = SDO_OBJECTS[:sensors]
    devmap = (CANOPEN_MAP.format(channel=channel, period=period, eds=SERVO_EDS.as_posix())
              + "".join(CANOPEN_SENSOR.format(index=i) for i in objects))
    return end_to_end(devmap, [f"o{i:04X}" for i in objects], cycles, "canopen")


def main(argv: Sequence[str] | None = None) -> int:
    """Run both benchmarks and print the figures; 0 if every ratio of a full bus (``--sensors``
    per tick) meets the target."""
    parser = argparse.ArgumentParser(description="field-bus driver vs library read rates")
    parser.add_argument("--reads", type=int, default=2000, help="reads per measurement")
    parser.add_argument("--sensors", type=int, default=len(SDO_OBJECTS),
                        choices=range(2, len(SDO_OBJECTS) + 1), help="sensors on a full bus")
    parser.add_argument("--target", type=float, default=TARGET,
                        help="canopen driver / canopen alone, a full bus")
    parser.add_argument("--repeat", type=int, default=5,
                        help="alternating runs of library and driver; the best of each is kept")
    parser.add_argument("--connections", type=int, default=4,
                        help="connections of the parallel Modbus poll")
    parser.add_argument("--modbus-target", type=float, default=0.95,
                        help="chcos end to end / asyncio + pymodbus, 1 connection")
    parser.add_argument("--json", help="also write the sections to this file (bench_suite)")
    args = parser.parse_args(argv)
    n = args.sensors
    lanes = args.connections
    #: (section title, [(what the figure includes, (reads/s, CPU µs/read), target or None)]),
    #: each section's first row its baseline, every ratio against it, all from this run
    sections: list[tuple[str, list[tuple[str, tuple[float, float], float | None]]]] = []
    with ModbusServerProcess(free_port()) as server:
        port = server.port
        cycles = args.reads // n
        mb = best_each(args.repeat, [
            functools.partial(modbus_library, port, n, cycles),
            functools.partial(modbus_chcos, port, n, cycles, 1),
            functools.partial(modbus_driver, port, n, cycles),
            functools.partial(modbus_parallel_library, port, n, cycles, lanes),
            functools.partial(modbus_chcos, port, n, cycles, lanes)])
        sections.append((f"modbus-tcp, {n} holding registers one request each, server "
                         f"(pymodbus, chcos sim modbus) in a child process", [
            (f"asyncio + pymodbus client, {n} reads in sequence (baseline)", mb[0], None),
            ("chcos end to end: kernel on the real clock, driver thread, task taking every "
             "reading, 1 connection", mb[1], args.modbus_target),
            ("chcos driver only: counting host, tick + settle per cycle (no kernel, no task)",
             mb[2], None),
            (f"asyncio + pymodbus by hand, {lanes} clients, reads outstanding at once", mb[3],
             None),
            (f"chcos end to end, connections = {lanes} (parallel poll)", mb[4], 1.0)]))
        one = best_each(args.repeat, [
            functools.partial(modbus_library, port, 1, args.reads),
            functools.partial(modbus_driver, port, 1, args.reads)])
        sections.append(("modbus-tcp, 1 sensor per tick (latency-bound: 2 thread hand-offs "
                         "per tick)", [
            ("asyncio + pymodbus client (baseline)", one[0], None),
            ("chcos driver only, counting host, tick + settle", one[1], None)]))

    channel = f"bench-{time.monotonic_ns()}"
    with CanopenSlave(5, channel=channel, heartbeat_period=0):
        for k in (n, 1):
            cycles = args.reads // k
            runs = [functools.partial(canopen_library, channel, k, cycles),
                    functools.partial(canopen_driver, channel, k, cycles)]
            if k == n:
                runs.append(functools.partial(canopen_chcos, channel, k, cycles))
            co = best_each(args.repeat, runs)
            rows = [("canopen alone: sdo.upload + decode_raw back to back (baseline)", co[0],
                     None),
                    ("chcos driver only: counting host, tick + settle per cycle, own reader "
                     "thread", co[1], args.target if k == n else None)]
            if k == n:
                rows.append(("chcos end to end: kernel on the real clock, driver threads, task "
                             "taking every reading", co[2], args.target))
            sections.append((f"canopen SDO upload, {k} object(s) per tick, simulated drive "
                             f"(canopen LocalNode) in this process, python-can virtual bus",
                             rows))

    ok = True
    print(f"best of {args.repeat} rounds; ratio = reads/s over the section's baseline; CPU = "
          f"this process's CPU time per read, all threads")
    for title, figs in sections:
        print(f"\n{title}")
        print(f"  {'figure (what it includes)':86} {'reads/s':>8} {'ratio':>6} {'CPU µs':>7}")
        base = figs[0][1][0]
        for label, (value, cpu), target in figs:
            ratio = value / base
            met = "" if target is None else (f"  target >= {target}: "
                                             f"{'met' if ratio >= target else 'NOT met'}")
            ok = ok and (target is None or ratio >= target)
            print(f"  {label:86} {value:8.0f} {ratio:6.2f} {cpu:7.0f}{met}")
    if args.json:
        Path(args.json).write_text(json.dumps({"repeat": args.repeat, "sections": [
            {"title": title, "rows": [{"label": label, "rate": value, "cpu_us": cpu,
                                       "ratio": value / figs[0][1][0], "target": target}
                                      for label, (value, cpu), target in figs]}
            for title, figs in sections]}, indent=2) + "\n", encoding="utf-8")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
