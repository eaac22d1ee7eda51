"""bench_rtu_line - what one dead unit costs the live one on a Modbus RTU line (issue 38).

Two stock libmodbus slaves (vcan_tests/peers/rtu_slave.c with libmodbus' default response
timeout) share one line (a pty hub passing every frame to every side, as RS-485 does); chcos
polls one sensor on each, on the real-time clock. In the same run it measures unit 1's readings
per second with both units alive (the baseline), then with unit 2 killed - while unit 2's polls
are thinned out (the ramp) and once they are backed off to ``dead_unit_backoff`` (steady) - and
how long after unit 2 restarts its readings come back. Target: the live unit keeps >= 90 % of
its rate (steady). Needs gcc, pkg-config and libmodbus-dev.

``python -m tools.bench_rtu_line [--window S] [--timeout S] [--retries N]``
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

from chcos.devices.spec import BusSpec
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from drivers.modbus_link import dead_unit_backoff
from tools.peer_rtu import LineHub, RtuSlave, compile_slave

PERIOD = 0.1
MAP = """
[[bus]]
name = "line"
kind = "modbus-rtu"
port = "{port}"
timeout = {timeout}
retries = {retries}
poll_period = {period}

[[device]]
name = "u1"
direction = "sensor"
bus = "line"
address = {{ unit = 1, table = "input", address = 2 }}

[[device]]
name = "u2"
direction = "sensor"
bus = "line"
address = {{ unit = 2, table = "input", address = 3 }}
"""


def readings(s: System, name: str) -> int:
    """The readings ``name`` got so far (a plain counter of the device table)."""
    return s.devtab.get(name).readings


def rate(s: System, name: str, seconds: float) -> float:
    """``name``'s readings per second over the next ``seconds``."""
    r0, t0 = readings(s, name), time.monotonic()
    time.sleep(seconds)
    return (readings(s, name) - r0) / (time.monotonic() - t0)


def wait_for(pred: object, limit: float) -> float:
    """Seconds until ``pred()`` holds (RuntimeError after ``limit``)."""
    t0 = time.monotonic()
    while not pred():   # type: ignore[operator]
        if time.monotonic() - t0 > limit:
            raise RuntimeError("timed out")
        time.sleep(0.01)
    return time.monotonic() - t0


def main() -> None:
    """Run the measurement and print it."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=10.0, help="s of the baseline window")
    ap.add_argument("--timeout", type=float, default=1.0, help="the bus's timeout (s)")
    ap.add_argument("--retries", type=int, default=0, help="the bus's retries")
    args = ap.parse_args()
    logging.disable(logging.ERROR)      # unit 2's timeouts are the point: keep the table alone
    with tempfile.TemporaryDirectory() as tmp:
        exe = compile_slave(Path(tmp))
        hub = LineHub(3)
        slaves = {u: RtuSlave(exe, Path(hub.port(u)), u, "default") for u in (1, 2)}
        path = Path(tmp) / "line.toml"
        path.write_text(MAP.format(port=hub.port(0), timeout=args.timeout,
                                   retries=args.retries, period=PERIOD), encoding="utf-8")
        bus = BusSpec(name="line", kind="modbus-rtu",
                      options={"timeout": args.timeout, "retries": args.retries,
                               "poll_period": PERIOD})
        cap = dead_unit_backoff(bus)
        cost = args.timeout * (args.retries + 1)
        s = System([path], clock=RealClock(), machines=[0])
        s.start()
        try:
            wait_for(lambda: readings(s, "u1") > 3 and readings(s, "u2") > 3, 10)
            alive = rate(s, "u1", args.window)
            slaves.pop(2).close()
            # the ramp: tries after 1, 2, 4 ... polls up to the cap, each try costing `cost`
            steps, k = [], 1
            while k < cap:
                steps.append(k)
                k *= 2
            ramp_s = sum(steps) * PERIOD + len(steps) * cost
            ramp = rate(s, "u1", ramp_s)
            steady_s = max(args.window, 2 * (cap * PERIOD + cost))
            steady = rate(s, "u1", steady_s)
            slaves[2] = RtuSlave(exe, Path(hub.port(2)), 2, "default")
            before = readings(s, "u2")
            back = wait_for(lambda: readings(s, "u2") > before, 2 * (cap * PERIOD + cost) + 10)
        finally:
            s.shutdown()
            for sl in slaves.values():
                sl.close()
            hub.close()
    print(f"Modbus RTU line, 2 stock libmodbus slaves, 19200 8N1, poll period {PERIOD} s, "
          f"timeout {args.timeout} s, retries {args.retries}; dead unit tried at most every "
          f"{cap} poll periods (dead_unit_backoff)")
    print(f"  unit 1, 2 of 2 alive        : {alive:6.2f} readings/s  (baseline, "
          f"{args.window:g} s)")
    print(f"  unit 1, unit 2 dead (ramp)  : {ramp:6.2f} readings/s  {ramp / alive:6.1%}  "
          f"(first {ramp_s:.1f} s)")
    print(f"  unit 1, unit 2 dead (steady): {steady:6.2f} readings/s  {steady / alive:6.1%}  "
          f"({steady_s:.1f} s; target >= 90 %)")
    print(f"  unit 2 restarted            : readings again after {back:.1f} s (its next try)")


if __name__ == "__main__":
    main()
