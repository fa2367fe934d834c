"""The path's look-ups on Python floats against the plain numpy computation they replaced.

The oracles below are the array forms (one numpy expression per step, over the whole
path); the module answers the same questions from lists made once per path. Random
paths include repeated vertices, tiny segments and hairpins, and the questions reach
past both ends.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from appliance.guidance.path_geometry import (
    PathProjection,
    Polyline,
    goal_shift_m,
    path_curvature_per_m,
    point_at_arc_length,
    project_onto_path,
    signed_cross_track_m,
)

FloatArray = np.ndarray

coordinate = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)


@st.composite
def paths(draw: st.DrawFn) -> Polyline:
    """Random polylines with some length; some vertices repeated."""
    count = draw(st.integers(2, 14))
    points = [(draw(coordinate), draw(coordinate))]
    for _ in range(count - 1):
        if draw(st.integers(0, 5)) == 0:
            points.append(points[-1])  # a repeated vertex: a zero-length segment
        else:
            points.append((draw(coordinate), draw(coordinate)))
    array = np.array(points)
    assume(float(np.sum(np.hypot(*np.diff(array, axis=0).T))) > 1e-3)
    return Polyline.from_points(array)


def _oracle_direction(path: Polyline, segment_index: int) -> tuple[float, float]:
    i = segment_index
    if not path.arc_m[i + 1] > path.arc_m[i]:
        lengths = np.diff(path.arc_m)
        ahead = np.flatnonzero(lengths[i:])
        i = i + int(ahead[0]) if ahead.size else int(np.flatnonzero(lengths[:i])[-1])
    length = float(path.arc_m[i + 1] - path.arc_m[i])
    delta = path.points_m[i + 1] - path.points_m[i]
    return float(delta[0]) / length, float(delta[1]) / length


def _oracle_project(
    path: Polyline, x_m: float, y_m: float, first: int, last: int
) -> PathProjection:
    starts = path.points_m[first : last + 1]
    deltas = path.points_m[first + 1 : last + 2] - starts
    lengths_sq = np.square(path.arc_m[first + 1 : last + 2] - path.arc_m[first : last + 1])
    to_point = np.array([x_m, y_m]) - starts
    dots = to_point[:, 0] * deltas[:, 0] + to_point[:, 1] * deltas[:, 1]
    fractions = np.clip(
        np.divide(dots, lengths_sq, out=np.zeros_like(dots), where=lengths_sq > 0), 0.0, 1.0
    )
    off = to_point - fractions[:, None] * deltas
    best = int(np.argmin(off[:, 0] ** 2 + off[:, 1] ** 2))
    return PathProjection(first + best, float(fractions[best]))


def _oracle_point_at(path: Polyline, target: float) -> tuple[tuple[float, float], bool]:
    total = float(path.arc_m[-1])
    if target > total + 1e-9:
        ux, uy = _oracle_direction(path, path.last_segment)
        end = path.points_m[-1]
        return (float(end[0]) + (target - total) * ux, float(end[1]) + (target - total) * uy), True
    if target < -1e-9:
        ux, uy = _oracle_direction(path, 0)
        start = path.points_m[0]
        return (float(start[0]) + target * ux, float(start[1]) + target * uy), True
    i = max(0, min(path.last_segment, int(np.searchsorted(path.arc_m, target, "right")) - 1))
    a0, a1 = float(path.arc_m[i]), float(path.arc_m[i + 1])
    f = min(1.0, max(0.0, 1.0 if a1 == a0 else (target - a0) / (a1 - a0)))
    p0, p1 = path.points_m[i], path.points_m[i + 1]
    return (float(p0[0] + f * (p1[0] - p0[0])), float(p0[1] + f * (p1[1] - p0[1]))), False


def _oracle_goal_shift(path: Polyline, from_arc_m: float, lookahead_m: float, h: float) -> float:
    if lookahead_m <= 0.0:
        return 0.0
    samples = max(4, math.ceil(lookahead_m / 0.25))
    u = np.linspace(0.0, lookahead_m, samples + 1)
    at = from_arc_m + u
    arc, xs, ys = path.arc_m, path.points_m[:, 0], path.points_m[:, 1]
    ax, ay = np.interp(at - h, arc, xs), np.interp(at - h, arc, ys)
    bx, by = np.interp(at, arc, xs), np.interp(at, arc, ys)
    cx, cy = np.interp(at + h, arc, xs), np.interp(at + h, arc, ys)
    cross = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    sides = np.hypot(bx - ax, by - ay) * np.hypot(cx - bx, cy - by) * np.hypot(cx - ax, cy - ay)
    kappa = np.divide(2.0 * cross, sides, out=np.zeros_like(cross), where=sides > 1e-12)
    integrand = (lookahead_m - u) * kappa
    offset_m = float(np.sum(0.5 * (integrand[1:] + integrand[:-1]) * np.diff(u)))
    return 0.5 * lookahead_m**2 * float(kappa[0]) - offset_m


def _close(a: float, b: float, scale: float = 1.0) -> bool:
    return math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-9 * scale)


@settings(max_examples=300, deadline=None)
@given(paths(), st.data())
def test_direction_is_the_segment_or_its_nearest_with_length(
    path: Polyline, data: st.DataObject
) -> None:
    i = data.draw(st.integers(0, path.last_segment))
    assert path.direction(i) == pytest.approx(_oracle_direction(path, i), rel=1e-12, abs=1e-12)


@settings(max_examples=300, deadline=None)
@given(paths(), coordinate, coordinate, st.data())
def test_projection_is_the_plain_nearest_point(
    path: Polyline, x: float, y: float, data: st.DataObject
) -> None:
    first = data.draw(st.integers(0, path.last_segment))
    last = data.draw(st.integers(first, path.last_segment))
    fast = project_onto_path(path, x, y, first, last)
    plain = _oracle_project(path, x, y, first, last)
    fast_point, plain_point = path.point(fast), path.point(plain)
    # the same point; the segment may differ only where two are equally near (a vertex)
    assert math.dist(fast_point, plain_point) <= 1e-9
    assert math.dist((x, y), fast_point) == pytest.approx(math.dist((x, y), plain_point), abs=1e-9)


@settings(max_examples=300, deadline=None)
@given(paths(), st.data(), st.floats(-80.0, 80.0))
def test_point_along_the_path_is_the_plain_one(
    path: Polyline, data: st.DataObject, ahead_m: float
) -> None:
    projection = PathProjection(
        data.draw(st.integers(0, path.last_segment)), data.draw(st.floats(0.0, 1.0))
    )
    (x, y), beyond = point_at_arc_length(path, projection, ahead_m)
    (ox, oy), o_beyond = _oracle_point_at(path, path.arc_at(projection) + ahead_m)
    assert beyond == o_beyond
    assert _close(x, ox, 100.0) and _close(y, oy, 100.0)


@settings(max_examples=300, deadline=None)
@given(paths(), st.floats(-10.0, 250.0), st.floats(0.0, 15.0), st.floats(0.1, 4.0))
def test_goal_shift_is_the_plain_quadrature(
    path: Polyline, from_arc_m: float, lookahead_m: float, half_window_m: float
) -> None:
    fast = goal_shift_m(path, from_arc_m, lookahead_m, half_window_m)
    plain = _oracle_goal_shift(path, from_arc_m, lookahead_m, half_window_m)
    # the curvature of a near-degenerate triangle is large and ill-conditioned: compare
    # at the size of the terms that were summed
    scale = 0.5 * lookahead_m**2 * max(1.0, abs(plain), abs(fast))
    assert _close(fast, plain, scale) or abs(fast - plain) <= 1e-6 * scale


@settings(max_examples=200, deadline=None)
@given(paths(), st.data(), coordinate, coordinate)
def test_cross_track_and_curvature_read_the_same_points(
    path: Polyline, data: st.DataObject, x: float, y: float
) -> None:
    projection = PathProjection(
        data.draw(st.integers(0, path.last_segment)), data.draw(st.floats(0.0, 1.0))
    )
    ux, uy = _oracle_direction(path, projection.segment_index)
    px, py = path.point(projection)
    assert _close(signed_cross_track_m(path, projection, x, y), ux * (y - py) - uy * (x - px), 100)
    here = path.arc_at(projection)
    (ax, ay), _ = _oracle_point_at(path, here - 2.0)
    (cx, cy), _ = _oracle_point_at(path, here + 2.0)
    cross = (px - ax) * (cy - ay) - (py - ay) * (cx - ax)
    sides = math.dist((ax, ay), (px, py)) * math.dist((px, py), (cx, cy))
    sides *= math.dist((ax, ay), (cx, cy))
    plain = 0.0 if sides <= 0.0 else 2.0 * cross / sides
    fast = path_curvature_per_m(path, projection, 2.0)
    assert math.isclose(fast, plain, rel_tol=1e-6, abs_tol=1e-9)


@given(paths(), st.floats(-20.0, 300.0))
def test_projection_at_an_arc_length_is_that_point(path: Polyline, arc_m: float) -> None:
    projection = path.projection_at_arc(arc_m)
    path.check(projection)
    clamped = min(max(arc_m, 0.0), float(path.arc_m[-1]))
    assert path.arc_at(projection) == pytest.approx(clamped, abs=1e-9)
    (x, y), _ = _oracle_point_at(path, clamped)
    assert math.dist(path.point(projection), (x, y)) <= 1e-9 * max(1.0, abs(x) + abs(y))
