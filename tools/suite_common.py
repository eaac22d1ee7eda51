"""suite_common - what the sections of tools/bench_suite.py share: the run's state
(:class:`SuiteRun`), the min / median / max cells, the verdicts, latency percentiles in ms and
pinning to one core."""

from __future__ import annotations

import contextlib
import os
import statistics
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from chcos.apps.bench.stats import Summary, summarize

ROOT = Path(__file__).resolve().parent.parent
THESIS_INTERRUPTS_PER_SATELLITE = 1150  # thesis 6.4: one MC68000 satellite, sensor+actuator

Row = tuple[str, str, str, str]


@dataclass
class SuiteRun:
    """One run of the suite: its sizes, the JSON results and the table rows so far."""

    quick: bool
    reps: int
    seed: int
    out: Path
    soak_s: float
    saturated_s: float
    res: dict[str, Any] = field(default_factory=dict)
    rows: list[Row] = field(default_factory=list)
    #: samples kept for the latency plot: (label, samples in seconds, dash pattern)
    plot: list[tuple[str, list[float], str]] = field(default_factory=list)


def spread(xs: Sequence[float], fmt: str = "{:.2f}") -> str:
    """``min / median / max`` of ``xs`` (one value printed alone, none as ``no data``)."""
    if not xs:
        return "no data"
    if len(xs) == 1:
        return fmt.format(xs[0])
    return " / ".join(fmt.format(v) for v in (min(xs), statistics.median(xs), max(xs)))


def med(xs: Sequence[float]) -> float:
    """The median, on which every real-time target is judged."""
    return float(statistics.median(xs))


def yes(ok: bool) -> str:
    """The table's verdict."""
    return "yes" if ok else "NO"


def p99s(batches: Sequence[Sequence[float]]) -> list[float]:
    """The p99 of each batch of latency samples, in milliseconds."""
    return [summarize(b).p99 * 1e3 for b in batches if b]


def p50s(batches: Sequence[Sequence[float]]) -> list[float]:
    """The p50 of each batch, in milliseconds."""
    return [summarize(b).p50 * 1e3 for b in batches if b]


def lat(sm: Summary) -> str:
    """p50/p99/max of a latency summary in ms."""
    return f"p50 {sm.p50 * 1e3:.3f} / p99 {sm.p99 * 1e3:.3f} / max {sm.max * 1e3:.3f} ms"


@contextlib.contextmanager
def one_core() -> Iterator[int]:
    """Pin this thread (and the threads it starts) to one allowed core; restore afterwards."""
    allowed = os.sched_getaffinity(0)
    core = min(allowed)
    os.sched_setaffinity(0, {core})
    try:
        yield core
    finally:
        os.sched_setaffinity(0, allowed)
