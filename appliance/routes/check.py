"""Can this vehicle drive this route? Tight turns refuse it; close passes, gaps and repeated
points are flagged. Every finding names where: the point's index, the distance from the
start along the route, east/north (and lat/lon when the frame is known).

Curvature is taken from three-point circles over a span of arc length (`curvature_span_m`,
3 m by default): at each point, the circle through it and the route 1.5 m behind and 1.5 m
ahead (the route's own points nearest there, else positions interpolated along the line;
see `signed_curvature_per_m`). Neighbouring points alone would turn a 2 cm error between
points 0.5 m apart into a 6 m radius. Measured on a kilometre of straight line with 2 cm of
independent noise per point every 0.5 m, the tightest radius faked is about 6 m with a 3 m
span (5 m with 2 m, 13 m with 4 m); after the recorder's smoothing 14-20 m (5-11 m with a
2 m span), and with 5 cm of noise 5-7 m. A turn shorter than the span reads wider than it
is (a 30° turn of 3 m radius reads 4.0 m; driven at 4 m it is 3.5 cm off), a longer one is
measured exactly, and a kink still reads as the circle through its three points.

The vehicle's limit is the kinematic one of proportional four-wheel counter-steer
(Stanley et al., eq. 1; `appliance/sim/vehicle.py`), at the vehicle's geometric centre,
which is the point a route describes (see `min_turn_radius_m`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from appliance.config.models import VehicleConfig
from appliance.localization.local_frame import LocalFrame
from appliance.routes.overlap import Overlap, find_overlaps

FloatArray = NDArray[np.float64]


def turn_radius_at_centre_m(
    wheelbase_m: float, counter_steer_ratio_k: float, steer_rad: float
) -> float:
    """Radius the geometric centre (midway between the axles) turns on at front steer angle
    ``steer_rad`` with the rear counter-steering ``k * steer_rad``.

    The turn centre is ``y0 = L / (tan φ + tan kφ)`` to the side of the vehicle's axis (that
    is the radius of the axis point that moves straight ahead); the geometric centre sits
    ``x0 = y0 * tan β`` from that point along the axis, with ``tan β = (tan φ - tan kφ) / 2``
    its sideslip, so its radius is ``y0 / cos β``. For k = 1 both are the same; for the
    Husky (k = 0.63, 32°) the centre's radius is 0.8 % larger. The simulated vehicle
    integrates the same (yaw rate ``v cos β (tan φ + tan kφ) / L``).
    """
    tan_front, tan_rear = math.tan(steer_rad), math.tan(counter_steer_ratio_k * steer_rad)
    tan_beta = (tan_front - tan_rear) / 2.0
    return wheelbase_m * math.sqrt(1.0 + tan_beta**2) / (tan_front + tan_rear)


def min_turn_radius_m(config: VehicleConfig) -> float:
    """The tightest turn of ``config``'s vehicle at full steer (limits.max_steer_angle_deg),
    at crawling speed: faster, the sideslip gain G_ss widens it, and the speed controller
    slows for curvature, so the kinematic radius is what a route may ask."""
    return turn_radius_at_centre_m(
        config.geometry.wheelbase_m,
        config.geometry.counter_steer_ratio_k,
        math.radians(config.limits.max_steer_angle_deg),
    )


def _snap_to_points(s_m: FloatArray, targets_m: FloatArray, half_m: float, behind: bool) -> None:
    """Move each target arc length onto the route's own point nearest to it, where one lies
    within ``half_m / 2`` (a tie goes to the point nearer the centre: deterministic, and
    the tighter reading)."""
    above = np.clip(np.searchsorted(s_m, targets_m), 1, len(s_m) - 1)
    below = above - 1
    to_below, to_above = targets_m - s_m[below], s_m[above] - targets_m
    tie_m = 1e-9 * max(1.0, float(s_m[-1]))
    if behind:
        nearest = np.where(to_above <= to_below + tie_m, above, below)
    else:
        nearest = np.where(to_below <= to_above + tie_m, below, above)
    close = np.abs(s_m[nearest] - targets_m) <= half_m / 2.0
    targets_m[close] = s_m[nearest[close]]


def signed_curvature_per_m(points_m: FloatArray, span_m: float) -> FloatArray:
    """(N,) curvature at each point, positive turning left (counter-clockwise), from the
    circle through the point and the route ``span_m / 2`` behind and ahead of it; 0 where
    less than a quarter of that half-span exists on a side (the two ends).

    Behind and ahead are the route's own points nearest to ``span_m / 2`` away (within a
    quarter span of it): positions interpolated on the chords between sparse points lie
    inside a curve and would make it read tighter (11 % at 1 m spacing on 15 m). Where no
    point is that close (long straight segments meeting at a kink) the positions are
    interpolated, so a kink reads as the corner it is."""
    points_m = np.asarray(points_m, dtype=np.float64)
    deltas = np.diff(points_m, axis=0)
    s_m = np.concatenate(([0.0], np.cumsum(np.hypot(deltas[:, 0], deltas[:, 1]))))
    half_m = span_m / 2.0
    s_back, s_ahead = np.maximum(s_m - half_m, 0.0), np.minimum(s_m + half_m, s_m[-1])
    if len(s_m) >= 2:
        _snap_to_points(s_m, s_back, half_m, behind=True)
        _snap_to_points(s_m, s_ahead, half_m, behind=False)
    back = np.column_stack([np.interp(s_back, s_m, points_m[:, k]) for k in (0, 1)])
    ahead = np.column_stack([np.interp(s_ahead, s_m, points_m[:, k]) for k in (0, 1)])
    in_ = points_m - back
    out = ahead - points_m
    chord = ahead - back
    cross = in_[:, 0] * out[:, 1] - in_[:, 1] * out[:, 0]
    sides = np.hypot(in_[:, 0], in_[:, 1]) * np.hypot(out[:, 0], out[:, 1])
    sides *= np.hypot(chord[:, 0], chord[:, 1])
    valid = (s_m - s_back >= half_m / 4.0) & (s_ahead - s_m >= half_m / 4.0) & (sides > 0.0)
    curvature = np.zeros(len(points_m))
    curvature[valid] = 2.0 * cross[valid] / sides[valid]
    return curvature


def min_radius_found_m(points_m: FloatArray, span_m: float) -> float:
    """The tightest radius along the route (inf for a straight line)."""
    curvature = np.abs(signed_curvature_per_m(points_m, span_m))
    peak = float(curvature.max()) if len(curvature) else 0.0
    return math.inf if peak == 0.0 else 1.0 / peak


@dataclass(frozen=True)
class CheckParams:
    curvature_span_m: float = 3.0
    # Parts of the route closer than this (and not neighbours along it) are flagged.
    overlap_distance_m: float = 2.0
    # Points further apart than this are flagged: the vehicle drives a straight line there.
    max_gap_m: float = 20.0
    # A point closer than this to the one before it repeats it (flagged, then dropped).
    duplicate_distance_m: float = 0.01
    # Longer routes are refused unchecked (a tangent plane is no map for them).
    max_length_m: float = 100_000.0
    max_problems_listed: int = 50


class Severity(StrEnum):
    REFUSE = "refused"
    WARN = "warning"


class ProblemKind(StrEnum):
    TIGHT_TURN = "tight_turn"
    SELF_OVERLAP = "self_overlap"
    GAP = "gap"
    DUPLICATE = "duplicate"
    UNUSABLE = "unusable"  # too long, too few distinct points


@dataclass(frozen=True)
class Place:
    """Where on the route: index into the points checked, distance along the route."""

    index: int
    distance_m: float
    east_m: float
    north_m: float
    lat_deg: float | None = None
    lon_deg: float | None = None

    def describe(self) -> str:
        text = (
            f"point {self.index}, {self.distance_m:.1f} m from the start "
            f"(east {self.east_m:.2f} m, north {self.north_m:.2f} m"
        )
        if self.lat_deg is not None and self.lon_deg is not None:
            text += f"; lat {self.lat_deg:.7f}, lon {self.lon_deg:.7f}"
        return text + ")"


@dataclass(frozen=True)
class Problem:
    kind: ProblemKind
    severity: Severity
    message: str  # says where
    place: Place | None = None
    other: Place | None = None  # the second place of an overlap, the end of a gap
    radius_m: float | None = None  # the tightest radius of a tight turn


@dataclass(frozen=True)
class CheckReport:
    problems: tuple[Problem, ...]  # refusals first, then along the route
    problems_not_listed: int
    min_turn_radius_m: float
    min_radius_found_m: float  # inf: no turn at all
    curvature_span_m: float
    length_m: float
    point_count: int

    @property
    def refused(self) -> bool:
        return any(problem.severity is Severity.REFUSE for problem in self.problems)


class _Places:
    """Builds `Place`s on the checked points: original indices, lat/lon when known."""

    def __init__(self, points_m: FloatArray, original_index: NDArray[np.int64], s_m: FloatArray,
                 frame: LocalFrame | None) -> None:  # fmt: skip
        self._points_m, self._index, self._s_m, self._frame = points_m, original_index, s_m, frame

    def at_point(self, k: int) -> Place:
        east_m, north_m = float(self._points_m[k, 0]), float(self._points_m[k, 1])
        return self.at(float(self._s_m[k]), east_m, north_m, int(self._index[k]))

    def at(
        self, distance_m: float, east_m: float, north_m: float, index: int | None = None
    ) -> Place:
        if index is None:  # the checked point nearest along the route
            k = int(np.clip(np.searchsorted(self._s_m, distance_m), 1, len(self._s_m) - 1))
            k = k - 1 if distance_m - self._s_m[k - 1] < self._s_m[k] - distance_m else k
            index = int(self._index[k])
        lat_deg = lon_deg = None
        if self._frame is not None:
            lat_deg, lon_deg, _alt = self._frame.to_geodetic(east_m, north_m)
        return Place(index, distance_m, east_m, north_m, lat_deg, lon_deg)


def _without_repeats(points_m: FloatArray, duplicate_m: float) -> NDArray[np.int64]:
    """Indices of the points kept: each at least ``duplicate_m`` from the last one kept."""
    if len(points_m) == 0:
        return np.zeros(0, dtype=np.int64)
    kept = [0]
    last_x, last_y = float(points_m[0, 0]), float(points_m[0, 1])
    for k, (x, y) in enumerate(points_m.tolist()):
        if math.hypot(x - last_x, y - last_y) >= duplicate_m:
            kept.append(k)
            last_x, last_y = x, y
    return np.asarray(kept, dtype=np.int64)


def check_route(
    points_enu_m: FloatArray,
    min_turn_radius_m: float,
    params: CheckParams = CheckParams(),
    frame: LocalFrame | None = None,
) -> CheckReport:
    """Check (N, 2) east-north metres (in ``frame``, used only to name places in lat/lon)
    against the vehicle's ``min_turn_radius_m``."""
    points_m = np.asarray(points_enu_m, dtype=np.float64)
    if points_m.ndim != 2 or points_m.shape[1] != 2 or not np.all(np.isfinite(points_m)):
        raise ValueError("points must be a finite (N, 2) array of east, north metres")
    problems: list[Problem] = []
    kept = _without_repeats(points_m, params.duplicate_distance_m)
    repeats = len(points_m) - len(kept)
    checked = points_m[kept]
    deltas = np.diff(checked, axis=0)
    seg_m = np.hypot(deltas[:, 0], deltas[:, 1])
    s_m = np.concatenate(([0.0], np.cumsum(seg_m)))
    length_m = float(s_m[-1])
    places = _Places(checked, kept, s_m, frame)
    if repeats:
        first_repeat = int(np.setdiff1d(np.arange(len(points_m)), kept)[0])
        problems.append(Problem(
            ProblemKind.DUPLICATE, Severity.WARN,
            f"{repeats} point(s) repeat the one before (within {params.duplicate_distance_m} m), "
            f"the first is point {first_repeat}; they are left out of the checks",
        ))  # fmt: skip
    unusable = None
    if len(checked) < 2:
        unusable = "fewer than 2 distinct points"
    elif length_m > params.max_length_m:
        limit_km = params.max_length_m / 1000
        unusable = f"{length_m / 1000:.1f} km long, more than the {limit_km:g} km a route may be"
    if unusable is not None:
        problems.insert(
            0, Problem(ProblemKind.UNUSABLE, Severity.REFUSE, f"the route is {unusable}")
        )
        return CheckReport(tuple(problems), 0, min_turn_radius_m, math.nan,
                           params.curvature_span_m, length_m, len(points_m))  # fmt: skip
    curvature = signed_curvature_per_m(checked, params.curvature_span_m)
    peak = float(np.abs(curvature).max())
    problems += _tight_turns(curvature, min_turn_radius_m, places, s_m)
    problems += _overlaps(checked, params.overlap_distance_m, places)
    for k in np.flatnonzero(seg_m > params.max_gap_m).tolist():
        start, end = places.at_point(k), places.at_point(k + 1)
        problems.append(Problem(
            ProblemKind.GAP, Severity.WARN,
            f"{seg_m[k]:.1f} m between {start.describe()} and point {end.index}: "
            "the vehicle drives a straight line there",
            start, end,
        ))  # fmt: skip
    order = {Severity.REFUSE: 0, Severity.WARN: 1}
    problems.sort(key=lambda p: (order[p.severity], p.place.distance_m if p.place else -1.0))
    listed = problems[: params.max_problems_listed]
    return CheckReport(
        tuple(listed), len(problems) - len(listed), min_turn_radius_m,
        math.inf if peak == 0.0 else 1.0 / peak, params.curvature_span_m, length_m,
        len(points_m),
    )  # fmt: skip


def _tight_turns(
    curvature: FloatArray, min_radius_m: float, places: _Places, s_m: FloatArray
) -> list[Problem]:
    """One refusal per stretch tighter than the vehicle can turn, at its tightest point."""
    too_tight = np.abs(curvature) * min_radius_m > 1.0
    edges = np.diff(np.concatenate(([0], too_tight.astype(np.int8), [0])))
    problems = []
    for start, stop in zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True):
        k = int(start + np.argmax(np.abs(curvature[start:stop])))
        radius_m = 1.0 / abs(float(curvature[k]))
        side = "left" if curvature[k] > 0 else "right"
        place = places.at_point(k)
        problems.append(Problem(
            ProblemKind.TIGHT_TURN, Severity.REFUSE,
            f"{side} turn of radius {radius_m:.2f} m at {place.describe()}: the vehicle needs "
            f"at least {min_radius_m:.2f} m (too tight from {s_m[start]:.1f} to "
            f"{s_m[stop - 1]:.1f} m)",
            place, radius_m=radius_m,
        ))  # fmt: skip
    return problems


def _overlaps(points_m: FloatArray, distance_m: float, places: _Places) -> list[Problem]:
    result = find_overlaps(points_m, distance_m)
    if result.skipped_reason is not None:
        return [
            Problem(
                ProblemKind.SELF_OVERLAP,
                Severity.WARN,
                f"not checked for overlaps: {result.skipped_reason}",
            )
        ]
    return [_overlap_problem(overlap, distance_m, places) for overlap in result.overlaps]


def _overlap_problem(overlap: Overlap, distance_m: float, places: _Places) -> Problem:
    first = places.at(overlap.first_distance_m, *overlap.first_xy_m)
    second = places.at(overlap.second_distance_m, *overlap.second_xy_m)
    if overlap.gap_m < distance_m / 8.0 and 20.0 < overlap.angle_deg < 160.0:
        how = "crosses itself"
    elif overlap.angle_deg <= 90.0:
        how = f"passes {overlap.gap_m:.2f} m beside itself, the same way"
    else:
        how = f"comes back {overlap.gap_m:.2f} m beside itself"
    near_ends = overlap.first_distance_m <= 1.5 * distance_m
    if near_ends and places.at_point(-1).distance_m - overlap.second_distance_m <= 1.5 * distance_m:
        how = f"ends {overlap.gap_m:.2f} m from where it starts (a loop)"
    return Problem(
        ProblemKind.SELF_OVERLAP, Severity.WARN,
        f"the route {how}: at {first.describe()} and at {second.describe()} "
        f"(within {distance_m:g} m over {_stretch(overlap.first_extent_m)} "
        f"and {_stretch(overlap.second_extent_m)})",
        first, second,
    )  # fmt: skip


def _stretch(extent_m: tuple[float, float]) -> str:
    return f"{extent_m[0]:.1f}..{extent_m[1]:.1f} m"
