"""learning - the cell learns what precedes a stuck tip: the learning curve over repeated runs.

:func:`learning_curve` runs the welding job ``runs`` times with the same scenario (by default a
tip that starts to stub into the pool 50 s into the job and freezes 2 s later) in one working
directory, so C1's learned examples (``learned/C1-tip.json`` beside the map) carry from run to
run. For each run it reports when the precursor began (the fault fired), when the cell reacted
and how (``hard-coded``: C1 saw the short circuit of a frozen tip; ``learned``: C1 recognized
the trend it learned and D2 cut the wire feed), the time from one to the other, whether the tip
froze and how much was welded. ``python -m chcos.apps.weld.learning [--runs N] [--reset]`` prints
the table. Raises ChcosError (from :func:`chcos.apps.weld.cell.open_cell`) if the cell cannot be
built.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TextIO

from chcos.errors import ChcosError

SCENARIO = "tip-stuck(precursor=2s)@t=50s"
"""The default scenario: the wire stubs into the pool from t=50 s and freezes at t=52 s."""


def forget(workdir: str | Path) -> None:
    """Delete everything the cell learned in ``workdir`` (its ``learned`` directory)."""
    shutil.rmtree(Path(workdir) / "learned", ignore_errors=True)


def one_run(workdir: Path, scenario: str, binding: str = "direct",
            limit: float = 200.0) -> dict[str, Any]:
    """One job in ``workdir``; returns the row of the learning curve."""
    from chcos.apps.weld.cell import open_cell

    with open_cell(binding, scenario=scenario, workdir=workdir) as cell:
        cell.start_job()
        cell.run(limit)
        m = cell.model
        fired = [e.t for e in m.events if e.fault.kind == "tip-stuck" and e.action == "fired"]
        froze = any(e.fault.kind == "tip-stuck" and e.action == "froze" for e in m.events)
        every = cell.world("C1")["sensory"].get("reactions", [])
        reactions = [r for r in every if fired and r["t"] >= fired[0]]
        early = [r for r in every if not fired or r["t"] < fired[0]]
        first = reactions[0] if reactions else None
        summary = cell.summary()
        outcome = cell.outcome()
    return {
        "onset": fired[0] if fired else None,
        "reaction": first["kind"] if first else "none",
        "after_s": (first["t"] - fired[0]) if first and fired else None,
        "froze": froze or m.tip_stuck, "false_alarms": len(early),
        "welded_mm": summary["welded_mm"], "seam_mm": summary["seam_mm"],
        "outcome": (outcome or {}).get("outcome", "unfinished"),
    }


def learning_curve(runs: int = 5, scenario: str = SCENARIO, workdir: str | Path = ".",
                   binding: str = "direct", out: TextIO | None = None) -> list[dict[str, Any]]:
    """Run the job ``runs`` times in ``workdir`` (learned data kept between runs); print a row
    per run to ``out`` if given; return the rows."""
    work = Path(workdir)
    rows = []
    if out is not None:
        print(f"learning curve: {runs} runs of {scenario!r} ({binding} binding), learned data "
              f"in {work / 'learned'}", file=out)
        print("  run  precursor at  reaction     after    tip froze  welded", file=out)
    for i in range(1, runs + 1):
        row = one_run(work, scenario, binding)
        rows.append(row)
        if out is not None:
            after = "-" if row["after_s"] is None else f"{row['after_s']:.2f} s"
            onset = "-" if row["onset"] is None else f"{row['onset']:.2f} s"
            print(f"  {i:3d}  {onset:>12s}  {row['reaction']:<11s}  {after:>7s}  "
                  f"{'yes' if row['froze'] else 'no':>9s}  {row['welded_mm']:.0f} of "
                  f"{row['seam_mm']:.0f} mm ({row['outcome']})", file=out, flush=True)
    return rows


def main(argv: Sequence[str] | None = None, out: TextIO = sys.stdout) -> int:
    """The command line; 0 on success, 2 if the cell could not be built."""
    ap = argparse.ArgumentParser(prog="python -m chcos.apps.weld.learning",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5, help="how many runs (default 5)")
    ap.add_argument("--scenario", default=SCENARIO, help=f"default {SCENARIO!r}")
    ap.add_argument("--workdir", default=".", help="where the map and learned data live")
    ap.add_argument("--binding", choices=("direct", "buses"), default="direct")
    ap.add_argument("--reset", action="store_true", help="forget what was learned first")
    args = ap.parse_args(argv)
    if args.runs < 1:
        ap.error(f"--runs {args.runs}: expected >= 1")
    if args.reset:
        forget(args.workdir)
    try:
        learning_curve(args.runs, args.scenario, args.workdir, args.binding, out)
    except ChcosError as exc:
        print(f"learning: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
