"""svg - a small, dependency-free SVG plot of latency distributions (empirical CDFs).

Each series is drawn as a step curve of the fraction of samples at or below a latency, on a
logarithmic latency axis (so microsecond processing times and the NBS cycle of tens of
milliseconds fit one picture). Samples at or below the axis minimum are drawn at the left edge
and the legend says how many there were (virtual-time CHC reactions are exactly 0).
Errors: :class:`~chcos.apps.bench.stats.StatsError` for a series without samples, ConfigError for a
bad axis range.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from html import escape
from pathlib import Path

from chcos.apps.bench.stats import ecdf, summarize
from chcos.errors import ConfigError

__all__ = ["PALETTE", "Series", "ecdf_svg", "write_ecdf_svg"]

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#7f7f7f")


@dataclass(frozen=True)
class Series:
    """One distribution: its legend ``name``, ``samples`` in seconds, and a dash pattern."""

    name: str
    samples: Sequence[float]
    dash: str = ""


def _fmt_time(s: float) -> str:
    if s >= 1e-3:
        return f"{s * 1e3:.3g} ms"
    return f"{s * 1e6:.3g} µs"


def ecdf_svg(series: Sequence[Series], title: str, *, x_min: float = 1e-5, x_max: float = 0.1,
             width: int = 860, height: int = 500) -> str:
    """The SVG document (text) of ``series`` as empirical CDFs on a log axis from ``x_min`` to
    ``x_max`` seconds. Raises ConfigError for a bad range, StatsError for an empty series."""
    if not 0 < x_min < x_max:
        raise ConfigError(f"plot axis: need 0 < x_min < x_max, got {x_min}, {x_max}")
    left, right, top, bottom = 70, 20, 50, 60 + 18 * len(series)
    pw, ph = width - left - right, height - top - bottom
    lo, hi = math.log10(x_min), math.log10(x_max)

    def x(v: float) -> float:
        v = min(max(v, x_min), x_max)
        return left + (math.log10(v) - lo) / (hi - lo) * pw

    def y(f: float) -> float:
        return top + (1.0 - f) * ph

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
           f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="12">',
           f'<rect width="{width}" height="{height}" fill="white"/>',
           f'<text x="{width / 2}" y="24" text-anchor="middle" font-size="15">'
           f'{escape(title)}</text>']
    # grid and axes
    for e in range(math.ceil(lo), math.floor(hi) + 1):
        gx = x(10.0 ** e)
        out.append(f'<line x1="{gx:.1f}" y1="{top}" x2="{gx:.1f}" y2="{top + ph}" '
                   'stroke="#ddd"/>')
        out.append(f'<text x="{gx:.1f}" y="{top + ph + 16}" text-anchor="middle">'
                   f'{escape(_fmt_time(10.0 ** e))}</text>')
    for k in range(0, 11, 2):
        f = k / 10
        out.append(f'<line x1="{left}" y1="{y(f):.1f}" x2="{left + pw}" y2="{y(f):.1f}" '
                   'stroke="#ddd"/>')
        out.append(f'<text x="{left - 6}" y="{y(f) + 4:.1f}" text-anchor="end">{f:.1f}</text>')
    out.append(f'<rect x="{left}" y="{top}" width="{pw}" height="{ph}" fill="none" '
               'stroke="#333"/>')
    out.append(f'<text x="{left + pw / 2}" y="{top + ph + 34}" text-anchor="middle">'
               'reaction latency (log scale)</text>')
    out.append(f'<text x="16" y="{top + ph / 2}" text-anchor="middle" '
               f'transform="rotate(-90 16 {top + ph / 2})">fraction of reactions ≤ latency</text>')
    # curves and legend
    for i, s in enumerate(series):
        color = PALETTE[i % len(PALETTE)]
        pts = ecdf(s.samples, 400)
        path = [f"M{x(pts[0][0]):.1f},{y(0.0):.1f}"]
        prev = 0.0
        for v, f in pts:
            path.append(f"L{x(v):.1f},{y(prev):.1f}L{x(v):.1f},{y(f):.1f}")
            prev = f
        path.append(f"L{left + pw:.1f},{y(prev):.1f}")
        dash = f' stroke-dasharray="{s.dash}"' if s.dash else ""
        out.append(f'<path d="{"".join(path)}" fill="none" stroke="{color}" '
                   f'stroke-width="2"{dash}/>')
        sm = summarize(s.samples)
        at_min = sum(1 for v in s.samples if v <= x_min)
        note = f", {at_min} at ≤ {_fmt_time(x_min)}" if at_min else ""
        ly = top + ph + 52 + 18 * i
        out.append(f'<line x1="{left}" y1="{ly - 4}" x2="{left + 30}" y2="{ly - 4}" '
                   f'stroke="{color}" stroke-width="2"{dash}/>')
        out.append(f'<text x="{left + 38}" y="{ly}">{escape(s.name)}: n={sm.n}, '
                   f'p50 {escape(_fmt_time(sm.p50))}, p99 {escape(_fmt_time(sm.p99))}, '
                   f'max {escape(_fmt_time(sm.max))}{escape(note)}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def write_ecdf_svg(path: str | Path, series: Sequence[Series], title: str) -> Path:
    """Write :func:`ecdf_svg` to ``path`` (directories made as needed); returns the path."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(ecdf_svg(series, title), encoding="utf-8")
    return p
