"""The path the tracker follows: a polyline with its arc length, and what is read off it.

Every control cycle the tracker asks a few questions of the path near the vehicle: the
point some metres ahead along it, its direction there, the anchor's nearest point within
a few segments, the curvature over a look-ahead. Each is a handful of points, so each is
answered in plain Python floats from lists made once per path: numpy's cost per call on
an array of ten elements is several times the arithmetic itself. The path may then be
the whole route (thousands of points, built once per route and travel direction): the
look-ups search the arc-length table (``bisect``), and only the projection walks the few
segments it is given.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

# Rounding left over from walking the segments: not "past the end".
_ARC_EPSILON_M = 1e-9
# goal_shift_m samples the curvature this often along the look-ahead.
_GOAL_SHIFT_SAMPLE_M = 0.25


class PathProjection(NamedTuple):
    """A point on a polyline: on segment ``segment_index`` (vertex i to i+1), ``fraction``
    of the way along it. (A named tuple: a few are made every cycle.)"""

    segment_index: int
    fraction: float


@dataclass(frozen=True)
class _Tables:
    """The path as Python floats: coordinates, arc lengths, each segment's unit direction."""

    x: list[float]
    y: list[float]
    arc: list[float]
    unit: list[tuple[float, float]]


@dataclass(frozen=True, eq=False)
class Polyline:
    """A path in travel order with its cumulative arc length, built once per path.

    The tracker runs at the control rate while the path changes only with the route (or
    its direction), so the O(N) work (checks, arc lengths, segment directions) is done
    here once and each cycle only searches the table. Zero-length segments (repeated
    vertices) are allowed; the points are a read-only copy.
    """

    points_m: FloatArray
    arc_m: FloatArray  # arc_m[i]: path length from vertex 0 to vertex i

    @classmethod
    def from_points(cls, points_m: FloatArray) -> Polyline:
        """An (N, 2) finite array, N >= 2, of non-zero length; ValueError otherwise."""
        points = np.array(points_m, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2 or points.shape[0] < 2:
            raise ValueError(f"path must be an (N, 2) array with N >= 2 (got {points.shape})")
        if not np.all(np.isfinite(points)):
            raise ValueError("path holds non-finite coordinates")
        lengths = np.hypot(*np.diff(points, axis=0).T)
        arc = np.concatenate([[0.0], np.cumsum(lengths)])
        if not arc[-1] > 0.0:
            raise ValueError("path has no length (all vertices coincide)")
        points.flags.writeable = False
        arc.flags.writeable = False
        return cls(points, arc)

    @cached_property
    def _tables(self) -> _Tables:
        """Made at the first look-up, once (the arrays are read-only)."""
        x: list[float] = self.points_m[:, 0].tolist()
        y: list[float] = self.points_m[:, 1].tolist()
        arc: list[float] = self.arc_m.tolist()
        own: list[tuple[float, float] | None] = []
        for i in range(len(arc) - 1):
            length = arc[i + 1] - arc[i]
            own.append(
                ((x[i + 1] - x[i]) / length, (y[i + 1] - y[i]) / length) if length > 0.0 else None
            )
        # A zero-length segment takes the direction of the nearest one with length,
        # looking forward first.
        unit: list[tuple[float, float] | None] = list(own)
        following: tuple[float, float] | None = None
        for i in range(len(own) - 1, -1, -1):
            following = own[i] if own[i] is not None else following
            unit[i] = following
        preceding: tuple[float, float] | None = None
        for i, value in enumerate(unit):
            if value is None:
                unit[i] = preceding
            else:
                preceding = own[i] if own[i] is not None else preceding
        filled = [u if u is not None else (0.0, 0.0) for u in unit]  # never: length > 0
        return _Tables(x, y, arc, filled)

    def prepare(self) -> None:
        """Make the look-up tables now rather than at the first look-up (a path made
        ahead of the control cycles that read it)."""
        _ = self._tables

    @property
    def last_segment(self) -> int:
        return int(self.points_m.shape[0]) - 2

    @property
    def length_m(self) -> float:
        return self._tables.arc[-1]

    def check(self, projection: PathProjection) -> None:
        if not 0 <= projection.segment_index <= self.last_segment:
            raise ValueError(
                f"segment_index {projection.segment_index} outside 0..{self.last_segment}"
            )
        if not 0.0 <= projection.fraction <= 1.0:
            raise ValueError(f"fraction {projection.fraction} outside [0, 1]")

    def arc_at(self, projection: PathProjection) -> float:
        arc = self._tables.arc
        i = projection.segment_index
        start = arc[i]
        return start + projection.fraction * (arc[i + 1] - start)

    def segment_at_arc(self, arc_m: float) -> int:
        """The segment holding the point ``arc_m`` along the path (clamped to the ends)."""
        index = bisect.bisect_right(self._tables.arc, arc_m) - 1
        return max(0, min(self.last_segment, index))

    def projection_at_arc(self, arc_m: float) -> PathProjection:
        """The point ``arc_m`` along the path (clamped to the path) as a projection; at a
        vertex, on the segment leaving it."""
        arc = self._tables.arc
        i = self.segment_at_arc(arc_m)
        span = arc[i + 1] - arc[i]
        fraction = min(max((arc_m - arc[i]) / span, 0.0), 1.0) if span > 0.0 else 0.0
        return PathProjection(i, fraction)

    def direction(self, segment_index: int) -> tuple[float, float]:
        """Unit direction of a segment, or of the nearest one with length (forward first)."""
        return self._tables.unit[segment_index]

    def point(self, projection: PathProjection) -> tuple[float, float]:
        t = self._tables
        i, f = projection.segment_index, projection.fraction
        x0, y0 = t.x[i], t.y[i]
        return x0 + f * (t.x[i + 1] - x0), y0 + f * (t.y[i + 1] - y0)


def project_onto_path(
    path: Polyline, x_m: float, y_m: float, first_segment: int = 0, last_segment: int = -1
) -> PathProjection:
    """Nearest point of segments ``first_segment..last_segment`` (inclusive) to (x, y).

    A plain nearest-point search within an index window (the tracker's: a few segments
    around where the anchor will be): the route planner's projection (bounded both ways
    from the last index, refusing jumps where the path overlaps itself) is the one the
    vehicle uses. Ties go to the lowest segment index.
    """
    first = max(0, min(first_segment, path.last_segment))
    last = (
        path.last_segment if last_segment < 0 else max(first, min(last_segment, path.last_segment))
    )
    t = path._tables
    xs, ys, arc = t.x, t.y, t.arc
    best, best_fraction, best_d2 = first, 0.0, math.inf
    for i in range(first, last + 1):
        ax, ay = xs[i], ys[i]
        dx, dy = xs[i + 1] - ax, ys[i + 1] - ay
        length = arc[i + 1] - arc[i]
        length_sq = length * length  # may underflow to 0 for a tiny segment
        to_x, to_y = x_m - ax, y_m - ay
        fraction = (to_x * dx + to_y * dy) / length_sq if length_sq > 0.0 else 0.0
        fraction = 0.0 if fraction < 0.0 else 1.0 if fraction > 1.0 else fraction
        off_x, off_y = to_x - fraction * dx, to_y - fraction * dy
        d2 = off_x * off_x + off_y * off_y
        if d2 < best_d2:
            best, best_fraction, best_d2 = i, fraction, d2
    return PathProjection(best, best_fraction)


def point_at_arc_length(
    path: Polyline, projection: PathProjection, ahead_m: float
) -> tuple[tuple[float, float], bool]:
    """The point ``ahead_m`` along the path from ``projection`` (negative: behind).

    Interpolated within a segment, never snapped to a vertex. Past either end the path is
    continued straight along its end segment: the goal keeps moving smoothly ahead of a
    vehicle nearing the route's end, so it settles onto the last segment's heading
    instead of chasing a goal that shrinks onto it (eta would swing as the distance goes
    to zero). The flag says whether the point lies on the continuation.
    """
    return _point_at(path, path.arc_at(projection) + ahead_m)


def _point_at(path: Polyline, target: float) -> tuple[tuple[float, float], bool]:
    t = path._tables
    arc = t.arc
    total = arc[-1]
    if target > total + _ARC_EPSILON_M:
        ux, uy = t.unit[-1]
        beyond = target - total
        return (t.x[-1] + beyond * ux, t.y[-1] + beyond * uy), True
    if target < -_ARC_EPSILON_M:
        ux, uy = t.unit[0]
        return (t.x[0] + target * ux, t.y[0] + target * uy), True
    i = max(0, min(len(arc) - 2, bisect.bisect_right(arc, target) - 1))
    start_arc, end_arc = arc[i], arc[i + 1]
    fraction = 1.0 if end_arc == start_arc else (target - start_arc) / (end_arc - start_arc)
    fraction = min(1.0, max(0.0, fraction))
    x0, y0 = t.x[i], t.y[i]
    return (x0 + fraction * (t.x[i + 1] - x0), y0 + fraction * (t.y[i + 1] - y0)), False


def signed_cross_track_m(
    path: Polyline, projection: PathProjection, x_m: float, y_m: float
) -> float:
    """Distance of (x, y) from the projected point, positive when left of the path."""
    px, py = path.point(projection)
    ux, uy = path.direction(projection.segment_index)
    return ux * (y_m - py) - uy * (x_m - px)


def path_curvature_per_m(path: Polyline, projection: PathProjection, half_window_m: float) -> float:
    """Signed curvature (left positive) of the circle through the path points
    ``half_window_m`` behind, at and ahead of the projection (Menger curvature): a
    polyline's curvature lives in its vertices, so it is measured over a window."""
    here_m = path.arc_at(projection)
    (ax, ay), _ = _point_at(path, here_m - half_window_m)
    bx, by = path.point(projection)
    (cx, cy), _ = _point_at(path, here_m + half_window_m)
    cross = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    sides = (
        math.hypot(bx - ax, by - ay) * math.hypot(cx - bx, cy - by) * math.hypot(cx - ax, cy - ay)
    )
    return 0.0 if sides <= 0.0 else 2.0 * cross / sides


def goal_shift_m(
    path: Polyline, from_arc_m: float, lookahead_m: float, half_window_m: float
) -> float:
    """How far left to move the goal so that the arc through it has the path's curvature
    at ``from_arc_m`` instead of the look-ahead's weighted mean (see PursuitParams).

    A path ahead of a vehicle on it is, to first order, ``y(L) = int_0^L (L - u) k(u) du``
    sideways of its tangent, and the arc through that point has curvature ``2 y(L) / L^2``;
    the shift is ``L^2 k(0) / 2 - y(L)``, zero where the curvature does not change. The
    curvature is the Menger one over +-``half_window_m`` (a polyline's lives in its
    vertices), sampled every quarter metre (trapezoids); past the path's ends the path
    is held at its end point, so the curvature there fades to zero.
    """
    if lookahead_m <= 0.0:
        return 0.0
    t = path._tables
    arc, xs, ys, unit = t.arc, t.x, t.y, t.unit
    first_arc, end_arc = arc[0], arc[-1]
    samples = max(4, math.ceil(lookahead_m / _GOAL_SHIFT_SAMPLE_M))
    step_m = lookahead_m / samples
    # The three points of each sample as np.interp gives them (held at the path's end
    # points beyond them; inside, the segment's slope times the way into it), each found
    # by walking on from the last sample's segment. Written out three times: this runs
    # 3 x ~12 times a cycle, and a call per point would cost as much as the arithmetic.
    behind = here = ahead = -1
    first_kappa = offset_m = last_u = last_integrand = 0.0
    for j in range(samples + 1):
        u = lookahead_m if j == samples else j * step_m
        at = from_arc_m + u
        s = at - half_window_m
        if s < first_arc:
            ax, ay = xs[0], ys[0]
        elif s >= end_arc:
            ax, ay = xs[-1], ys[-1]
        else:
            if behind < 0:
                behind = bisect.bisect_right(arc, s) - 1
            while arc[behind + 1] <= s:
                behind += 1
            (sx, sy), into = unit[behind], s - arc[behind]
            ax, ay = sx * into + xs[behind], sy * into + ys[behind]
        if at < first_arc:
            bx, by = xs[0], ys[0]
        elif at >= end_arc:
            bx, by = xs[-1], ys[-1]
        else:
            if here < 0:
                here = bisect.bisect_right(arc, at) - 1
            while arc[here + 1] <= at:
                here += 1
            (sx, sy), into = unit[here], at - arc[here]
            bx, by = sx * into + xs[here], sy * into + ys[here]
        s = at + half_window_m
        if s < first_arc:
            cx, cy = xs[0], ys[0]
        elif s >= end_arc:
            cx, cy = xs[-1], ys[-1]
        else:
            if ahead < 0:
                ahead = bisect.bisect_right(arc, s) - 1
            while arc[ahead + 1] <= s:
                ahead += 1
            (sx, sy), into = unit[ahead], s - arc[ahead]
            cx, cy = sx * into + xs[ahead], sy * into + ys[ahead]
        abx, aby, acx, acy = bx - ax, by - ay, cx - ax, cy - ay
        sides = math.hypot(abx, aby) * math.hypot(cx - bx, cy - by) * math.hypot(acx, acy)
        kappa = 2.0 * (abx * acy - aby * acx) / sides if sides > 1e-12 else 0.0
        integrand = (lookahead_m - u) * kappa
        if j == 0:
            first_kappa = kappa
        else:
            offset_m += 0.5 * (integrand + last_integrand) * (u - last_u)
        last_u, last_integrand = u, integrand
    return 0.5 * lookahead_m**2 * first_kappa - offset_m
