"""model64 - the thesis' cycle model of section 6.4 (interrupts/s on 1, 2 and 3 satellites).

Computes, from the figures the thesis states in its text, how many sensor/actuator interrupts per
second one, two and three MC68000 satellites (8 MHz) can serve, and reproduces its table:
1150 / 2100 / 3075 interrupts/s in total (1150 / 1050 / 1025 per CPU).

Stated in the text (used as given):
* one system call ("resched" as the average system routine): 300 + 50 = 350 cycles;
* per sensor/actuator interrupt: 1750 interrupt handling (five system routines), 1050 driver,
  2000 user-written filtering, 2100 message transfer, 2000 consumer/producer task, 700
  rescheduling after a task's interruption or completion (two system calls);
* 1.25 task executions per interrupt: one for the driver, 0.25 for the higher levels (five
  messages at level n make one at level n+1);
* remote (inter-processor) tasks per interrupt: 0.125 with 2 machines, 0.166 with 3;
* 7,790,000 cycles/s left after clock processing.

Figure 6.7 (the per-item weights, and the inter-processor overhead on its left-hand side) is an
image not in the text, so the model has to assume, and prints, these:
* A1 the driver's own task execution is its user-written filtering plus one rescheduling
  (2000 + 700); a higher-level task execution is one message transfer, the task and one
  rescheduling (2100 + 2000 + 700) - with A1, the local total 6,700 cycles/interrupt gives
  7,790,000 / 6,700 = 1,162.7, the thesis' 1150;
* A2 clock processing is 60 Hz x 10 system calls x 350 = 210,000 cycles per *second* (the text
  says "per minute"; only per second gives 8,000,000 - 210,000 = 7,790,000);
* A3 the thesis' per-CPU figures are rounded down to a multiple of 25;
* A4 one inter-processor message costs three groups of five system routines (3 x 1750 = 5,250
  cycles: the communications manager and the software interrupt on the sending machine, the
  communications interrupt on the receiving one). The thesis' own totals bound this cost: with
  A1 and A3, 2 satellites at 1050/CPU and 3 at 1025/CPU hold only for a cost in
  (4,372, 5,422] cycles (:func:`remote_cost_bounds` computes the interval), and 5,250 lies in it.

Usage: python -m chcos.apps.bench.model64 [--json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass

CPU_HZ = 8_000_000
SYSTEM_CALL = 300 + 50
CLOCK_HZ = 60
CLOCK_CALLS = 10
CYCLES_LEFT = 7_790_000  # stated; CPU_HZ - clock processing (A2)

INTERRUPT_HANDLING = 5 * SYSTEM_CALL  # 1750
DRIVER = 3 * SYSTEM_CALL  # 1050
USER_FILTERING = 2000
MESSAGE_TRANSFER = 6 * SYSTEM_CALL  # 2100
TASK = 2000
RESCHEDULING = 2 * SYSTEM_CALL  # 700

HIGHER_TASKS_PER_INTERRUPT = 0.25  # 1.25 task executions per interrupt, one the driver's
REMOTE_TASKS = {1: 0.0, 2: 0.125, 3: 0.166}  # stated per interrupt
REMOTE_MESSAGE = 3 * INTERRUPT_HANDLING  # A4: 5250
ROUND_TO = 25  # A3

THESIS_TABLE = {1: (1150, 1150), 2: (1050, 2100), 3: (1025, 3075)}  # per CPU, total

ASSUMPTIONS = (
    "A1 driver task execution = user filtering + 1 rescheduling (2000+700); a higher-level task "
    "execution = message transfer + task + rescheduling (2100+2000+700)",
    "A2 clock processing = 60 Hz x 10 calls x 350 = 210,000 cycles per second (text: 'per "
    "minute'; only per second gives 8,000,000 - 210,000 = 7,790,000)",
    "A3 the thesis' per-CPU figures are rounded down to a multiple of 25",
    "A4 one inter-processor message = 3 x 1750 = 5,250 cycles (sender's communications manager "
    "+ software interrupt, receiver's communications interrupt); figure 6.7 is not in the text, "
    "the thesis' own totals bound it to the interval printed above",
)


@dataclass(frozen=True)
class Row:
    """One configuration of the model."""

    satellites: int
    cycles_per_interrupt: float
    exact_per_cpu: float
    per_cpu: int
    total: int
    ratio_to_one: float


def clock_cycles() -> int:
    """Cycles/s the clock interrupt handler takes (A2)."""
    return CLOCK_HZ * CLOCK_CALLS * SYSTEM_CALL


def local_cycles() -> int:
    """Cycles for one interrupt and its 1.25 task executions, all on one machine (A1)."""
    fixed = INTERRUPT_HANDLING + DRIVER + USER_FILTERING + RESCHEDULING
    higher = MESSAGE_TRANSFER + TASK + RESCHEDULING
    return fixed + round(HIGHER_TASKS_PER_INTERRUPT * higher)


def cycles_per_interrupt(satellites: int, remote_message: float = REMOTE_MESSAGE) -> float:
    """Cycles per interrupt on ``satellites`` machines (1..3); raises KeyError otherwise."""
    return local_cycles() + REMOTE_TASKS[satellites] * remote_message


def row(satellites: int, remote_message: float = REMOTE_MESSAGE) -> Row:
    """The model's figures for ``satellites`` machines (1..3); raises KeyError otherwise."""
    c = cycles_per_interrupt(satellites, remote_message)
    exact = CYCLES_LEFT / c
    per_cpu = int(exact // ROUND_TO) * ROUND_TO
    one = int(CYCLES_LEFT / cycles_per_interrupt(1) // ROUND_TO) * ROUND_TO
    return Row(satellites, c, exact, per_cpu, per_cpu * satellites, per_cpu * satellites / one)


def table(remote_message: float = REMOTE_MESSAGE) -> list[Row]:
    """The model for 1, 2 and 3 satellites."""
    return [row(n, remote_message) for n in (1, 2, 3)]


def remote_cost_bounds() -> tuple[float, float]:
    """The interval (low, high] of inter-processor message costs for which the model (A1, A3)
    gives exactly the thesis' 1050 per CPU on 2 satellites and 1025 on 3."""
    lo, hi = 0.0, math.inf
    for n in (2, 3):
        per_cpu = THESIS_TABLE[n][0]
        # per_cpu <= CYCLES_LEFT / c < per_cpu + ROUND_TO
        c_hi = CYCLES_LEFT / per_cpu
        c_lo = CYCLES_LEFT / (per_cpu + ROUND_TO)
        lo = max(lo, (c_lo - local_cycles()) / REMOTE_TASKS[n])
        hi = min(hi, (c_hi - local_cycles()) / REMOTE_TASKS[n])
    return lo, hi


def report() -> str:
    """The model as text: assumptions, per-satellite and total interrupts/s, ratios."""
    lo, hi = remote_cost_bounds()
    lines = [f"thesis 6.4 cycle model: {CPU_HZ:,} cycles/s, clock {clock_cycles():,} cycles/s, "
             f"{CYCLES_LEFT:,} left; local interrupt {local_cycles():,} cycles; "
             f"inter-processor message {REMOTE_MESSAGE:,} cycles "
             f"(consistent with the thesis' totals for ({lo:,.0f}, {hi:,.0f}])"]
    lines += [f"  {a}" for a in ASSUMPTIONS]
    lines.append(f"  {'satellites':>10} {'cycles/int':>11} {'exact/CPU':>10} {'per CPU':>8} "
                 f"{'total':>6} {'x of 1':>7}  thesis")
    for r in table():
        tp, tt = THESIS_TABLE[r.satellites]
        lines.append(f"  {r.satellites:>10} {r.cycles_per_interrupt:>11,.1f} "
                     f"{r.exact_per_cpu:>10,.1f} {r.per_cpu:>8,} {r.total:>6,} "
                     f"{r.ratio_to_one:>6.2f}x  {tp}/CPU, {tt} total")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Print the model (or its rows as JSON with ``--json``)."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--json", action="store_true", help="the rows as JSON")
    args = ap.parse_args(argv)
    if args.json:
        print(json.dumps({"rows": [asdict(r) for r in table()],
                          "remote_cost_bounds": remote_cost_bounds(),
                          "assumptions": list(ASSUMPTIONS)}))
    else:
        print(report())
    return 0


if __name__ == "__main__":
    sys.exit(main())
