"""bench_sim_timers - how far the simulated CANopen node's timers drift: the heartbeat producer
(0x1017) and a TPDO's event timer (0x1800:05), counted over a long run on virtual time and on
real time, against the frames the periods make due.

Run: ``python -m tools.bench_sim_timers [--seconds 60] [--real-seconds 60] [--periods 7 25 33
100]``. For each period (ms), one node with its heartbeat and its event timer at that period:

* virtual: the node's pure core (``attach``, no bus) advanced by :meth:`tick` in 10 ms steps, as
  the kernel's slaves advance it, for ``--seconds`` of its clock;
* real: the node on python-can's ``virtual`` bus as ``chcos sim canopen`` runs it (``Clock.REAL``:
  the heartbeat on its own thread on the wall clock; ``run_realtime``: the node's time, and so
  the event timer, ticked on the wall clock every 10 ms), every period's node at once, for
  ``--real-seconds`` of wall time; an observer on the same bus counts what they sent
  (``--real-seconds 0`` skips it).

Drift, slow when positive: on virtual time (expected - counted) / expected, expected the whole
periods in the run; on real time the growth of the frames' lateness over the run
(:func:`lateness_drift`: robust to the machine's stalls, which delay a few frames that the timer
then sends at once), beside the count. The figures are in ``docs/canopen-sim.md`` (section Time).
"""

from __future__ import annotations

import argparse
import math
import statistics
import struct
import threading
import time
from collections.abc import Sequence

import can

from chcos.apps.sim.canopen_slave import SERVO_EDS, CanopenSlave, Clock
from drivers.codecs.can import CanFrame

STEP = 0.01


def _setup(node: CanopenSlave, period_ms: int) -> list[CanFrame]:
    """SDO downloads of 0x1017 and 0x1800:05 (``period_ms``) and the NMT start, for ``node``."""
    nid = node.node_id
    return [CanFrame(0x600 + nid, struct.pack("<BHBH2x", 0x2B, 0x1017, 0, period_ms)),
            CanFrame(0x600 + nid, struct.pack("<BHBH2x", 0x2B, 0x1800, 5, period_ms)),
            CanFrame(0x000, bytes([0x01, nid]))]


def virtual(period_ms: int, seconds: float) -> tuple[int, int]:
    """(heartbeats, event-timer TPDOs) of one node over ``seconds`` of its tick clock."""
    node = CanopenSlave(1, SERVO_EDS, channel="unused", clock=Clock.TICK, heartbeat_period=0,
                        servo=False)
    node.attach()
    for frame in _setup(node, period_ms):
        node.handle(frame)
    node.take()
    beats = tpdos = 0
    for _ in range(round(seconds / STEP)):
        node.tick(STEP)
        for frame in node.take():
            beats += frame.arbitration_id == 0x701
            tpdos += frame.arbitration_id == 0x181
    return beats, tpdos


def real(periods: Sequence[int], seconds: float) -> dict[int, tuple[list[float], list[float]]]:
    """Per period: the send times of the heartbeats and of the event-timer TPDOs within
    ``seconds`` of wall time, all nodes at once, from half a second after they were
    configured."""
    channel = f"bench-sim-timers-{threading.get_ident()}"
    observer = can.Bus(interface="virtual", channel=channel)
    master = can.Bus(interface="virtual", channel=channel)
    nodes = [CanopenSlave(n, SERVO_EDS, channel=channel, clock=Clock.REAL, heartbeat_period=0,
                          servo=False) for n in range(1, len(periods) + 1)]
    beats: dict[int, list[float]] = {n.node_id: [] for n in nodes}
    tpdos: dict[int, list[float]] = {n.node_id: [] for n in nodes}
    try:
        for node, period in zip(nodes, periods, strict=True):
            node.start()
            node.run_realtime(STEP)      # as chcos sim canopen: the node's time on the wall
            for frame in _setup(node, period):
                master.send(can.Message(arbitration_id=frame.arbitration_id, data=frame.data,
                                        is_extended_id=False))
        begin = time.time() + 0.5            # the virtual bus stamps frames with time.time()
        end = begin + seconds
        while (msg := observer.recv(1.0)) is None or msg.timestamp < end:
            if msg is None or msg.timestamp < begin:
                continue
            nid = msg.arbitration_id & 0x7F
            if msg.arbitration_id == 0x700 + nid and nid in beats:
                beats[nid].append(msg.timestamp)
            elif msg.arbitration_id == 0x180 + nid and nid in tpdos:
                tpdos[nid].append(msg.timestamp)
    finally:
        for node in nodes:
            node.stop()
        observer.shutdown()
        master.shutdown()
    return {period: (beats[n], tpdos[n]) for n, period in enumerate(periods, 1)}


def lateness_drift(stamps: list[float], period: float) -> float:
    """How much the frames' lateness grew over the run, as a share of the run: the median of
    (stamp_k - k periods) over the last tenth of the frames minus that over the first tenth,
    divided by the time between them (medians: a stall of the machine that delays a few frames,
    which the timer then sends at once, does not count; a timer counting from late times
    does)."""
    if len(stamps) < 20:
        return float("nan")
    tenth = len(stamps) // 10
    offsets = [t - k * period for k, t in enumerate(stamps)]
    early = statistics.median(offsets[:tenth])
    late = statistics.median(offsets[-tenth:])
    span = stamps[-tenth // 2] - stamps[tenth // 2]
    return (late - early) / span


def _line(mode: str, timer: str, period_ms: int, counted: int, seconds: float,
          drift: float | None = None) -> str:
    expected = seconds * 1000 / period_ms
    if drift is None:                          # virtual: against the whole periods in the run
        whole = math.floor(expected + 1e-9)
        drift = (whole - counted) / whole
    return (f"{mode:8s} {timer:12s} {period_ms:5d} ms  {counted:7d} frames  expected "
            f"{expected:9.1f}  drift {drift * 100:+6.2f} %")


def main(argv: Sequence[str] | None = None) -> int:
    """Print one line per mode, timer and period. Returns 0."""
    parser = argparse.ArgumentParser(prog="python -m tools.bench_sim_timers",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="virtual run, s")
    parser.add_argument("--real-seconds", type=float, default=60.0, help="real-time run, s")
    parser.add_argument("--periods", type=int, nargs="+", default=[7, 25, 33, 100],
                        help="timer periods, ms")
    args = parser.parse_args(argv)
    print(f"virtual time: {args.seconds:.0f} s in {STEP * 1000:.0f} ms steps", flush=True)
    for period in args.periods:
        counts = virtual(period, args.seconds)
        for timer, count in zip(("heartbeat", "event timer"), counts, strict=True):
            print(_line("virtual", timer, period, count, args.seconds), flush=True)
    if args.real_seconds > 0:
        print(f"real time: {args.real_seconds:.0f} s of wall time", flush=True)
        for period, sent in real(args.periods, args.real_seconds).items():
            for timer, stamps in zip(("heartbeat", "event timer"), sent, strict=True):
                drift = lateness_drift(stamps, period / 1000)
                print(_line("real", timer, period, len(stamps), args.real_seconds, drift))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
