"""diff - ``chcos diff GOLDEN NEW``: compare two traces of a run (``chcos run --trace``).

Prints the first divergence of each device and task with its time (:mod:`chcos.hil.diff`) and a
summary. Exit status 0: the traces agree; 1: they diverge; 2: one cannot be read (or the
arguments are wrong).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from chcos.hil.diff import compare, parse_tolerances, report_lines
from chcos.hil.trace import TraceError, read_trace


def parser() -> argparse.ArgumentParser:
    """The command line of ``chcos diff``."""
    ap = argparse.ArgumentParser(
        prog="chcos diff",
        description="Compare two traces of a run (chcos run SYSTEM --virtual --trace FILE): the "
                    "first divergence of each device and task with its virtual time, and a "
                    "summary. Values are compared as signals (within --tolerance), status "
                    "changes, commands, bus errors and task events as sequences. Exit status 0: "
                    "the same; 1: different; 2: a trace cannot be read.")
    ap.add_argument("golden", metavar="GOLDEN", help="the reference trace (.trace or .trace.gz)")
    ap.add_argument("new", metavar="NEW", help="the trace to check against it")
    ap.add_argument("--tolerance", action="append", default=[], metavar="DEVICE=NUMBER",
                    help="numbers of DEVICE (or of every device: *=NUMBER) that differ by at "
                         "most NUMBER count as the same (repeatable; default: exactly)")
    ap.add_argument("--text", action="store_true",
                    help="also compare the texts for people (failure reasons, event details), "
                         "which hold addresses and wall-clock figures that differ between runs")
    ap.add_argument("--limit", type=int, default=20, metavar="N",
                    help="print at most N divergences (default 20)")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """``chcos diff``; returns the exit status (0 same, 1 different, 2 unreadable)."""
    ap = parser()
    args = ap.parse_args(argv)
    try:
        tolerance = parse_tolerances(args.tolerance)
    except ValueError as exc:
        print(f"chcos diff: {exc}", file=sys.stderr)
        return 2
    try:
        golden = read_trace(args.golden)
        new = read_trace(args.new)
    except TraceError as exc:
        print(f"chcos diff: {exc}", file=sys.stderr)
        return 2
    result = compare(golden, new, tolerance, text=args.text)
    print("\n".join(report_lines(result, max(1, args.limit))))
    return 0 if result.same else 1
