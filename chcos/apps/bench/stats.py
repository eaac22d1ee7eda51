"""stats - percentiles and summaries of latency samples, exact and deterministic.

Percentiles use the nearest-rank definition: the p-th percentile of n sorted samples is the
smallest sample with at least p % of all samples at or below it (``s[ceil(p/100 * n) - 1]``), so
a reported p99 is always a latency that was actually observed, and "p99 under 0.5 ms" means at
least 99 % of the samples were. Errors: :class:`StatsError` (a
:class:`~chcos.errors.ChcosError`) for an empty sample set or a percentile outside 0..100.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

from chcos.errors import ChcosError

__all__ = ["StatsError", "Summary", "ecdf", "percentile", "summarize"]


class StatsError(ChcosError):
    """A statistic was asked of no samples, or a percentile outside 0..100."""


def percentile(samples: Iterable[float], q: float, *, presorted: bool = False) -> float:
    """The nearest-rank ``q``-th percentile (0 < q <= 100; q = 0 gives the minimum) of
    ``samples``. Raises StatsError for no samples or ``q`` outside 0..100."""
    if not 0 <= q <= 100:
        raise StatsError(f"percentile {q!r} outside 0..100")
    s = list(samples) if presorted else sorted(samples)
    if not s:
        raise StatsError("percentile of no samples")
    rank = max(1, math.ceil(q / 100 * len(s) - 1e-9))
    return s[min(rank, len(s)) - 1]


@dataclass(frozen=True)
class Summary:
    """Count, p50, p99, maximum, minimum and mean of a set of samples (same unit as the
    samples; :meth:`scaled` converts, e.g. seconds to milliseconds)."""

    n: int
    p50: float
    p99: float
    max: float
    min: float
    mean: float

    def scaled(self, factor: float) -> Summary:
        """The same summary with every value (not the count) multiplied by ``factor``."""
        return Summary(self.n, self.p50 * factor, self.p99 * factor, self.max * factor,
                       self.min * factor, self.mean * factor)

    def as_dict(self) -> dict[str, float]:
        """The summary as a JSON-ready dict."""
        return {k: float(v) for k, v in asdict(self).items()}


def summarize(samples: Iterable[float]) -> Summary:
    """The :class:`Summary` of ``samples``. Raises StatsError if there are none."""
    s = sorted(samples)
    if not s:
        raise StatsError("summary of no samples")
    return Summary(len(s), percentile(s, 50, presorted=True), percentile(s, 99, presorted=True),
                   s[-1], s[0], math.fsum(s) / len(s))


def ecdf(samples: Sequence[float], points: int = 200) -> list[tuple[float, float]]:
    """At most ``points`` (value, fraction of samples <= value) pairs of the empirical
    distribution, evenly spaced in rank, always including the minimum and the maximum.
    Raises StatsError for no samples or fewer than 2 points."""
    if points < 2:
        raise StatsError(f"an ECDF needs at least 2 points, got {points}")
    s = sorted(samples)
    if not s:
        raise StatsError("ECDF of no samples")
    n = len(s)
    if n <= points:
        return [(v, (i + 1) / n) for i, v in enumerate(s)]
    idx = sorted({round(k * (n - 1) / (points - 1)) for k in range(points)})
    return [(s[i], (i + 1) / n) for i in idx]
