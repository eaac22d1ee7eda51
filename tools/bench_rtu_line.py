"""bench_rtu_line - what one dead unit costs the live one on a Modbus RTU line (issue 38).

Two stock libmodbus slaves (vcan_tests/peers/rtu_slave.c with libmodbus' default response
timeout) share one line (a pty hub passing every frame to every side, as RS-485 does). In the
same run, two masters poll one register of each unit every poll period, one after the other
on the same line:

* a hand-written loop on pymodbus' own ``ModbusSerialClient`` (no chcos: read unit 1, read
  unit 2, sleep to the next period) - the baseline;
* chcos (a device map, :class:`chcos.system.embedded.System` on the real-time clock).

For each it measures unit 1's readings per second with both units alive, then with unit 2
killed: over the first backoff cycle after the kill (its first miss and the gap until its
next try, ``dead_unit_first`` poll periods: what the live unit keeps from the start) and, for
chcos, over the following cycles (steady); then how long after unit 2 restarts its readings
come back (bounded by one backoff cycle). Target: the live unit keeps >= 90 % of its own
rate from the kill on. Needs gcc, pkg-config and libmodbus-dev.

``python -m tools.bench_rtu_line [--window S] [--timeout S] [--retries N]``
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

from pymodbus.client import ModbusSerialClient
from pymodbus.exceptions import ModbusException

from chcos.devices.spec import BusSpec
from chcos.kernel.clock import RealClock
from chcos.system.embedded import System
from drivers.modbus_link import dead_unit_backoff, dead_unit_first
from tools.peer_rtu import LineHub, RtuSlave, compile_slave

PERIOD = 0.1
TARGET = 0.90
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


def rate(count: Callable[[], int], seconds: float) -> float:
    """Readings per second of ``count()`` over the next ``seconds``."""
    r0, t0 = count(), time.monotonic()
    time.sleep(seconds)
    return (count() - r0) / (time.monotonic() - t0)


def wait_for(pred: Callable[[], bool], limit: float) -> float:
    """Seconds until ``pred()`` holds (RuntimeError after ``limit``)."""
    t0 = time.monotonic()
    while not pred():
        if time.monotonic() - t0 > limit:
            raise RuntimeError("timed out")
        time.sleep(0.01)
    return time.monotonic() - t0


class PlainLoop:
    """The hand-written master: pymodbus' serial client polling unit 1 then unit 2 every
    period on a thread of its own, counting each unit's answered reads."""

    def __init__(self, port: str, timeout: float, retries: int) -> None:
        self.client = ModbusSerialClient(port, baudrate=19200, timeout=timeout, retries=retries)
        if not self.client.connect():
            raise RuntimeError(f"pymodbus cannot open {port}")
        self.count = {1: 0, 2: 0}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="plain-pymodbus", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        due = time.monotonic()
        while not self._stop.is_set():
            for unit, address in ((1, 2), (2, 3)):
                try:
                    rr = self.client.read_input_registers(address, count=1, device_id=unit)
                except ModbusException:
                    continue
                if not rr.isError():
                    self.count[unit] += 1
            due += PERIOD
            now = time.monotonic()
            if due < now:          # late: start again from now, as chcos' polls do
                due = now
            self._stop.wait(due - now)

    def close(self) -> None:
        """Stop the loop and close the port."""
        self._stop.set()
        self._thread.join(30)
        self.client.close()  # type: ignore[no-untyped-call]


def plain_run(hub: LineHub, slaves: dict[int, RtuSlave], exe: Path, args: argparse.Namespace,
              first_s: float) -> tuple[float, float]:
    """Unit 1's rates under the plain loop: both alive, and the first ``first_s`` s after unit 2
    died. Unit 2 runs again afterwards."""
    loop = PlainLoop(hub.port(0), args.timeout, args.retries)
    try:
        wait_for(lambda: loop.count[1] > 3 and loop.count[2] > 3, 10)
        alive = rate(lambda: loop.count[1], args.window)
        slaves.pop(2).close()
        dead = rate(lambda: loop.count[1], first_s)
    finally:
        loop.close()
        if 2 not in slaves:
            slaves[2] = RtuSlave(exe, Path(hub.port(2)), 2, "default")
    return alive, dead


def chcos_run(hub: LineHub, slaves: dict[int, RtuSlave], exe: Path, args: argparse.Namespace,
              tmp: Path, first_s: float, cycle_s: float) -> tuple[float, float, float, float]:
    """Unit 1's rates under chcos (alive, the first ``first_s`` s after unit 2 died, the next
    ``2 x cycle_s`` s) and the seconds until unit 2 reads again after its restart."""
    path = tmp / "line.toml"
    path.write_text(MAP.format(port=hub.port(0), timeout=args.timeout, retries=args.retries,
                               period=PERIOD), encoding="utf-8")
    s = System([path], clock=RealClock(), machines=[0])

    def readings(name: str) -> int:
        return s.devtab.get(name).readings

    s.start()
    try:
        wait_for(lambda: readings("u1") > 3 and readings("u2") > 3, 10)
        alive = rate(lambda: readings("u1"), args.window)
        slaves.pop(2).close()
        first = rate(lambda: readings("u1"), first_s)
        steady = rate(lambda: readings("u1"), max(args.window, 2 * cycle_s))
        slaves[2] = RtuSlave(exe, Path(hub.port(2)), 2, "default")
        before = readings("u2")
        back = wait_for(lambda: readings("u2") > before, cycle_s + 10)
    finally:
        s.shutdown()
    return alive, first, steady, back


def main() -> None:
    """Run both masters on the same line and print unit 1's rates side by side."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--window", type=float, default=10.0, help="s of the baseline windows")
    ap.add_argument("--timeout", type=float, default=1.0, help="the bus's timeout (s)")
    ap.add_argument("--retries", type=int, default=0, help="the bus's retries")
    args = ap.parse_args()
    logging.disable(logging.ERROR)      # unit 2's timeouts are the point: keep the table alone
    logging.getLogger("pymodbus").disabled = True
    bus = BusSpec(name="line", kind="modbus-rtu",
                  options={"timeout": args.timeout, "retries": args.retries,
                           "poll_period": PERIOD})
    cap, first_turns = dead_unit_backoff(bus), dead_unit_first(bus)
    cost = args.timeout * (args.retries + 1)
    first_s = first_turns * PERIOD + cost      # the first miss and the gap to the next try
    cycle_s = cap * PERIOD + cost
    with tempfile.TemporaryDirectory() as tmp:
        exe = compile_slave(Path(tmp))
        hub = LineHub(3)
        slaves = {u: RtuSlave(exe, Path(hub.port(u)), u, "default") for u in (1, 2)}
        try:
            p_alive, p_dead = plain_run(hub, slaves, exe, args, first_s)
            c_alive, c_first, c_steady, back = chcos_run(hub, slaves, exe, args, Path(tmp),
                                                         first_s, cycle_s)
        finally:
            for sl in slaves.values():
                sl.close()
            hub.close()
    met = c_first / c_alive >= TARGET and c_steady / c_alive >= TARGET
    print(f"Modbus RTU line, 2 stock libmodbus slaves (default response timeout), 19200 8N1, "
          f"poll period {PERIOD} s, timeout {args.timeout} s, retries {args.retries}; chcos "
          f"tries a dead unit again after {first_turns} poll periods, then doubling up to "
          f"{cap} (dead_unit_first, dead_unit_backoff)")
    print("  unit 1 readings/s                        pymodbus loop      chcos")
    print(f"  both alive ({args.window:g} s)                   {p_alive:8.2f}       "
          f"{c_alive:8.2f}")
    print(f"  unit 2 dead, first {first_s:5.1f} s from the kill {p_dead:8.2f} "
          f"{p_dead / p_alive:6.1%}  {c_first:8.2f} {c_first / c_alive:6.1%}")
    print(f"  unit 2 dead, next {max(args.window, 2 * cycle_s):5.1f} s (chcos)"
          f"                  {c_steady:8.2f} {c_steady / c_alive:6.1%}")
    print(f"  unit 2 restarted: chcos reads it again after {back:.1f} s (bound: one backoff "
          f"cycle, {cycle_s:.1f} s)")
    print(f"  target: unit 1 keeps >= {TARGET:.0%} of its rate from the kill on: "
          f"{'met' if met else 'NOT met'} (chcos {min(c_first, c_steady) / c_alive:.1%}, "
          f"plain loop {p_dead / p_alive:.1%})")


if __name__ == "__main__":
    main()
