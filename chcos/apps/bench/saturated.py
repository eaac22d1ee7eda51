"""saturated - a saturated CAN bus through chcos: 8,800 frames/s in, 1,000 answers/s out, one core.

A 1 Mbit/s CAN bus at 100 % load carries about 8,800 frames/s of 8 data bytes (~113 bits each
with stuffing). The benchmark puts that load on a python-can ``virtual`` bus through chcos' real
CAN driver (kind ``can``) with a DBC (``saturated.dbc`` beside this module: eight 8-byte input
messages ``In0..In7`` and eight 8-byte answers ``Answer0..Answer7``):

* a peer thread sends ``rate_in`` frames/s round-robin on ``In0..In7`` (paced on an absolute
  schedule); each carries a sequence number ``Seq<i>`` = 2k + r, r = 1 on ``rate_out`` of every
  ``rate_in`` frames (spread evenly): those ask for an answer;
* eight level-1 driver tasks ``D0..D7`` (:func:`answer`) read their ``Seq<i>`` sensor, report
  every fifth reading to the level-2 task ``C`` (:func:`collect`, the thesis' five-to-one fan-in)
  and, for an odd sequence number, write it to their actuator ``Echo<i>``: the driver sends the
  ``Answer<i>`` frame;
* a peer listener thread takes every answer off the bus and times it against its request.

Measured over the run: frames sent vs frames the driver received, readings, drops, bus errors,
readings the tasks consumed and readings overwritten unread (newest-wins), answers asked,
written by the tasks, sent by the driver and received by the peer - :meth:`SaturatedResult.
unaccounted` is zero when no frame is lost without a count; the CPU time of the process (
``resource.getrusage``) and of chcos alone (the process minus the peer's two threads, read from
``/proc/self/task/<tid>/stat``), as a share of one core; the reaction (peer's send of a request
-> its answer received by the peer) p50/p99/max. The process is pinned to one core for the run.
Errors: ConfigError for bad parameters, BusError if the virtual bus cannot be opened.
"""

from __future__ import annotations

import os
import resource
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import can

from chcos.devices.spec import BusSpec, DeviceMap, DeviceSpec
from chcos.errors import ConfigError
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from chcos.user.context import TaskContext

__all__ = ["DBC", "N_IDS", "SaturatedResult", "answer", "collect", "run_saturated"]

DBC = Path(__file__).with_name("saturated.dbc")
N_IDS = 8
IN_BASE, OUT_BASE = 0x100, 0x200
_M = "chcos.apps.bench.saturated"
_TICK = os.sysconf("SC_CLK_TCK")
QUEUE = 1024  # readings a sensor link holds by default (0: newest-wins)


async def answer(ctx: TaskContext, command: Any) -> None:
    """D<i>: read the sequence number; every fifth reading upward; an odd one is echoed to the
    actuator (the answer frame). Counts what it consumed in its world model."""
    read, write, put = ctx.read, ctx.write, ctx.put
    sensory = ctx.world.sensory
    n = 0
    while True:
        v = int(await read(0))
        n += 1
        if v & 1:
            write(0, v)
        if n % 5 == 0:
            put(v)
        sensory["consumed"] = n


async def collect(ctx: TaskContext, command: Any) -> None:
    """C, level 2: reads every driver task's reports."""
    while True:
        await ctx.read_any()


def devmap(channel: str) -> DeviceMap:
    """The devices on the virtual CAN ``channel``, addressed through the DBC."""
    bus = BusSpec("can0", "can", {"interface": "virtual", "channel": channel, "dbc": str(DBC)})
    devs = [DeviceSpec(f"Seq{i}", "sensor", 0, "can0", {"message": f"In{i}", "signal": f"Seq{i}"})
            for i in range(N_IDS)]
    devs += [DeviceSpec(f"Echo{i}", "actuator", 0, "can0",
                        {"message": f"Answer{i}", "signal": f"Echo{i}"}, safe_value=0.0)
             for i in range(N_IDS)]
    return DeviceMap((bus,), tuple(devs))


def build(channel: str, queue: int = QUEUE) -> System:
    """The installed system, every task invoked (not started); ``queue`` > 0 makes each
    sensor link queued (that many readings), 0 newest-wins. Raises BusError/InstallError."""
    s = System(devmap(channel), clock=RealClock(), machines=[0], base_dir=Path.cwd())
    for i in range(N_IDS):
        q = f" --queue=Seq{i}={queue}" if queue > 0 else ""
        s.execute(f"install -m0i1o1{q} --code={_M}:answer D{i} Seq{i} Echo{i}")
    s.execute(f"install -m0i{N_IDS} --code={_M}:collect C " + " ".join(f"D{i}"
                                                                     for i in range(N_IDS)))
    s.invoke("C")
    for i in range(N_IDS):
        s.invoke(f"D{i}")
    return s


def _thread_cpu(tid: int) -> float:
    """CPU seconds (user + system) of thread ``tid`` of this process; 0.0 if it is gone."""
    try:
        stat = Path(f"/proc/self/task/{tid}/stat").read_text()
    except OSError:
        return 0.0
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / _TICK


def _process_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


@dataclass
class SaturatedResult:
    """What one run sent, counted and measured (see the module doc)."""

    seconds: float = 0.0
    rate_in: float = 0.0
    rate_out: float = 0.0
    core: int = -1
    warmup: float = 0.0
    queue: int = 0  # readings each sensor link holds (0: newest-wins)
    sent: int = 0
    sent_measured: int = 0  # frames sent in the measured window (after the warm-up)
    answers_measured: int = 0  # answers received in the measured window
    requests: int = 0
    received_by_driver: int = 0
    readings: int = 0
    dropped: int = 0
    bus_errors: int = 0
    consumed: int = 0
    overwritten: int = 0
    answers_written: int = 0
    answers_sent: int = 0
    answer_write_errors: int = 0
    answers_received: int = 0
    unanswered: int = 0
    cpu_process: float = 0.0
    cpu_peer: float = 0.0
    reaction: list[float] = field(default_factory=list)
    load: tuple[float, float, float] = (0.0, 0.0, 0.0)
    cpus: int = 0

    @property
    def cpu_chcos(self) -> float:
        """chcos' share of one core: the process' CPU time minus the peer threads', per second."""
        return (self.cpu_process - self.cpu_peer) / self.seconds if self.seconds else 0.0

    @property
    def cpu_total(self) -> float:
        """The whole process' share of one core (chcos and the peer)."""
        return self.cpu_process / self.seconds if self.seconds else 0.0

    def unaccounted(self) -> dict[str, int]:
        """Every balance that must be zero when nothing is lost without a count (name ->
        difference); unread readings (at most one per sensor) are allowed in ``in-tasks``."""
        # a reading is consumed, overwritten unread (newest-wins only: a queued link keeps
        # it), or still unread
        unread = self.readings - self.consumed - self.overwritten
        return {
            "in-bus": self.sent - self.received_by_driver,
            "in-devtab": self.received_by_driver - self.readings - self.dropped - self.bus_errors,
            "in-tasks": 0 if 0 <= unread <= N_IDS * max(1, self.queue) else unread,
            "out-driver": self.answers_written - self.answers_sent - self.answer_write_errors,
            "out-bus": self.answers_sent - self.answers_received,
            "out-asked": 0 if self.unanswered <= (N_IDS * max(1, self.queue) if self.queue else
                                                  self.overwritten + N_IDS) else self.unanswered,
        }

    def percentile(self, q: float) -> float:
        """The ``q`` quantile (0..1) of the reaction times in seconds; nan if none."""
        if not self.reaction:
            return float("nan")
        s = sorted(self.reaction)
        return s[min(len(s) - 1, max(0, int(len(s) * q + 0.5) - 1))]


class _Peer:
    """The peer: a sender thread (``rate_in`` frames/s, ``rate_out`` of them requests) and a
    listener thread timing every answer against its request."""

    def __init__(self, bus: can.BusABC, rate_in: float, rate_out: float) -> None:
        self.bus = bus
        self.rate_in, self.rate_out = rate_in, rate_out
        self.sent = self.requests = self.answers = 0
        self.asked: dict[int, float] = {}
        self.reaction: list[float] = []
        self.measuring = False
        self._stop_send = threading.Event()
        self._stop_recv = threading.Event()
        self.sender = threading.Thread(target=self._send_loop, name="sat-peer-tx", daemon=True)
        self.listener = threading.Thread(target=self._recv_loop, name="sat-peer-rx", daemon=True)

    def start(self) -> None:
        self.sender.start()
        self.listener.start()

    def stop_sending(self) -> None:
        self._stop_send.set()
        self.sender.join(5.0)

    def stop(self) -> None:
        self.stop_sending()
        self._stop_recv.set()
        self.listener.join(5.0)

    def cpu(self) -> float:
        return sum(_thread_cpu(t.native_id) for t in (self.sender, self.listener)
                   if t.native_id is not None)

    def _send_loop(self) -> None:
        t0 = time.perf_counter()
        rin, rout = self.rate_in, self.rate_out
        send, perf = self.bus.send, time.perf_counter
        while not self._stop_send.is_set():
            due = int((perf() - t0) * rin) - self.sent
            for _ in range(min(due, 64)):
                k = self.sent
                req = (k + 1) * rout // rin > k * rout // rin
                seq = 2 * k + (1 if req else 0)
                data = seq.to_bytes(4, "little") + b"\x10\x00\x00\x00"
                msg = can.Message(arbitration_id=IN_BASE + k % N_IDS, is_extended_id=False,
                                  data=data)
                if req:
                    self.requests += 1
                    self.asked[seq] = perf()
                send(msg)
                self.sent += 1
            self._stop_send.wait(0.0005)

    def _recv_loop(self) -> None:
        recv, perf = self.bus.recv, time.perf_counter
        while not self._stop_recv.is_set():
            msg = recv(0.05)
            if msg is None or not OUT_BASE <= msg.arbitration_id < OUT_BASE + N_IDS:
                continue
            t = perf()
            self.answers += 1
            t_send = self.asked.pop(int.from_bytes(msg.data[:4], "little"), None)
            if t_send is not None and self.measuring:
                self.reaction.append(t - t_send)


def machine_load() -> tuple[tuple[float, float, float], int]:
    """The machine's load averages (1, 5, 15 min) and its CPU count."""
    return os.getloadavg(), os.cpu_count() or 0


def run_saturated(seconds: float = 60.0, rate_in: float = 8800.0, rate_out: float = 1000.0,
                  *, warmup: float = 1.0, core: int | None = None, queue: int = QUEUE
                  ) -> SaturatedResult:
    """Run the benchmark for ``warmup`` + ``seconds`` on one core (``core``, default the lowest
    allowed; the affinity is restored afterwards); ``queue``: see :func:`build`. Raises
    ConfigError for bad parameters, BusError if the virtual bus cannot be opened."""
    if not (seconds > 0 and rate_in > 0 and 0 <= rate_out <= rate_in and warmup >= 0
            and queue >= 0):
        raise ConfigError(f"saturated: need seconds > 0, rate_in > 0, 0 <= rate_out <= rate_in, "
                          f"warmup >= 0; got {seconds}, {rate_in}, {rate_out}, {warmup}")
    allowed = os.sched_getaffinity(0)
    pin = min(allowed) if core is None else core
    if pin not in allowed:
        raise ConfigError(f"saturated: core {pin} is not among the allowed {sorted(allowed)}")
    os.sched_setaffinity(0, {pin})
    channel = f"chcos-bench-sat-{os.getpid()}-{time.monotonic_ns()}"
    res = SaturatedResult(rate_in=rate_in, rate_out=rate_out, core=pin, warmup=warmup,
                          queue=queue)
    res.load, res.cpus = machine_load()
    try:
        s = build(channel, queue)
        peer_bus = can.Bus(interface="virtual", channel=channel)
        peer = _Peer(peer_bus, rate_in, rate_out)
        try:
            s.start()
            peer.start()
            threading.Event().wait(warmup)
            cpu0, peer0, t0 = _process_cpu(), peer.cpu(), time.perf_counter()
            sent0, answers0 = peer.sent, peer.answers
            peer.measuring = True
            threading.Event().wait(seconds)
            peer.measuring = False
            res.seconds = time.perf_counter() - t0
            res.cpu_process, res.cpu_peer = _process_cpu() - cpu0, peer.cpu() - peer0
            res.sent_measured, res.answers_measured = peer.sent - sent0, peer.answers - answers0
            peer.stop_sending()
            drivers = list(s.devtab.drivers)
            # quiet: every frame sent reached the driver and every answer came back
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline:
                got = sum(getattr(d, "received", 0) for d in drivers)
                out = sum(getattr(d, "sent", 0) for d in drivers)
                # queued links: every request is answered in the end
                if got >= peer.sent and peer.answers >= out and (queue == 0 or not peer.asked):
                    threading.Event().wait(0.2)
                    if (sum(getattr(d, "received", 0) for d in drivers) == got
                            and sum(getattr(d, "sent", 0) for d in drivers) == out
                            and peer.answers == out):
                        break
                threading.Event().wait(0.05)
            peer.stop()
            res.sent, res.requests, res.answers_received = peer.sent, peer.requests, peer.answers
            res.unanswered = len(peer.asked)
            res.reaction = peer.reaction
            res.received_by_driver = sum(getattr(d, "received", 0) for d in drivers)
            res.answers_sent = sum(getattr(d, "sent", 0) for d in drivers)
            res.bus_errors = sum(sum(getattr(d, "error_counts", {}).values()) for d in drivers)
            for i in range(N_IDS):
                e = s.devtab.get(f"Seq{i}")
                res.readings += e.readings
                res.dropped += e.dropped
                res.overwritten += e.overwrites
                a = s.devtab.get(f"Echo{i}")
                res.answers_written += a.commands
                res.answer_write_errors += a.write_errors
                t = s.tsktab.get(f"D{i}")
                wm = t.world if t is not None else None
                sensory = getattr(wm, "sensory", {})
                res.consumed += int(sensory.get("consumed", 0))
        finally:
            s.shutdown()
            peer_bus.shutdown()
    finally:
        os.sched_setaffinity(0, allowed)
    return res


def report(r: SaturatedResult) -> str:
    """The run as text: rates, accounting, CPU, reaction, machine load."""
    bal = r.unaccounted()
    lost = "none" if not any(bal.values()) else ", ".join(f"{k} {v}" for k, v in bal.items() if v)
    p = r.percentile
    return "\n".join([
        f"saturated bus: {r.sent_measured / max(r.seconds, 1e-9):,.0f}/s in (target "
        f"{r.rate_in:,.0f}), {r.answers_measured / max(r.seconds, 1e-9):,.0f}/s answers out "
        f"(target {r.rate_out:,.0f}) for {r.seconds:.1f} s on core {r.core}; counts below include "
        f"the {r.warmup:.1f} s warm-up and the drain",
        f"  in : sent {r.sent:,}, driver received {r.received_by_driver:,}, readings "
        f"{r.readings:,}, dropped {r.dropped:,}, bus errors {r.bus_errors:,}; tasks consumed "
        f"{r.consumed:,}, overwritten unread {r.overwritten:,} "
        + (f"(sensor links queued, {r.queue} each: they keep every reading)" if r.queue else
           "(newest-wins)"),
        f"  out: asked {r.requests:,}, written by tasks {r.answers_written:,}, sent "
        f"{r.answers_sent:,}, write errors {r.answer_write_errors:,}, received by the peer "
        f"{r.answers_received:,}, unanswered {r.unanswered:,}",
        f"  frames lost without a count: {lost}",
        f"  CPU: chcos {r.cpu_chcos * 100:.1f} % of a core (target <= 50 %), whole process with "
        f"the peer {r.cpu_total * 100:.1f} %",
        f"  reaction (request sent -> answer received), {len(r.reaction):,} answers: p50 "
        f"{p(0.5) * 1e3:.3f} ms, p99 {p(0.99) * 1e3:.3f} ms, max {p(1.0) * 1e3:.3f} ms",
        f"  machine: load {r.load[0]:.2f} {r.load[1]:.2f} {r.load[2]:.2f} on {r.cpus} CPUs",
    ])
