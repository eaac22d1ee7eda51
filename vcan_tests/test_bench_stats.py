"""The measuring helpers of the benchmark suite: percentiles, summaries, ECDF, the reaction
probe and the SVG plot (deterministic, no timing)."""

from __future__ import annotations

import itertools
import random
import xml.etree.ElementTree as ET

import pytest

from chcos.apps.bench.load import ReactionProbe
from chcos.apps.bench.stats import StatsError, ecdf, percentile, summarize
from chcos.apps.bench.svg import Series, ecdf_svg
from chcos.errors import ChcosError


def test_percentile_is_nearest_rank() -> None:
    xs = list(range(1, 101))
    random.Random(3).shuffle(xs)
    assert percentile(xs, 50) == 50
    assert percentile(xs, 99) == 99
    assert percentile(xs, 100) == 100
    assert percentile(xs, 0) == 1
    assert percentile(xs, 1) == 1
    assert percentile(xs, 99.5) == 100
    assert percentile(range(1, 1001), 99) == 990
    assert percentile(range(1, 1001), 99.9) == 999
    assert percentile([7.5], 99) == 7.5
    # p99 of 10 samples is the largest: at least 99 % of samples must be at or below it
    assert percentile(range(10), 99) == 9
    assert percentile(range(10), 90) == 8


def test_percentile_errors_are_chcos_errors() -> None:
    with pytest.raises(StatsError):
        percentile([], 50)
    with pytest.raises(StatsError, match="outside"):
        percentile([1.0], 101)
    with pytest.raises(ChcosError):
        summarize([])


def test_summary_and_scaling() -> None:
    s = summarize([0.004, 0.001, 0.002, 0.003])
    assert (s.n, s.p50, s.p99, s.max, s.min) == (4, 0.002, 0.004, 0.004, 0.001)
    assert s.mean == pytest.approx(0.0025)
    ms = s.scaled(1e3)
    assert (ms.n, ms.p50, ms.max) == (4, 2.0, 4.0)
    assert ms.as_dict()["p99"] == 4.0


def test_ecdf_keeps_the_ends_and_is_monotone() -> None:
    xs = [float(i) for i in range(1000)]
    pts = ecdf(xs, 50)
    assert pts[0] == (0.0, 0.001) and pts[-1] == (999.0, 1.0)
    assert len(pts) <= 50
    assert all(a[0] <= b[0] and a[1] < b[1] for a, b in itertools.pairwise(pts))
    assert ecdf([2.0, 1.0], 10) == [(1.0, 0.5), (2.0, 1.0)]
    with pytest.raises(StatsError):
        ecdf([], 10)


def test_reaction_probe_pairs_events_with_the_first_reacting_write() -> None:
    now = [0.0]
    probe = ReactionProbe(lambda: now[0], {"M1": ("S1", "S2"), "M2": ("S3",)})
    probe.event("S1", 1.0)
    probe.event("S1", 1.5)          # still pending from 1.0: the first event counts
    now[0] = 2.0
    probe.written("M2", 0.0)        # M2 does not react to S1
    assert probe.samples == []
    probe.written("M1", 0.0)
    assert probe.samples == [1.0]
    probe.written("M1", 0.0)        # nothing pending any more
    probe.event("S3", 3.0)
    probe.event("S2", 3.1)
    now[0] = 3.25
    probe.written("M2", 0.0)
    assert probe.samples == [1.0, 0.25]
    probe.active = False
    probe.written("M1", 0.0)
    assert len(probe.samples) == 2


def test_svg_is_well_formed_and_names_every_series() -> None:
    doc = ecdf_svg([Series("NBS", [0.001, 0.02, 0.028]), Series("CHC", [0.0, 0.0], "4,2")],
                   "t <title>")
    root = ET.fromstring(doc)
    assert root.tag.endswith("svg")
    text = "".join(root.itertext())
    assert "NBS: n=3" in text and "CHC: n=2" in text and "2 at ≤ 10 µs" in text
    assert "t <title>" in text
    with pytest.raises(ChcosError):
        ecdf_svg([Series("x", [1.0])], "t", x_min=1.0, x_max=0.5)
