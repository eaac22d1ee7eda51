#!/usr/bin/env python3
"""bench_saturated - a saturated CAN bus (8,800 frames/s in, 1,000 answers/s out) through chcos.

Runs :func:`chcos.apps.bench.saturated.run_saturated` (see its module doc for what is sent,
counted and timed) on one core and prints the rates, the frame accounting (no frame lost without
a count), chcos' CPU share of the core (target <= 50 %), the reaction p50/p99/max and the
machine's load. Exit status 1 if a frame was lost without a count.
Usage: python -m tools.bench_saturated [--duration S] [--rate-in N] [--rate-out N] [--runs N]
                                      [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from dataclasses import asdict
from pathlib import Path

from chcos.apps.bench.saturated import QUEUE, report, run_saturated


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark ``--runs`` times and print each run and min/median/max."""
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds measured per run")
    ap.add_argument("--rate-in", type=float, default=8800.0, help="frames/s the peer sends")
    ap.add_argument("--rate-out", type=float, default=1000.0, help="answers/s asked of tasks")
    ap.add_argument("--queue", type=int, default=QUEUE,
                    help="readings each sensor link holds (0: newest-wins, requests overwritten "
                         "unread go unanswered, counted)")
    ap.add_argument("--runs", type=int, default=1, help="runs (min/median/max when > 1)")
    ap.add_argument("--json", type=Path, help="write every run's figures here")
    args = ap.parse_args(argv)
    runs = []
    bad = False
    for _ in range(max(1, args.runs)):
        r = run_saturated(args.duration, args.rate_in, args.rate_out, queue=args.queue)
        print(report(r), flush=True)
        bad |= any(r.unaccounted().values())
        runs.append(r)
    if len(runs) > 1:
        for name, vals in (("chcos CPU %", [r.cpu_chcos * 100 for r in runs]),
                           ("reaction p99 ms", [r.percentile(0.99) * 1e3 for r in runs])):
            print(f"{name}: min {min(vals):.3f}, median {statistics.median(vals):.3f}, "
                  f"max {max(vals):.3f} over {len(vals)} runs")
    if args.json:
        args.json.write_text(json.dumps([dict(asdict(r), reaction_p99=r.percentile(0.99),
                                              cpu_chcos=r.cpu_chcos) | {"reaction": []}
                                         for r in runs]))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
