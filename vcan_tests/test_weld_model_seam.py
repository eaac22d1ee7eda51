"""The seam on the plate: centre line, width, nearest point, markers, linear sensor view."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from chcos.apps.weld.seam import Seam, SeamSpec
from chcos.errors import ConfigError

SEAM = Seam()


def runs(pixels: tuple[bool, ...]) -> list[tuple[int, int]]:
    """Dark runs as (first index, length)."""
    out: list[tuple[int, int]] = []
    start = None
    for i, dark in enumerate((*pixels, False)):
        if dark and start is None:
            start = i
        elif not dark and start is not None:
            out.append((start, i - start))
            start = None
    return out


def _segment_distance(
    p: tuple[float, float], a: tuple[float, float], b: tuple[float, float]
) -> float:
    ex, ey = b[0] - a[0], b[1] - a[1]
    f = ((p[0] - a[0]) * ex + (p[1] - a[1]) * ey) / (ex * ex + ey * ey)
    f = min(1.0, max(0.0, f))
    return math.dist(p, (a[0] + f * ex, a[1] + f * ey))


def across(seam: Seam, s: float, lateral: float = 0.0, height: float = 10.0) -> tuple[bool, ...]:
    """Pixels of a 64 x 0.5 mm sensor laid across the seam at (s, lateral)."""
    x, y = seam.centre(s)
    h = seam.heading(s)
    x -= lateral * math.sin(h)
    y += lateral * math.cos(h)
    return seam.sense(x, y, height, h + math.pi / 2).pixels


def test_centre_line_is_parametrised_by_arc_length() -> None:
    assert SEAM.centre(0.0) == pytest.approx(SEAM.spec.start)
    n = 600
    pts = [SEAM.centre(SEAM.length * k / n) for k in range(n + 1)]
    total = sum(math.dist(a, b) for a, b in itertools.pairwise(pts))
    assert total == pytest.approx(SEAM.length, rel=1e-4)
    # the default seam curves (an S): its middle lies well off the chord
    (x0, y0), (x1, y1) = SEAM.start, SEAM.end
    chord = math.dist(SEAM.start, SEAM.end)
    off_chord = max(abs((x1 - x0) * (ym - y0) - (y1 - y0) * (xm - x0)) / chord for xm, ym in pts)
    assert off_chord > 15.0


@given(st.floats(0.5, 299.5))
def test_heading_is_the_direction_of_the_curve(s: float) -> None:
    (x0, y0), (x1, y1) = SEAM.centre(s - 0.25), SEAM.centre(s + 0.25)
    direction = math.atan2(y1 - y0, x1 - x0)
    assert abs(math.remainder(direction - SEAM.heading(s), 2 * math.pi)) < 1e-3


def test_heading_follows_the_curvature_profile() -> None:
    # heading change = integral of the piecewise-linear curvature: 0.5 * 150 * (1/120) by s=150
    assert SEAM.heading(150.0) - SEAM.heading(0.0) == pytest.approx(0.625, abs=1e-6)
    assert SEAM.heading(300.0) - SEAM.heading(0.0) == pytest.approx(0.0, abs=1e-6)


def test_width_profile_and_overrides() -> None:
    assert SEAM.width(0.0) == pytest.approx(2.0)
    assert SEAM.width(100.0) == pytest.approx(2.2)
    assert SEAM.width(50.0) == pytest.approx(2.1)
    assert SEAM.width(-1.0) == 0.0 and SEAM.width(301.0) == 0.0
    wide = SEAM.with_width_override(150.0, 170.0, 4.0)
    assert wide.width(160.0) == 4.0 and wide.width(171.0) == pytest.approx(SEAM.width(171.0))
    assert SEAM.width(160.0) != 4.0  # the original is unchanged
    with pytest.raises(ConfigError, match="override"):
        SEAM.with_width_override(10.0, 5.0, 1.0)


@given(st.floats(0.0, 300.0), st.floats(-25.0, 25.0))
def test_nearest_recovers_arc_length_and_lateral_offset(s: float, lateral: float) -> None:
    x, y = SEAM.centre(s)
    h = SEAM.heading(s)
    p = SEAM.nearest(x - lateral * math.sin(h), y + lateral * math.cos(h))
    assert p.s == pytest.approx(s, abs=1e-3)
    assert p.lateral == pytest.approx(lateral, abs=1e-3)


@given(st.floats(450.0, 650.0), st.floats(-200.0, 200.0))
def test_nearest_agrees_with_brute_force(x: float, y: float) -> None:
    p = SEAM.nearest(x, y)
    brute = min(
        _segment_distance((x, y), SEAM.centre(k * 0.25), SEAM.centre(k * 0.25 + 0.25))
        for k in range(1200)
    )
    inside = 0.0 <= p.s <= SEAM.length
    # the brute force measures to 0.25 mm chords of the curve: their sagitta makes it differ from
    # the true distance by up to ~1e-4 mm at ~100 mm, so compare to 1 um
    if inside:
        assert abs(p.lateral) == pytest.approx(brute, abs=1e-3)
    else:  # on a tangent extension: never farther than the nearest point of the seam itself
        assert abs(p.lateral) <= brute + 1e-3


def test_nearest_beyond_the_ends_extends_the_tangents() -> None:
    x, y = SEAM.centre(0.0)
    p = SEAM.nearest(x, y - 20.0)  # the seam starts heading +y
    assert p.s == pytest.approx(-20.0, abs=1e-6)
    assert p.lateral == pytest.approx(0.0, abs=1e-6)


def test_sensor_sees_the_gap_centred_and_as_wide_as_it_is() -> None:
    pixels = across(SEAM, 100.0)
    ((first, length),) = runs(pixels)
    assert length == pytest.approx(2.2 / 0.5, abs=1)
    assert (first + length / 2) == pytest.approx(32, abs=1)


def test_sensor_offset_moves_the_dark_run() -> None:
    ((centred, _),) = runs(across(SEAM, 60.0))
    ((shifted, _),) = runs(across(SEAM, 60.0, lateral=3.0))
    # the sensor moved 3 mm to the left: the gap appears 6 pixels lower (pixels run leftwards)
    assert centred - shifted == pytest.approx(6, abs=1)


def test_start_and_end_markers_have_distinct_patterns() -> None:
    start = runs(across(SEAM, 0.0))
    end = runs(across(SEAM, SEAM.length + 3.0))
    middle = runs(across(SEAM, 150.0))
    assert len(start) == 3 and len(end) == 2 and len(middle) == 1
    assert max(n for _, n in end) >= 8  # end bars are 4 mm wide
    assert max(n for _, n in start) <= 5  # start bars are 2 mm (plus the gap in the middle)


def test_marker_flags() -> None:
    x, y = SEAM.centre(2.0)
    view = SEAM.sense(x, y, 10.0, SEAM.heading(2.0) + math.pi / 2)
    assert view.start_marker and not view.end_marker
    x, y = SEAM.centre(SEAM.length - 1.0)
    view = SEAM.sense(x, y, 10.0, 0.0)
    assert view.end_marker and not view.start_marker
    x, y = SEAM.centre(150.0)
    view = SEAM.sense(x, y, 10.0, 0.0)
    assert not view.start_marker and not view.end_marker


def test_probable_start_needs_a_search() -> None:
    px, py = SEAM.probable_start
    assert math.dist((px, py), SEAM.start) > 10.0
    h = SEAM.heading(0.0)
    # the sensor looks 5 mm ahead of the tip along the expected direction of the seam
    view = SEAM.sense(px + 5 * math.cos(h), py + 5 * math.sin(h), 10.0, h + math.pi / 2)
    assert not view.start_marker
    assert not any(view.pixels)


def test_range_is_limited_to_ten_centimetres() -> None:
    x, y = SEAM.centre(100.0)
    assert SEAM.sense(x, y, 100.0, 0.0).range_mm == 100.0
    far = SEAM.sense(x, y, 100.5, 0.0)
    assert far.range_mm is None and not any(far.pixels) and len(far.pixels) == 64
    assert SEAM.sense(x, y, -1.0, 0.0).range_mm is None


@pytest.mark.parametrize(
    ("spec", "fragment"),
    [
        (SeamSpec(length=0.0), "length"),
        (SeamSpec(step=0.0), "step"),
        (SeamSpec(width=((0.0, 2.0), (0.0, 3.0))), "increasing"),
        (SeamSpec(width=((0.0, 2.0), (10.0, -1.0))), "width"),
        (SeamSpec(curvature=()), "no knots"),
        (SeamSpec(marker_length=0.0), "marker_length"),
    ],
)
def test_bad_specs_are_config_errors(spec: SeamSpec, fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        Seam(spec)


def test_a_straight_seam() -> None:
    seam = Seam(SeamSpec(start=(0.0, 0.0), heading=0.0, length=100.0, curvature=((0.0, 0.0),)))
    assert seam.end == pytest.approx((100.0, 0.0))
    p = seam.nearest(40.0, 7.0)
    assert (p.s, p.lateral) == pytest.approx((40.0, 7.0))
