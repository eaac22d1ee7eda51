"""rundigest - the welding job's run digest: what a virtual-time run of the cell did, hashed.

:func:`run_digest` builds the cell on a binding (``direct`` or ``buses``), runs the job on
virtual time for a number of seconds and returns the run's document and its hash: the weld
(length, share in the band, too hot, too cold, without gas, the outcome, the faults and how they
were handled), the messages per level, the assassin's latencies, the last outputs, every
device's readings and commands, every task's executions, the event log with its virtual times
(:func:`chcos.system.digest.system_doc`) and, after the shutdown, what became of every safe
value. Two runs of the same binding, scenario, seed and duration must give the same hash on a
quiet or a loaded machine and whatever ``PYTHONHASHSEED`` (``python -m tools.run_digest``,
``vcan_tests/test_vtime_digest.py``). Raises what :func:`chcos.apps.weld.cell.open_cell` raises.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from chcos.apps.weld.cell import open_cell
from chcos.system.digest import digest_of, system_doc


@dataclass(frozen=True)
class RunDigest:
    """A run's document (plain data) and its SHA-256 (:func:`chcos.system.digest.digest_of`)."""

    doc: dict[str, Any]
    digest: str


def run_digest(binding: str = "direct", seconds: float = 20.0, *, scenario: str = "",
               seed: int = 0, workdir: str | Path | None = None) -> RunDigest:
    """Run the welding job on ``binding`` for ``seconds`` of virtual time (less if it finishes
    first) and digest it (see the module doc)."""
    with open_cell(binding, scenario=scenario, seed=seed, workdir=workdir) as cell:
        cell.start_job()
        cell.run(seconds)
        summary = cell.summary()
        doc: dict[str, Any] = {
            "binding": binding, "scenario": scenario, "seed": seed,
            "weld": {k: summary[k] for k in ("seconds", "outcome", "seam_mm", "welded_mm",
                                             "in_band_mm", "in_band_pct", "too_hot_mm",
                                             "too_cold_mm", "no_gas_mm", "band", "faults",
                                             "handled")},
            "messages": summary["messages"], "steps_by_level": summary["steps_by_level"],
            "latency_s": summary["latency_s"], "outputs": summary["outputs"],
            "system": system_doc(cell.system, cell.events),
        }
    outcomes = cell.system.devtab.safe_outcomes
    doc["shutdown"] = {name: {"written": o.written, "reason": o.reason, "attempts": o.attempts}
                       for name, o in sorted(outcomes.items())}
    return RunDigest(doc, digest_of(doc))
