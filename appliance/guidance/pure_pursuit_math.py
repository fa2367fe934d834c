"""Pure pursuit for proportional four-wheel counter-steer: the pure functions.

Stanley et al.'s eqs. 1-3, written in this repository's frames, and the path geometry the
tracker (``pure_pursuit.py``) needs. Everything here is a function of its arguments.

**Signs.** Frames are counter-clockwise positive. ``eta_rad`` is the angle from the
vehicle's heading to the line from the anchor to the goal (a goal to the left is positive)
and a positive front wheel angle turns left; the rear wheels counter-steer by ``k`` times
the front angle, positive in the counter-steer direction, as ``appliance.sim.vehicle``
has it (``yaw_rate = v / L * (tan phi_f + tan phi_r) * G_ss``). The paper's leading minus
sign is its own convention's (after Kuwata et al., steer angle and eta counted in opposite
senses); here a goal to the left must give a left turn, so the minus is dropped, and the
tests drive the simulated vehicle at the commanded angle to check that the anchor does
reach the goal.

**Geometry** (Fig. 8). With ``tan(phi_r) = r * tan(phi_f)`` the instant centre of rotation
lies ``R = L / ((1 + r) tan phi_f)`` to the side, level with a *virtual rear axle*
``L r / (1 + r)`` ahead of the real one. The anchor, ``l_fw`` ahead of the real rear
axle (the paper measures from the rear axle; the vehicle file's
``anchor_point_forward_m`` is from the centre, so ``l_fw = L / 2 + anchor_point_forward_m``),
is ``l = l_fw - L r / (1 + r)`` ahead of the virtual axle. The circle about the centre
of rotation through the anchor passes through a goal at distance ``D`` and angle eta
when ``R = (D / 2 + l cos eta) / sin eta``, hence

    tan phi_f = (L / (1 + r)) sin eta / (D / 2 + (l_fw - L r / (1 + r)) cos eta)

which is eq. 2 with ``r = tan(k phi_f) / tan(phi_f)`` (the wheel *angles* are
proportional), eq. 3 with ``r = k`` and eq. 1 with ``r = 0``.

**Sideslip.** The model's gain ``G_ss`` scales the yaw rate but not the direction of
travel at the centre, so the centre of rotation moves out *from the vehicle centre* by
``1 / G_ss``: the radius grows and the virtual axle slides back by
``(1 / G_ss - 1) (L / 2 - L r / (1 + r))``. ``sideslip_gain`` < 1 puts both into the
formula, so the arc the plant drives is the one pure pursuit meant; with ``G_ss = 1`` the
formula is the paper's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]

EQ2_TOLERANCE_RAD = 1e-12
EQ2_MAX_ITERATIONS = 50
# Below this |phi| the ratio tan(k phi) / tan(phi) is replaced by its series, because the
# quotient of two tiny tangents loses digits and is 0/0 at phi = 0.
_SMALL_ANGLE_RAD = 1e-4
# Rounding left over from walking the segments: not "past the end".
_ARC_EPSILON_M = 1e-9


def steer_for_ratio_rad(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    rear_ratio: float,
    sideslip_gain: float = 1.0,
) -> float:
    """Front wheel angle whose arc takes the anchor through the goal (module docstring).

    ``lookahead_m`` is the straight distance from the anchor to the goal (``L_fw``) and
    ``rear_ratio`` is ``tan(phi_r) / tan(phi_f)``. When the denominator is not positive
    the circle through anchor and goal curves away from the goal (it reaches it the long
    way round; with the anchor at or ahead of the virtual axle, only ever for a goal
    behind the anchor), so the answer is full lock towards the goal instead: ``atan2``
    clipped to ±pi/2, continuous as the denominator passes through zero.
    """
    effective_wheelbase_m = wheelbase_m / ((1.0 + rear_ratio) * sideslip_gain)
    virtual_axle_from_centre_m = (
        wheelbase_m * rear_ratio / (1.0 + rear_ratio) - wheelbase_m / 2.0
    ) / sideslip_gain
    anchor_from_virtual_axle_m = anchor_from_rear_axle_m - (
        wheelbase_m / 2.0 + virtual_axle_from_centre_m
    )
    numerator = effective_wheelbase_m * math.sin(eta_rad)
    denominator = lookahead_m / 2.0 + anchor_from_virtual_axle_m * math.cos(eta_rad)
    phi = math.atan2(numerator, denominator)
    return max(-math.pi / 2.0, min(math.pi / 2.0, phi))


def steer_eq3_rad(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
    *,
    sideslip_gain: float = 1.0,
) -> float:
    """The paper's general form, eq. 3 (eq. 1 when ``k = 0``), in our signs.

    ``lookahead_m`` is the distance from the anchor to the goal, ``L_fw`` in the paper.
    """
    return steer_for_ratio_rad(
        eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k, sideslip_gain
    )


def counter_steer_tan_ratio(phi_rad: float, k: float) -> float:
    """``tan(k phi) / tan(phi)``: the tangent ratio when the wheel *angles* are in ratio k.

    Tends to ``k`` as phi -> 0 (series ``k (1 - (1 - k^2) phi^2 / 3)``), and to 0 at
    ±pi/2 where tan(phi) is unbounded.
    """
    if abs(phi_rad) < _SMALL_ANGLE_RAD:
        return k * (1.0 - (1.0 - k * k) * phi_rad * phi_rad / 3.0)
    return math.tan(k * phi_rad) / math.tan(phi_rad)


@dataclass(frozen=True)
class Eq2Solution:
    phi_rad: float
    iterations: int
    converged: bool


def solve_eq2(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
    *,
    sideslip_gain: float = 1.0,
    tolerance_rad: float = EQ2_TOLERANCE_RAD,
    max_iterations: int = EQ2_MAX_ITERATIONS,
) -> Eq2Solution:
    """The open form, eq. 2, by fixed-point iteration.

    ``phi_{n+1} = F(r(phi_n))`` with ``F`` = :func:`steer_for_ratio_rad` and
    ``r(phi) = tan(k phi) / tan(phi)``, from eq. 3's answer (``r = k``). Converged when
    two iterates differ by at most ``tolerance_rad`` (1e-12 rad); after ``max_iterations``
    (50) the last iterate is returned with ``converged=False``. It contracts because ``r``
    changes slowly with phi (``dr/dphi ~ -2 k (1 - k^2) phi / 3``): for the Husky at most
    10 iterations within ±35° and 15 for any goal ahead; it slows only towards ±90°,
    beyond any steering limit. At phi -> 0, ``r`` -> k through its series
    (:func:`counter_steer_tan_ratio`), so eq. 2 meets eq. 3 there and the iteration ends
    at once; with ``k = 0`` the two are the same equation. ``k`` must lie in [0, 1] so
    that ``k phi`` stays within ±pi/2.
    """
    if not 0.0 <= k <= 1.0:
        raise ValueError(f"k must lie in [0, 1] for the open form (got {k})")
    phi = steer_for_ratio_rad(
        eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k, sideslip_gain
    )
    for iteration in range(1, max_iterations + 1):
        ratio = counter_steer_tan_ratio(phi, k)
        following = steer_for_ratio_rad(
            eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, ratio, sideslip_gain
        )
        if abs(following - phi) <= tolerance_rad:
            return Eq2Solution(following, iteration, True)
        phi = following
    return Eq2Solution(phi, max_iterations, False)


def steer_eq2_rad(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
    *,
    sideslip_gain: float = 1.0,
) -> float:
    """The open form, eq. 2, in our signs (see :func:`solve_eq2`)."""
    return solve_eq2(
        eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k, sideslip_gain=sideslip_gain
    ).phi_rad


@dataclass(frozen=True)
class Eq2Eq3Comparison:
    """Eq. 2 against eq. 3 over a grid of eta, for the paper's "<= 2 % within ±30°"."""

    eta_rad: FloatArray
    eq2_rad: FloatArray
    eq3_rad: FloatArray
    relative_difference: FloatArray  # |eq3 - eq2| / |eq2|, 0 where both are 0

    def max_within(self, steer_limit_rad: float, max_abs_eta_rad: float = math.pi / 2) -> float:
        """Largest relative difference where the exact (eq. 2) angle is within the limit.

        Only goals ahead (``|eta| <= max_abs_eta_rad``) by default: a goal behind the
        anchor can also need a small angle (a long way round), which is not tracking.
        """
        inside = (np.abs(self.eq2_rad) <= steer_limit_rad) & (
            np.abs(self.eta_rad) <= max_abs_eta_rad
        )
        return float(np.max(self.relative_difference[inside], initial=0.0))


def eq2_vs_eq3_difference(
    eta_grid_rad: FloatArray,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
) -> Eq2Eq3Comparison:
    eta = np.asarray(eta_grid_rad, dtype=np.float64)
    eq2 = np.array(
        [steer_eq2_rad(e, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k) for e in eta]
    )
    eq3 = np.array(
        [steer_eq3_rad(e, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k) for e in eta]
    )
    scale = np.abs(eq2)
    difference = np.abs(eq3 - eq2)
    relative = np.divide(difference, scale, out=np.zeros_like(difference), where=scale > 0)
    return Eq2Eq3Comparison(eta, eq2, eq3, relative)


# --- look-ahead -----------------------------------------------------------------------


def minimum_turn_radius_m(
    wheelbase_m: float, k: float, max_steer_rad: float, sideslip_gain: float = 1.0
) -> float:
    """Lateral distance to the centre of rotation at full lock (eq. 3's geometry)."""
    return wheelbase_m / ((1.0 + k) * math.tan(max_steer_rad) * sideslip_gain)


def minimum_lookahead_m(
    min_turn_radius_m: float, anchor_from_virtual_axle_m: float, linear_eta_rad: float
) -> float:
    """Shortest goal distance at which a goal ``linear_eta_rad`` off the heading is reachable.

    A goal at distance D and angle eta needs ``R = (D / 2 + l cos eta) / sin eta``; below
    ``D = 2 (R_min sin eta - l cos eta)`` that radius is tighter than full lock, so every
    goal further off than eta saturates the steering and pure pursuit stops being a
    smooth law and becomes bang-bang. With this floor a goal up to ``linear_eta_rad``
    off the heading is always inside the reachable set.
    """
    return max(
        0.0,
        2.0
        * (
            min_turn_radius_m * math.sin(linear_eta_rad)
            - anchor_from_virtual_axle_m * math.cos(linear_eta_rad)
        ),
    )


# --- the path -------------------------------------------------------------------------


@dataclass(frozen=True)
class PathProjection:
    """A point on a polyline: on segment ``segment_index`` (vertex i to i+1), ``fraction``
    of the way along it."""

    segment_index: int
    fraction: float


@dataclass(frozen=True, eq=False)
class Polyline:
    """A path in travel order with its cumulative arc length, built once per path.

    The tracker runs at the control rate while the planner changes the path at 0.5 Hz, so
    the O(N) work (checks, arc lengths) is done here once and each cycle only searches
    the table. Zero-length segments (repeated vertices) are allowed; the points are a
    read-only copy.
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

    @property
    def last_segment(self) -> int:
        return int(self.points_m.shape[0]) - 2

    def check(self, projection: PathProjection) -> None:
        if not 0 <= projection.segment_index <= self.last_segment:
            raise ValueError(
                f"segment_index {projection.segment_index} outside 0..{self.last_segment}"
            )
        if not 0.0 <= projection.fraction <= 1.0:
            raise ValueError(f"fraction {projection.fraction} outside [0, 1]")

    def arc_at(self, projection: PathProjection) -> float:
        i = projection.segment_index
        start, end = float(self.arc_m[i]), float(self.arc_m[i + 1])
        return start + projection.fraction * (end - start)

    def segment_at_arc(self, arc_m: float) -> int:
        """The segment holding the point ``arc_m`` along the path (clamped to the ends)."""
        index = int(np.searchsorted(self.arc_m, arc_m, side="right")) - 1
        return max(0, min(self.last_segment, index))

    def direction(self, segment_index: int) -> tuple[float, float]:
        """Unit direction of a segment, or of the nearest one with length (forward first)."""
        i = segment_index
        if not self.arc_m[i + 1] > self.arc_m[i]:
            lengths = np.diff(self.arc_m)
            ahead = np.flatnonzero(lengths[i:])
            i = i + int(ahead[0]) if ahead.size else int(np.flatnonzero(lengths[:i])[-1])
        length = float(self.arc_m[i + 1] - self.arc_m[i])
        delta = self.points_m[i + 1] - self.points_m[i]
        return float(delta[0]) / length, float(delta[1]) / length

    def point(self, projection: PathProjection) -> tuple[float, float]:
        i, f = projection.segment_index, projection.fraction
        start, end = self.points_m[i], self.points_m[i + 1]
        return float(start[0] + f * (end[0] - start[0])), float(start[1] + f * (end[1] - start[1]))


def project_onto_path(
    path: Polyline, x_m: float, y_m: float, first_segment: int = 0, last_segment: int = -1
) -> PathProjection:
    """Nearest point of segments ``first_segment..last_segment`` (inclusive) to (x, y).

    A plain nearest-point search within an index window, for tests and standalone use:
    the route planner's projection (bounded both ways from the last index, refusing jumps
    where the path overlaps itself) is the one the vehicle uses. Ties go to the lowest
    segment index.
    """
    first = max(0, min(first_segment, path.last_segment))
    last = (
        path.last_segment if last_segment < 0 else max(first, min(last_segment, path.last_segment))
    )
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
    target = path.arc_at(projection) + ahead_m
    total = float(path.arc_m[-1])
    if target > total + _ARC_EPSILON_M:
        ux, uy = path.direction(path.last_segment)
        end = path.points_m[-1]
        beyond = target - total
        return (float(end[0]) + beyond * ux, float(end[1]) + beyond * uy), True
    if target < -_ARC_EPSILON_M:
        ux, uy = path.direction(0)
        start = path.points_m[0]
        return (float(start[0]) + target * ux, float(start[1]) + target * uy), True
    i = path.segment_at_arc(target)
    start_arc, end_arc = float(path.arc_m[i]), float(path.arc_m[i + 1])
    fraction = 1.0 if end_arc == start_arc else (target - start_arc) / (end_arc - start_arc)
    return path.point(PathProjection(i, min(1.0, max(0.0, fraction)))), False


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
    (ax, ay), _ = point_at_arc_length(path, projection, -half_window_m)
    bx, by = path.point(projection)
    (cx, cy), _ = point_at_arc_length(path, projection, half_window_m)
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
    vertices), sampled every quarter metre; past the path's ends it is taken as straight.
    """
    if lookahead_m <= 0.0:
        return 0.0
    samples = max(4, math.ceil(lookahead_m / 0.25))
    u = np.linspace(0.0, lookahead_m, samples + 1)
    at = from_arc_m + u
    arc, xs, ys = path.arc_m, path.points_m[:, 0], path.points_m[:, 1]
    ax, ay = np.interp(at - half_window_m, arc, xs), np.interp(at - half_window_m, arc, ys)
    bx, by = np.interp(at, arc, xs), np.interp(at, arc, ys)
    cx, cy = np.interp(at + half_window_m, arc, xs), np.interp(at + half_window_m, arc, ys)
    cross = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    sides = np.hypot(bx - ax, by - ay) * np.hypot(cx - bx, cy - by) * np.hypot(cx - ax, cy - ay)
    kappa = np.divide(2.0 * cross, sides, out=np.zeros_like(cross), where=sides > 1e-12)
    weights = lookahead_m - u
    integrand = weights * kappa
    offset_m = float(np.sum(0.5 * (integrand[1:] + integrand[:-1]) * np.diff(u)))
    return 0.5 * lookahead_m**2 * float(kappa[0]) - offset_m


def predict_pose(
    pose: Pose2D, forward_mps: float, lateral_mps: float, yaw_rate_radps: float, horizon_s: float
) -> Pose2D:
    """Pose after ``horizon_s`` of constant body-frame velocity and yaw rate (an SE(2) arc)."""
    turn = yaw_rate_radps * horizon_s
    if abs(turn) < 1e-9:
        dx_body, dy_body = forward_mps * horizon_s, lateral_mps * horizon_s
    else:
        sin_t, one_minus_cos = math.sin(turn), 1.0 - math.cos(turn)
        dx_body = (forward_mps * sin_t - lateral_mps * one_minus_cos) / yaw_rate_radps
        dy_body = (forward_mps * one_minus_cos + lateral_mps * sin_t) / yaw_rate_radps
    moved = pose.compose(Pose2D(dx_body, dy_body, turn))
    return Pose2D(moved.x_m, moved.y_m, math.remainder(moved.yaw_rad, math.tau))
