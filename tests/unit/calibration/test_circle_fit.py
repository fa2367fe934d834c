"""The circle fit: exact on exact circles and lines, near the truth on noisy ones."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from calibration.circle_fit import (
    arc_length_m,
    fit_circle,
    mean_tangent_offset_rad,
    signed_curvature_per_m,
    tangent_offsets_rad,
)


def arc(
    cx: float, cy: float, radius: float, start: float, span: float, n: int, direction: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points along a circle in travel order, and the heading of travel at each."""
    theta = start + direction * span * np.linspace(0.0, 1.0, n)
    x, y = cx + radius * np.cos(theta), cy + radius * np.sin(theta)
    return x, y, theta + direction * math.pi / 2


@given(
    cx=st.floats(-1e4, 1e4),
    cy=st.floats(-1e4, 1e4),
    radius=st.floats(0.5, 500.0),
    start=st.floats(-math.pi, math.pi),
    span=st.floats(0.2, 2 * math.pi),
    n=st.integers(5, 60),
    direction=st.sampled_from([-1.0, 1.0]),
)
def test_exact_on_exact_circles_at_any_place_size_and_turning_sense(
    cx: float, cy: float, radius: float, start: float, span: float, n: int, direction: float
) -> None:
    x, y, heading = arc(cx, cy, radius, start, span, n, direction)
    fit = fit_circle(x, y)
    assert fit.radius_m == pytest.approx(radius, rel=1e-6)
    assert fit.centre_m == pytest.approx((cx, cy), abs=1e-6 * max(radius, 1.0) + 1e-7)
    assert fit.rms_m < 1e-6 * radius
    # Left turns (counter-clockwise travel) are positive, driven either way round.
    assert signed_curvature_per_m(fit, x, y, heading) == pytest.approx(direction / radius, rel=1e-6)
    assert np.max(np.abs(tangent_offsets_rad(fit, x, y, heading))) < 1e-6
    # Reversing back along the arc (same headings, points the other way round) keeps the
    # sign, as the wheels keep their angle; facing the other way round turns it.
    rx, ry, rh = x[::-1], y[::-1], heading[::-1]
    assert signed_curvature_per_m(fit, rx, ry, rh) == pytest.approx(direction / radius, rel=1e-6)
    assert np.max(np.abs(tangent_offsets_rad(fit, rx, ry, rh))) < 1e-6
    turned = heading + math.pi
    assert signed_curvature_per_m(fit, x, y, turned) == pytest.approx(-direction / radius, rel=1e-6)
    assert arc_length_m(fit, x, y) == pytest.approx(radius * span, rel=1e-6)


@given(
    x0=st.floats(-1e4, 1e4),
    y0=st.floats(-1e4, 1e4),
    angle=st.floats(-math.pi, math.pi),
    length=st.floats(1.0, 100.0),
)
def test_a_straight_line_is_a_circle_of_zero_curvature(
    x0: float, y0: float, angle: float, length: float
) -> None:
    s = np.linspace(0.0, length, 30)
    x, y = x0 + s * math.cos(angle), y0 + s * math.sin(angle)
    fit = fit_circle(x, y)
    assert abs(fit.curvature_per_m) < 1e-9
    assert fit.rms_m < 1e-8
    assert arc_length_m(fit, x, y) == pytest.approx(length, rel=1e-6)
    heading = np.full_like(x, angle)
    assert np.max(np.abs(tangent_offsets_rad(fit, x, y, heading))) < 1e-9


def test_sideslip_is_the_angle_from_heading_to_tangent() -> None:
    x, y, heading = arc(10.0, -4.0, 6.0, 0.3, 1.5, 50, 1.0)
    beta = math.radians(4.0)
    offsets = tangent_offsets_rad(fit_circle(x, y), x, y, heading - beta)
    assert offsets == pytest.approx(np.full(50, beta), abs=1e-9)


def test_noisy_arc_recovers_the_radius_within_its_stated_sigma() -> None:
    rng = np.random.default_rng(7)
    misses = []
    for _ in range(40):
        x, y, _ = arc(0.0, 0.0, 8.0, 0.0, 1.2, 80, 1.0)
        fit = fit_circle(
            x + rng.normal(0, 0.02, 80), y + rng.normal(0, 0.02, 80), robust_scale_m=0.06
        )
        misses.append((abs(fit.curvature_per_m) - 1 / 8.0) / fit.curvature_sigma_per_m)
        assert fit.rms_m == pytest.approx(0.02, rel=0.3)
    # The sigma is honest: the misses scatter like a standard normal.
    assert 0.6 < float(np.std(misses)) < 1.5


def test_the_mean_sideslip_sigma_counts_the_circle_s_own_uncertainty() -> None:
    """Heading noise averages out over an arc; the circle's misplacement turns every
    tangent at once and does not, so a sigma from the scatter alone would be too small."""
    rng = np.random.default_rng(11)
    beta = math.radians(3.0)
    misses = []
    for _ in range(60):
        x, y, heading = arc(0.0, 0.0, 4.0, 0.0, 2.0, 120, 1.0)
        x, y = x + rng.normal(0, 0.02, 120), y + rng.normal(0, 0.02, 120)
        noisy_heading = heading - beta + rng.normal(0, math.radians(0.2), 120)
        fit = fit_circle(x, y, robust_scale_m=0.06)
        mean, sigma = mean_tangent_offset_rad(fit, x, y, noisy_heading)
        misses.append((mean - beta) / sigma)
    assert abs(float(np.mean(misses))) < 0.5
    assert 0.7 < float(np.std(misses)) < 1.4


def test_a_stray_point_pulls_the_robust_fit_little() -> None:
    x, y, _ = arc(0.0, 0.0, 5.0, 0.0, 1.5, 60, 1.0)
    y = y.copy()
    y[30] += 0.5
    fit = fit_circle(x, y, robust_scale_m=0.02)
    assert fit.radius_m == pytest.approx(5.0, rel=2e-3)


@pytest.mark.parametrize(
    ("x", "y", "message"),
    [
        ([0.0, 1.0], [0.0, 1.0], "at least 3"),
        ([0.0, 1.0, math.nan], [0.0, 1.0, 2.0], "non-finite"),
        ([0.0, 1.0, 2.0], [0.0, 1.0, 2.0, 3.0], "differ in length"),
        ([[0.0, 1.0, 2.0]], [[0.0, 1.0, 2.0]], "one-dimensional"),
        ([1.0, 1.0, 1.0], [2.0, 2.0, 2.0], "all the same"),
        (["a", "b", "c"], [0.0, 1.0, 2.0], "not an array of numbers"),
    ],
)
def test_garbage_raises_value_error(x: object, y: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        fit_circle(x, y)  # type: ignore[arg-type]
