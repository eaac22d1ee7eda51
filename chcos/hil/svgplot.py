"""svgplot - plots as inline SVG for self-contained HTML pages: a pair of axes with a grid, ticks
and labels around a body of paths (the welding report's pictures, :mod:`chcos.apps.weld.report`,
and the HIL evidence's diverging signals, :mod:`chcos.hil.report`)."""

from __future__ import annotations

import html
import math
from collections.abc import Callable, Sequence

W, H = 760, 240
"""Plot size (px) inside the margins."""
ML, MR, MT, MB = 60, 20, 20, 36


def scale(lo: float, hi: float, a: float, b: float) -> Callable[[float], float]:
    """The linear map of ``lo..hi`` onto ``a..b`` (a span of zero widens to one)."""
    if hi - lo < 1e-12:
        hi = lo + 1.0
    return lambda v: a + (v - lo) * (b - a) / (hi - lo)


def ticks(lo: float, hi: float, n: int = 6) -> list[float]:
    """About ``n`` round tick values (steps of 1, 2 or 5 times a power of ten) in ``lo..hi``."""
    span = max(hi - lo, 1e-9)
    raw = span / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((k * mag for k in (1, 2, 5, 10) if k * mag >= raw), default=10 * mag)
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step) + 1)]


def axes(title: str, xlabel: str, ylabel: str, xr: tuple[float, float],
         yr: tuple[float, float], body: str, cls: str) -> str:
    """A captioned figure: axes over ``xr`` and ``yr`` with grid, ticks and labels, ``body``
    (SVG drawn in plot coordinates: :func:`scale` of ``xr`` onto ``ML..ML + W`` and of ``yr``
    onto ``MT + H..MT``) inside; ``cls`` is the svg element's class."""
    fx = scale(xr[0], xr[1], ML, ML + W)
    fy = scale(yr[0], yr[1], MT + H, MT)
    grid = []
    for x in ticks(*xr):
        grid.append(f'<line x1="{fx(x):.1f}" y1="{MT}" x2="{fx(x):.1f}" y2="{MT + H}" '
                    f'class="grid"/><text x="{fx(x):.1f}" y="{MT + H + 14}" '
                    f'text-anchor="middle">{x:g}</text>')
    for y in ticks(*yr, n=5):
        grid.append(f'<line x1="{ML}" y1="{fy(y):.1f}" x2="{ML + W}" y2="{fy(y):.1f}" '
                    f'class="grid"/><text x="{ML - 6}" y="{fy(y) + 4:.1f}" '
                    f'text-anchor="end">{y:g}</text>')
    return (f'<figure><figcaption>{html.escape(title)}</figcaption>'
            f'<svg class="{cls}" width="{ML + W + MR}" height="{MT + H + MB}" '
            f'viewBox="0 0 {ML + W + MR} {MT + H + MB}" xmlns="http://www.w3.org/2000/svg">'
            f'{"".join(grid)}'
            f'<rect x="{ML}" y="{MT}" width="{W}" height="{H}" class="frame"/>{body}'
            f'<text x="{ML + W / 2}" y="{MT + H + 30}" text-anchor="middle">'
            f'{html.escape(xlabel)}</text>'
            f'<text x="14" y="{MT + H / 2}" transform="rotate(-90 14 {MT + H / 2})" '
            f'text-anchor="middle">{html.escape(ylabel)}</text></svg></figure>')


def path(points: Sequence[tuple[float, float]], fx: Callable[[float], float],
         fy: Callable[[float], float], cls: str) -> str:
    """An SVG path through ``points`` mapped by ``fx``/``fy`` ("" without points)."""
    if not points:
        return ""
    d = " ".join(f"{'M' if i == 0 else 'L'}{fx(x):.1f},{fy(y):.1f}"
                 for i, (x, y) in enumerate(points))
    return f'<path d="{d}" class="{cls}"/>'

