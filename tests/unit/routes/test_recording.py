"""Recording a driven track: thinning by distance, smoothing without cutting corners, the
summary; against hand computations and exact course geometry."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.localization.local_frame import LocalFrame
from appliance.routes.recording import (
    RecorderParams,
    RecordingError,
    RouteRecorder,
    smooth_along_arc,
)
from appliance.routes.route import Directions, GeodeticLine, LocalLine
from tests.unit.routes.courses import ArcCourse

FRAME = LocalFrame(52.2, 9.3, 80.0)


def test_thinning_keeps_a_point_every_half_metre() -> None:
    """Fixes every 0.125 m along a line: kept at 0, 0.5, 1.0, ... (exact in binary)."""
    recorder = RouteRecorder()
    kept = [x for k in range(81) if recorder.update(x := k * 0.125, 0.0, now_s=k * 0.1)]
    assert kept == [k * 0.5 for k in range(21)]


def test_standstill_jitter_leaves_one_point() -> None:
    rng = np.random.default_rng(3)
    recorder = RouteRecorder()
    recorder.update(0.0, 0.0, 0.0)
    for k in range(1, 600):  # a minute at 10 Hz, 5 cm of jitter
        east, north = rng.normal(0.0, 0.05, 2)
        recorder.update(float(east), float(north), k * 0.1)
    assert recorder.points_kept == 1
    assert recorder.update(0.6, 0.0, 60.0)  # then it drives off
    assert recorder.points_kept == 2


def test_smoothing_is_the_seven_point_savitzky_golay_on_even_spacing() -> None:
    """Alternating ±e across a line every 0.5 m, a window of 3 points each side: the
    quadratic SG weights (-2, 3, 6, 7, 6, 3, -2) / 21 leave ±5e/21 (hand sum: 2 + 3 - 6 +
    7 - 6 + 3 + 2 = 5), and the along-track position unchanged."""
    e = 0.04
    step_m = math.hypot(0.5, 2 * e)  # every segment is this long: even arc length spacing
    points = np.array([(0.5 * k, e * (-1) ** k) for k in range(40)])
    smoothed = smooth_along_arc(points, half_window_m=3.5 * step_m)
    interior = slice(4, 36)  # windows that do not reach an end (those fit a straight line)
    np.testing.assert_allclose(smoothed[interior, 0], points[interior, 0], atol=1e-12)
    np.testing.assert_allclose(smoothed[interior, 1], points[interior, 1] * 5 / 21, atol=1e-12)


def test_smoothing_keeps_a_parabola_exactly() -> None:
    """A quadratic fit reproduces any quadratic in arc length; y = x² / 30 is one only
    approximately in s, so use points evenly spaced in s along a straight line and a
    coordinate quadratic in s."""
    s = np.arange(0.0, 20.0, 0.5)
    points = np.column_stack((s * 0.6, s * 0.8))  # a straight line: s is exact
    np.testing.assert_allclose(smooth_along_arc(points, 1.5), points, atol=1e-12)


def _drive(
    course: ArcCourse,
    fix_step_m: float,
    noise_m: float = 0.0,
    seed: int = 0,
    params: RecorderParams | None = None,
) -> RouteRecorder:
    rng = np.random.default_rng(seed)
    recorder = RouteRecorder(params or RecorderParams())
    count = round(course.length_m / fix_step_m)
    for k in range(count + 1):
        east, north = course.at(k * course.length_m / count)
        east += rng.normal(0.0, noise_m) if noise_m else 0.0
        north += rng.normal(0.0, noise_m) if noise_m else 0.0
        recorder.update(east, north, now_s=k * 0.1)
    return recorder


@pytest.mark.parametrize("fix_step_m", [0.1, 0.2, 0.447])
def test_a_15_m_turn_is_not_cut(fix_step_m: float) -> None:
    """Straight, a 90° turn of 15 m radius, straight, driven at 1, 2 and 4.47 m/s with 10 Hz
    fixes: every point of the recorded route is within 2 cm of the course (exact distance),
    and the turn's radius is found."""
    course = ArcCourse(radius_m=15.0)
    route, summary = _drive(course, fix_step_m).finish("turn", FRAME, geodetic=False)
    points = route.points_enu_m(FRAME)
    worst_m = max(course.distance_m(x, y) for x, y in points)
    assert worst_m < 0.02
    assert summary.min_radius_m == pytest.approx(15.0, rel=0.05)


def test_smoothing_reduces_fix_noise_on_the_turn() -> None:
    """2 cm of fix noise, 2 m/s: the distance from the course shrinks by more than 30 %
    (the evenly spaced 7-point fit would give √(1/3); thinning leaves 4 to 7 points)."""
    course = ArcCourse(radius_m=15.0)
    unsmoothed = RecorderParams(smoothing_half_window_m=0.0)  # a window of one point
    raw = _drive(course, 0.2, noise_m=0.02, seed=5, params=unsmoothed)
    kept = raw.finish("raw", FRAME, geodetic=False)[0].points_enu_m(FRAME)
    route, _summary = _drive(course, 0.2, noise_m=0.02, seed=5).finish(
        "turn", FRAME, geodetic=False
    )
    smoothed = route.points_enu_m(FRAME)
    assert len(smoothed) == len(kept)

    def rms(points: np.ndarray) -> float:
        return math.sqrt(np.mean([course.distance_m(x, y) ** 2 for x, y in points[5:-5]]))

    assert rms(smoothed) < 0.7 * rms(kept)


def test_the_summary() -> None:
    """60 m straight at 1 m/s with 10 Hz fixes, then 10 s standing."""
    recorder = RouteRecorder()
    for k in range(601):
        recorder.update(k * 0.1, 0.0, now_s=100.0 + k * 0.1)
    for k in range(1, 101):
        recorder.update(60.0 + 0.01 * (-1) ** k, 0.0, now_s=160.0 + k * 0.1)
    recorder.update(math.nan, 0.0, now_s=171.0)
    route, summary = recorder.finish(
        "straight", FRAME, directions=Directions.FORWARD, speed_limit_mps=2.0, recorded="2024-05-01"
    )
    assert summary.fixes_received == 702 and summary.fixes_rejected == 1
    assert summary.points_kept == 121  # 0, 0.5, ..., 60.0 (0.1 * k is within 1e-12 of it)
    assert summary.points_dropped == 701 - 121
    assert summary.duration_s == pytest.approx(70.0)
    assert summary.length_m == pytest.approx(60.0, abs=1e-9)
    assert math.isinf(summary.min_radius_m) and not summary.truncated
    assert isinstance(route.line, GeodeticLine)  # written as lon/lat by default
    assert route.directions is Directions.FORWARD and route.speed_limit_mps == 2.0
    np.testing.assert_allclose(route.points_enu_m(FRAME)[-1], (60.0, 0.0), atol=1e-6)


def test_local_output_declares_the_frame() -> None:
    recorder = _drive(ArcCourse(radius_m=15.0), 0.2)
    route, _ = recorder.finish("local", FRAME, geodetic=False)
    assert isinstance(route.line, LocalLine) and route.line.origin == FRAME


def test_too_little_recorded_and_reset() -> None:
    recorder = RouteRecorder()
    recorder.update(0.0, 0.0, 0.0)
    recorder.update(0.3, 0.0, 1.0)
    with pytest.raises(RecordingError, match="recorded 1 point"):
        recorder.finish("short", FRAME)
    recorder.update(1.0, 0.0, 2.0)
    recorder.reset()
    assert recorder.points_kept == 0
    with pytest.raises(RecordingError, match="recorded 0 point"):
        recorder.finish("short", FRAME)


def test_the_point_cap_truncates_and_says_so() -> None:
    recorder = RouteRecorder(RecorderParams(max_points=10))
    for k in range(30):
        recorder.update(float(k), 0.0, float(k))
    route, summary = recorder.finish("capped", FRAME)
    assert summary.points_kept == route.point_count == 10 and summary.truncated
    assert summary.points_dropped == 20


def test_a_bad_name_is_a_value_error() -> None:
    recorder = _drive(ArcCourse(radius_m=15.0), 0.2)
    with pytest.raises(ValueError, match="not a route name"):
        recorder.finish("../escape", FRAME)


@given(
    st.lists(
        st.tuples(
            st.floats(-1e4, 1e4) | st.just(math.nan),
            st.floats(-1e4, 1e4),
            st.floats(0.0, 1e5),
        ),
        max_size=60,
    )
)
def test_any_fixes_give_a_route_or_a_recording_error(
    fixes: list[tuple[float, float, float]],
) -> None:
    recorder = RouteRecorder()
    for east, north, now_s in fixes:
        recorder.update(east, north, now_s)
    try:
        route, summary = recorder.finish("any", FRAME, geodetic=False)
    except RecordingError:
        assert recorder.points_kept < 2
        return
    assert summary.points_kept == route.point_count == recorder.points_kept
    assert summary.points_kept + summary.points_dropped + summary.fixes_rejected == len(fixes)
    assert np.all(np.isfinite(route.points_enu_m(FRAME)))


def test_the_ends_of_a_noisy_recording_are_no_tight_turn() -> None:
    """A gentle 38 m arc driven for 19 m at 1.6 m/s, 10 Hz fixes with 5 cm noise (the
    runtime test's drive): over 300 seeds the recording's tightest turn stays above the
    Husky's 3.66 m. With a quadratic extrapolated to the end points, 41 of 1,000 such
    recordings were refused for a turn the vehicle never made (down to 2.07 m)."""
    course = ArcCourse(radius_m=38.0, turn_deg=29.0, lead_m=0.0, tail_m=0.0)
    tightest = min(
        _drive(course, 0.16, noise_m=0.05, seed=seed)
        .finish("drive", FRAME, geodetic=False)[1]
        .min_radius_m
        for seed in range(300)
    )
    assert tightest > 3.66, tightest
