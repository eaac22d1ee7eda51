#!/usr/bin/env python3
"""run_digest - the welding job's run digest on virtual time: one line with the hash, the weld and
the counts, or the whole document (``--json FILE``).

Two runs of the same binding, scenario, seed and duration must print the same hash on a quiet or
a loaded machine and whatever ``PYTHONHASHSEED`` (issue 47; ``vcan_tests/test_vtime_digest.py``
runs this tool that way). ``--compare FILE`` reads a document written before by ``--json`` and
names where this run differs from it (exit status 1 if it does).
Usage: python -m tools.run_digest [--binding direct|buses] [--seconds S] [--scenario TEXT]
                                  [--seed N] [--json FILE] [--compare FILE]
Errors: exit status 2 with the reason when the cell cannot be built.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from chcos.apps.weld.cell import BINDINGS
from chcos.apps.weld.rundigest import run_digest
from chcos.errors import ChcosError
from chcos.system.digest import differences, digest_of


def main(argv: list[str] | None = None) -> int:
    """Run, print the digest line; 0, or 1 when ``--compare`` found a difference."""
    doc = __doc__ or "run_digest"
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--binding", choices=BINDINGS, default="direct")
    ap.add_argument("--seconds", type=float, default=20.0, help="virtual seconds (20)")
    ap.add_argument("--scenario", default="", help="fault scenario (chcos run --scenario)")
    ap.add_argument("--seed", type=int, default=0, help="measurement-noise seed (0)")
    ap.add_argument("--json", type=Path, help="write the whole document here")
    ap.add_argument("--compare", type=Path, help="a document written by --json to compare with")
    args = ap.parse_args(argv)
    logging.getLogger("chcos").setLevel(logging.CRITICAL)   # the digest is the output
    try:
        run = run_digest(args.binding, args.seconds, scenario=args.scenario, seed=args.seed)
    except ChcosError as exc:
        print(f"run_digest: {exc}", file=sys.stderr)
        return 2
    weld = run.doc["weld"]
    steps = sum(t["steps"] for t in run.doc["system"]["tasks"].values())
    readings = sum(d["readings"] for d in run.doc["system"]["devices"].values())
    print(f"digest {run.digest} binding {args.binding} {weld['seconds']:.2f} s welded "
          f"{weld['welded_mm']:.3f} mm in band {weld['in_band_pct']:.3f} % task executions "
          f"{steps} readings {readings} events {len(run.doc['system'].get('events', []))}",
          flush=True)
    if args.json is not None:
        args.json.write_text(json.dumps(run.doc, default=repr, indent=1), encoding="utf-8")
    if args.compare is not None:
        other = json.loads(args.compare.read_text(encoding="utf-8"))
        ours = json.loads(json.dumps(run.doc, default=repr))
        if digest_of(other) != digest_of(ours):
            for line in differences(other, ours):
                print(f"  differs: {line}")
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
