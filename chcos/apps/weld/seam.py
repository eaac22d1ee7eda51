"""seam - the gap to weld: a curving butt gap on a flat plate, its markers and what sensors see.

A seam lies on a flat plate at height ``plate_z`` (mm, base frame of the arm). Its centre line is a
smooth curve parametrised by arc length ``s`` (mm): the curvature (1/mm) is piecewise linear in
``s`` (a clothoid spline, so heading and curvature are continuous), integrated from a start point
and heading. The gap width (mm) is piecewise linear in ``s`` (nominal about 2 mm) and may carry
local overrides (a too-wide or too-narrow stretch, see :mod:`chcos.apps.weld.faults`).

Before ``s = 0`` and after ``s = length`` the centre line continues as straight tangent lines
(there is no gap there). A start marker is centred on ``s = 0`` and an end marker on
``s = length``: each is a set of dark bands parallel to the seam, ``marker_length`` mm long, so a
linear light sensor laid across the seam sees a distinct binary pattern there (task B5.s):

* start marker: three bars at lateral offsets -7..-5, -1..1, 5..7 mm (the gap adds to the middle);
* end marker: two wide bars at lateral offsets -7..-3 and 3..7 mm.

A linear light sensor (task A7.s) is a row of N binary pixels: ``True`` means dark (gap or marker
bar), ``False`` bright plate. It reports the range (mm) to the surface, 0..100 mm, and nothing
(all ``False``, range ``None``) beyond that. The task C2 gets a *probable* start position, offset
from the true start, from which it must spiral-search for the start marker.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from chcos.errors import ConfigError

START_MARKER_BANDS: tuple[tuple[float, float], ...] = ((-7.0, -5.0), (-1.0, 1.0), (5.0, 7.0))
END_MARKER_BANDS: tuple[tuple[float, float], ...] = ((-7.0, -3.0), (3.0, 7.0))
MARKER_HALF_WIDTH = 8.0
"""Lateral half width (mm) of a marker plate: a marker detector sees it within this offset."""
SENSOR_RANGE_MM = 100.0
"""The linear sensor's range limit (mm): 0-10 cm as in thesis section 5.1."""


def _knots(name: str, knots: Sequence[tuple[float, float]]) -> tuple[tuple[float, float], ...]:
    """``knots`` checked: at least one, ``s`` (mm) strictly increasing and finite values."""
    out = tuple((float(s), float(v)) for s, v in knots)
    if not out:
        raise ConfigError(f"seam {name}: no knots, expected at least one (s_mm, value) pair")
    for i, (s, v) in enumerate(out):
        if not (math.isfinite(s) and math.isfinite(v)):
            raise ConfigError(f"seam {name}[{i}] = ({s}, {v}): expected finite numbers")
        if i and s <= out[i - 1][0]:
            raise ConfigError(
                f"seam {name}[{i}]: s={s} mm after s={out[i - 1][0]} mm, expected increasing s"
            )
    return out


def _interp(knots: Sequence[tuple[float, float]], s: float) -> float:
    """Piecewise-linear interpolation in ``knots``, held constant outside them."""
    if s <= knots[0][0]:
        return knots[0][1]
    if s >= knots[-1][0]:
        return knots[-1][1]
    lo, hi = 0, len(knots) - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if knots[mid][0] <= s:
            lo = mid
        else:
            hi = mid
    (s0, v0), (s1, v1) = knots[lo], knots[hi]
    return v0 + (v1 - v0) * (s - s0) / (s1 - s0)


@dataclass(frozen=True)
class SeamSpec:
    """The description of a seam. Lengths in mm, angles in rad, curvature in 1/mm.

    ``start`` is the true start of the gap (x, y), ``heading`` the initial direction of travel,
    ``curvature`` and ``width`` knots ``(s, value)``, ``probable_start_offset`` the (dx, dy) from
    the true start to the position the cell is told to start searching at.
    """

    start: tuple[float, float] = (550.0, -150.0)
    heading: float = math.pi / 2.0
    length: float = 300.0
    curvature: tuple[tuple[float, float], ...] = (
        (0.0, 0.0),
        (75.0, 1.0 / 120.0),
        (150.0, 0.0),
        (225.0, -1.0 / 120.0),
        (300.0, 0.0),
    )
    width: tuple[tuple[float, float], ...] = ((0.0, 2.0), (100.0, 2.2), (200.0, 1.85), (300.0, 2.0))
    plate_z: float = 0.0
    probable_start_offset: tuple[float, float] = (-8.0, -14.0)
    marker_length: float = 12.0
    step: float = 0.5


@dataclass(frozen=True)
class SeamPoint:
    """The seam point nearest to a query: arc length ``s`` (mm, may be < 0 or > length on the
    tangent extensions), its centre ``x``/``y`` (mm), ``heading`` (rad) and the query's signed
    ``lateral`` offset (mm, positive to the left of the direction of travel)."""

    s: float
    x: float
    y: float
    heading: float
    lateral: float


class LinearView:
    """What the linear light sensor sees: ``pixels`` (``True`` = dark), ``range_mm`` to the surface
    (``None`` when beyond 0..100 mm, then all pixels are ``False``), and the start/end marker flags
    of the marker detector at the sensor centre.

    ``pixels`` is given as the tuple or as a function that computes it: the row is the model's
    costliest reading and most views are never asked for it (the raw-CAN markers and the range
    need only the centre), so it is computed on the first read and kept. The function must be
    pure (it sees the pose the view was taken at), so the answer does not depend on when it is
    asked. Immutable; equal when every field and the pixels are."""

    __slots__ = ("_pixels", "_sample", "end_marker", "range_mm", "start_marker")

    def __init__(self, pixels: tuple[bool, ...] | Callable[[], tuple[bool, ...]],
                 range_mm: float | None, start_marker: bool, end_marker: bool) -> None:
        self._pixels: tuple[bool, ...] | None = pixels if isinstance(pixels, tuple) else None
        self._sample: Callable[[], tuple[bool, ...]] | None = (
            None if isinstance(pixels, tuple) else pixels)
        self.range_mm = range_mm
        self.start_marker = start_marker
        self.end_marker = end_marker

    @property
    def pixels(self) -> tuple[bool, ...]:
        """The row of pixels, ``True`` = dark (computed on the first read)."""
        row = self._pixels
        if row is None:
            assert self._sample is not None
            row = self._pixels = self._sample()
            self._sample = None
        return row

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, LinearView):
            return NotImplemented
        return (self.range_mm == other.range_mm and self.start_marker == other.start_marker
                and self.end_marker == other.end_marker and self.pixels == other.pixels)

    def __hash__(self) -> int:
        return hash((self.range_mm, self.start_marker, self.end_marker, self.pixels))

    def __repr__(self) -> str:
        row = "".join("1" if p else "0" for p in self.pixels)
        return (f"LinearView(pixels={row}, range_mm={self.range_mm!r}, "
                f"start_marker={self.start_marker!r}, end_marker={self.end_marker!r})")


@dataclass(frozen=True)
class WidthOverride:
    """A stretch ``s_from``..``s_to`` (mm) of the seam where the gap is ``width`` mm instead."""

    s_from: float
    s_to: float
    width: float


@dataclass(frozen=True)
class _Geometry:
    ds: float
    xs: tuple[float, ...]
    ys: tuple[float, ...]
    hs: tuple[float, ...]


def _integrate(spec: SeamSpec) -> _Geometry:
    """Sample the centre line every ~``spec.step`` mm (midpoint rule on the heading)."""
    n = max(1, math.ceil(spec.length / spec.step))
    ds = spec.length / n
    xs, ys, hs = [spec.start[0]], [spec.start[1]], [spec.heading]
    h = spec.heading
    for k in range(n):
        s0 = k * ds
        k0 = _interp(spec.curvature, s0)
        km = _interp(spec.curvature, s0 + ds / 2.0)
        k1 = _interp(spec.curvature, s0 + ds)
        h_mid = h + ds / 2.0 * (k0 + km) / 2.0
        h_next = h + ds * (k0 + 4.0 * km + k1) / 6.0
        xs.append(xs[-1] + ds * math.cos(h_mid))
        ys.append(ys[-1] + ds * math.sin(h_mid))
        hs.append(h_next)
        h = h_next
    return _Geometry(ds, tuple(xs), tuple(ys), tuple(hs))


def _half_gap(spec: SeamSpec, overrides: Sequence[WidthOverride]) -> float:
    """Half the widest gap anywhere on the seam (mm): the width is piecewise linear between its
    knots, so its largest value is at a knot or in an override."""
    return max([w for _s, w in spec.width] + [o.width for o in overrides]) / 2.0


class Seam:
    """A seam on a flat plate (see the module docstring). Immutable: overrides make a new seam.

    Raises :class:`chcos.errors.ConfigError` for an invalid :class:`SeamSpec` (non-positive length,
    width or step, unordered knots).
    """

    def __init__(
        self, spec: SeamSpec | None = None, overrides: Sequence[WidthOverride] = ()
    ) -> None:
        spec = spec if spec is not None else SeamSpec()
        if not (math.isfinite(spec.length) and spec.length > 0.0):
            raise ConfigError(f"seam length={spec.length!r} mm, expected a positive length")
        if not spec.step > 0.0:
            raise ConfigError(f"seam step={spec.step!r} mm, expected a positive sample step")
        if not spec.marker_length > 0.0:
            raise ConfigError(f"seam marker_length={spec.marker_length!r} mm, expected > 0")
        _knots("curvature", spec.curvature)
        for i, (s, w) in enumerate(_knots("width", spec.width)):
            if w <= 0.0:
                raise ConfigError(f"seam width[{i}] at s={s} mm is {w} mm, expected > 0")
        for o in overrides:
            if not (o.s_from < o.s_to and o.width >= 0.0):
                raise ConfigError(f"seam width override {o!r}: expected s_from < s_to, width >= 0")
        self.spec = spec
        self.length = spec.length
        self.plate_z = spec.plate_z
        self.overrides: tuple[WidthOverride, ...] = tuple(overrides)
        self._g = _integrate(spec)
        self._half_gap = _half_gap(spec, self.overrides)

    def with_width_override(self, s_from: float, s_to: float, width: float) -> Seam:
        """A copy of this seam whose gap is ``width`` mm between ``s_from`` and ``s_to`` (mm)."""
        new = Seam.__new__(Seam)
        new.spec = self.spec
        new.length = self.length
        new.plate_z = self.plate_z
        override = WidthOverride(float(s_from), float(s_to), float(width))
        if not (override.s_from < override.s_to and override.width >= 0.0):
            raise ConfigError(
                f"seam width override {override!r}: expected s_from < s_to, width >= 0"
            )
        new.overrides = (*self.overrides, override)
        new._g = self._g
        new._half_gap = _half_gap(new.spec, new.overrides)
        return new

    # --- the centre line -------------------------------------------------------------------

    def _frame(self, s: float) -> tuple[float, float, float]:
        """Centre x, y (mm) and heading (rad) at arc length ``s`` (mm), tangents beyond the ends."""
        g = self._g
        n = len(g.xs) - 1
        if s <= 0.0:
            h = g.hs[0]
            return g.xs[0] + s * math.cos(h), g.ys[0] + s * math.sin(h), h
        if s >= self.length:
            h = g.hs[n]
            e = s - self.length
            return g.xs[n] + e * math.cos(h), g.ys[n] + e * math.sin(h), h
        k = min(int(s / g.ds), n - 1)
        f = s / g.ds - k
        return (
            g.xs[k] + f * (g.xs[k + 1] - g.xs[k]),
            g.ys[k] + f * (g.ys[k + 1] - g.ys[k]),
            g.hs[k] + f * (g.hs[k + 1] - g.hs[k]),
        )

    def centre(self, s: float) -> tuple[float, float]:
        """The gap centre (x, y) in mm at arc length ``s`` (mm); on the tangents beyond the ends."""
        x, y, _ = self._frame(s)
        return x, y

    def heading(self, s: float) -> float:
        """The direction of travel (rad) at arc length ``s`` (mm)."""
        return self._frame(s)[2]

    def width(self, s: float) -> float:
        """The gap width (mm) at arc length ``s`` (mm); 0 outside ``0..length`` (no gap there)."""
        if not 0.0 <= s <= self.length:
            return 0.0
        for o in reversed(self.overrides):
            if o.s_from <= s <= o.s_to:
                return o.width
        return _interp(self.spec.width, s)

    @property
    def start(self) -> tuple[float, float]:
        """The true start of the gap (x, y) in mm."""
        return self.centre(0.0)

    @property
    def end(self) -> tuple[float, float]:
        """The end of the gap (x, y) in mm."""
        return self.centre(self.length)

    @property
    def probable_start(self) -> tuple[float, float]:
        """Where the cell is told the gap probably starts (x, y) in mm: the true start plus
        ``probable_start_offset``; a spiral search from here finds the start marker."""
        sx, sy = self.start
        return sx + self.spec.probable_start_offset[0], sy + self.spec.probable_start_offset[1]

    def project(self, x: float, y: float, s_guess: float) -> SeamPoint:
        """The seam point nearest (x, y) (mm) found by Newton steps from ``s_guess`` (mm).

        Cheap and exact near the seam (lateral offset much smaller than the radius of curvature);
        use :meth:`nearest` when no good guess is known or the point may be far.
        """
        s, cx, cy, h, lateral = self._foot(x, y, s_guess)
        return SeamPoint(s, cx, cy, h, lateral)

    def _foot(self, x: float, y: float, s: float) -> tuple[float, float, float, float, float]:
        """:meth:`project`'s Newton steps from ``s``: (s, centre x, centre y, heading, lateral)
        of the foot point, without building a :class:`SeamPoint` (the line sensor asks this for
        its pixels)."""
        frame, curvature, length = self._frame, self.spec.curvature, self.length
        cos, sin = math.cos, math.sin
        for _ in range(8):
            cx, cy, h = frame(s)
            ch, sh = cos(h), sin(h)
            along = (x - cx) * ch + (y - cy) * sh
            lateral = -(x - cx) * sh + (y - cy) * ch
            kappa = _interp(curvature, s) if 0.0 < s < length else 0.0
            step = along / max(0.1, 1.0 - kappa * lateral)
            s += step
            if abs(step) < 1e-7:
                break
        cx, cy, h = frame(s)
        lateral = -(x - cx) * sin(h) + (y - cy) * cos(h)
        return s, cx, cy, h, lateral

    def nearest(self, x: float, y: float) -> SeamPoint:
        """The seam point nearest (x, y) (mm), over the whole seam and its tangent extensions.

        A coarse scan of the samples, point-to-segment distances around the best one, then
        Newton steps on the smooth curve (:meth:`project`).
        """
        g = self._g
        last = len(g.xs) - 1
        stride = 8
        best_k, best_d = 0, math.inf
        for k in (*range(0, last, stride), last):
            d = (g.xs[k] - x) ** 2 + (g.ys[k] - y) ** 2
            if d < best_d:
                best_k, best_d = k, d
        best_s, best_d = 0.0, math.inf
        for k in range(max(0, best_k - 2 * stride), min(last, best_k + 2 * stride)):
            ax, ay = g.xs[k], g.ys[k]
            ex, ey = g.xs[k + 1] - ax, g.ys[k + 1] - ay
            f = ((x - ax) * ex + (y - ay) * ey) / (ex * ex + ey * ey)
            if (k > 0 or f > 0.0) and (k < last - 1 or f < 1.0):
                f = min(1.0, max(0.0, f))
            d = (ax + f * ex - x) ** 2 + (ay + f * ey - y) ** 2
            if d < best_d:
                best_s, best_d = (k + f) * g.ds, d
        return self.project(x, y, best_s)

    # --- what sensors see --------------------------------------------------------------------

    def dark(self, s: float, lateral: float) -> bool:
        """True if the plate is dark at seam coordinates (``s``, ``lateral``) in mm: inside the gap
        or on a bar of the start or end marker."""
        half_marker = self.spec.marker_length / 2.0
        if abs(lateral) <= self.width(s) / 2.0:
            return True
        if abs(s) <= half_marker and any(lo <= lateral <= hi for lo, hi in START_MARKER_BANDS):
            return True
        return abs(s - self.length) <= half_marker and any(
            lo <= lateral <= hi for lo, hi in END_MARKER_BANDS
        )

    def markers(self, point: SeamPoint) -> tuple[bool, bool]:
        """(start, end) marker detector flags for a sensor over ``point``."""
        half = self.spec.marker_length / 2.0
        near = abs(point.lateral) <= MARKER_HALF_WIDTH
        return near and abs(point.s) <= half, near and abs(point.s - self.length) <= half

    def sense(
        self,
        x: float,
        y: float,
        height: float,
        axis: float,
        pixels: int = 64,
        pitch: float = 0.5,
        s_guess: float | None = None,
    ) -> LinearView:
        """What a linear sensor centred at (``x``, ``y``) mm, ``height`` mm above the plate, with
        ``pixels`` pixels ``pitch`` mm apart laid along direction ``axis`` (rad, pixel index
        increasing) sees. ``s_guess`` (mm) speeds up the search when the seam position is known.
        """
        if not 0.0 <= height <= SENSOR_RANGE_MM:
            return LinearView((False,) * pixels, None, False, False)
        centre = self.nearest(x, y) if s_guess is None else self.project(x, y, s_guess)
        if abs(centre.lateral) > 100.0 and s_guess is not None:
            centre = self.nearest(x, y)
        start, end = self.markers(centre)
        row = functools.partial(self._row, x, y, axis, centre, pixels, pitch)
        return LinearView(row, height, start, end)

    def _dark_reach(self, centre: SeamPoint, pixels: int, pitch: float) -> float:
        """How far (mm) from the centre line anything dark can be under a sensor row over
        ``centre``: the widest half gap, or the marker bars' outer edge where a marker may lie
        under the row (its ends within the row's half length, with room for the curvature)."""
        half_row = (pixels - 1) / 2.0 * abs(pitch)
        near = self.spec.marker_length / 2.0 + 2.0 * half_row + 10.0
        if (abs(centre.lateral) > 40.0 or abs(centre.s) <= near
                or abs(centre.s - self.length) <= near):
            return max(self._half_gap, *(max(abs(lo), abs(hi)) for lo, hi in
                                         (*START_MARKER_BANDS, *END_MARKER_BANDS)))
        return self._half_gap

    def _row(self, x: float, y: float, axis: float, centre: SeamPoint, pixels: int,
             pitch: float) -> tuple[bool, ...]:
        """The pixels of :meth:`sense` (see there), each pixel's seam coordinates found as
        :meth:`project` finds them from the guess the centre gives. A pixel whose foot lies
        farther from the centre line than anything dark can (:meth:`_dark_reach`) is bright,
        and so are the next ones as long as that distance, less their distance along the row,
        stays beyond it (a point's distance to the curve changes no faster than the point
        moves): only the pixels near the gap and the marker bars are projected."""
        ca, sa = math.cos(axis), math.sin(axis)
        ct, st = math.cos(centre.heading), math.sin(centre.heading)
        cs = centre.s
        reach = self._dark_reach(centre, pixels, pitch) + 1e-9
        step_mm = abs(pitch)
        foot, dark = self._foot, self.dark
        out = [False] * pixels
        half = (pixels - 1) / 2.0
        i = 0
        while i < pixels:
            off = (i - half) * pitch
            px, py = x + off * ca, y + off * sa
            guess = cs + (px - x) * ct + (py - y) * st
            s, _cx, _cy, _h, lateral = foot(px, py, guess)
            if dark(s, lateral):
                out[i] = True
            clear = abs(lateral) - reach    # mm of row beyond pixel i that is surely bright
            i += 1 if clear <= 0.0 or step_mm == 0.0 else max(1, math.ceil(clear / step_mm))
        return tuple(out)
