"""Turning the track the operator drives into a route (`dbw route record NAME`).

Two steps, both chosen so that the route keeps the vehicle's real path and loses the fix's
noise:

1. **Thinning by distance** (on line): a fix is kept when it is at least ``spacing_m``
   (0.5 m) from the last kept one. At standstill the fix wanders by centimetres; those fixes
   are never ``spacing_m`` away, so a stop leaves one point, not a cloud whose noise would
   read as tight turns.
2. **Smoothing** (at the end): a local quadratic fit over arc length, evaluated at each kept
   point (Savitzky–Golay generalised to the uneven spacing thinning leaves), over
   ``smoothing_half_window_m`` (1.5 m) either side (a straight line where the window is
   one-sided, near the ends: a quadratic extrapolated to an end point multiplies the fix
   noise into a turn the vehicle never made). A quadratic follows an arc exactly to
   second order, so unlike a moving average it does not pull a turn inwards: on a 15 m
   radius the shift is below a millimetre (a 3 m moving average would cut 2.5 cm), while
   fix noise at 0.5 m spacing is reduced to √(1/3) ≈ 0.58 of its σ (7 points, weights
   (-2, 3, 6, 7, 6, 3, -2) / 21 when evenly spaced; thinning leaves 0.5-0.9 m).

Pure: positions and ``now_s`` in, a Route and a summary out; no clock, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from appliance.localization.local_frame import LocalFrame
from appliance.routes.check import CheckParams, min_radius_found_m
from appliance.routes.geojson import MAX_POINTS
from appliance.routes.route import Route

FloatArray = NDArray[np.float64]

# The route's curvature in the summary is taken over the check's span.
SUMMARY_CURVATURE_SPAN_M = CheckParams().curvature_span_m


class RecordingError(ValueError):
    """Nothing usable was recorded (fewer than two points apart)."""


@dataclass(frozen=True)
class RecorderParams:
    spacing_m: float = 0.5
    smoothing_half_window_m: float = 1.5
    max_points: int = MAX_POINTS  # kept; further fixes are dropped and the summary says so


@dataclass(frozen=True)
class RecordingSummary:
    name: str
    length_m: float  # of the smoothed route
    duration_s: float  # first to last fix received
    fixes_received: int
    fixes_rejected: int  # not finite
    points_kept: int
    points_dropped: int  # closer than spacing_m to the last kept point (or past max_points)
    min_radius_m: float  # tightest turn of the smoothed route; inf when straight
    truncated: bool  # max_points was reached


def smooth_along_arc(points_m: FloatArray, half_window_m: float) -> FloatArray:
    """(N, 2) points smoothed by a local quadratic fit of x(s) and y(s) over the points
    within ``half_window_m`` of arc length, evaluated at each point's own arc length.

    A window holding fewer than 3 points leaves its point as it is."""
    points_m = np.asarray(points_m, dtype=np.float64)
    count = len(points_m)
    if count < 3:
        return points_m.copy()
    deltas = np.diff(points_m, axis=0)
    s_m = np.concatenate(([0.0], np.cumsum(np.hypot(deltas[:, 0], deltas[:, 1]))))
    tolerance_m = 1e-9 * max(1.0, half_window_m)
    lo = np.searchsorted(s_m, s_m - half_window_m - tolerance_m, side="left")
    hi = np.searchsorted(s_m, s_m + half_window_m + tolerance_m, side="right")
    scale_m = half_window_m if half_window_m > 0.0 else 1.0  # u in -1..1: a well-posed fit
    reach = int(max(np.max(np.arange(count) - lo), np.max(hi - 1 - np.arange(count))))
    # Sums of u^p and u^p * (x, y) over each window, u = (s_j - s_i) / scale: one pass per
    # offset from the point, all points at once.
    moments = np.zeros((count, 5))
    weighted = np.zeros((count, 3, 2))
    index = np.arange(count)
    for offset in range(-reach, reach + 1):
        other = index + offset
        inside = (other >= lo) & (other < hi)
        rows, cols = index[inside], other[inside]
        u = (s_m[cols] - s_m[rows]) / scale_m
        powers = u[:, None] ** np.arange(5)
        moments[rows] += powers
        weighted[rows] += powers[:, :3, None] * points_m[cols][:, None, :]
    normal = moments[:, [[0, 1, 2], [1, 2, 3], [2, 3, 4]]]
    smoothed = points_m.copy()
    fit = (hi - lo >= 3) & (np.abs(np.linalg.det(normal)) > 1e-9)
    coefficients = np.linalg.solve(normal[fit], weighted[fit])
    smoothed[fit] = coefficients[:, 0, :]  # the fit's value at u = 0
    # Near an end the window is one-sided, and a quadratic extrapolated to its end point
    # multiplies the fix noise there (a false tight turn at the end of a recording): a
    # straight line through the same window extrapolates with less than the fix's noise.
    one_sided = (lo == 0) | (hi == count)  # the window reaches an end of the recording
    line_normal = moments[:, [[0, 1], [1, 2]]]
    line = one_sided & (hi - lo >= 2) & (np.abs(np.linalg.det(line_normal)) > 1e-12)
    line_coefficients = np.linalg.solve(line_normal[line], weighted[line][:, :2, :])
    smoothed[line] = line_coefficients[:, 0, :]
    return smoothed


class RouteRecorder:
    """Feed it the vehicle's position every fix; `finish` turns what it kept into a route."""

    def __init__(self, params: RecorderParams = RecorderParams()) -> None:
        if not (params.spacing_m > 0.0 and params.smoothing_half_window_m >= 0.0):
            raise ValueError("spacing_m must be positive and smoothing_half_window_m >= 0")
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._east_m: list[float] = []
        self._north_m: list[float] = []
        self._received = 0
        self._rejected = 0
        self._first_s: float | None = None
        self._last_s: float | None = None
        self._truncated = False

    @property
    def points_kept(self) -> int:
        return len(self._east_m)

    def update(self, east_m: float, north_m: float, now_s: float) -> bool:
        """Offer the position at ``now_s``; True when it was kept."""
        self._received += 1
        if not (math.isfinite(east_m) and math.isfinite(north_m) and math.isfinite(now_s)):
            self._rejected += 1
            return False
        if self._first_s is None:
            self._first_s = now_s
        self._last_s = now_s
        if self._east_m:
            step_m = math.hypot(east_m - self._east_m[-1], north_m - self._north_m[-1])
            if step_m < self.params.spacing_m:
                return False
            if len(self._east_m) >= self.params.max_points:
                self._truncated = True
                return False
        self._east_m.append(east_m)
        self._north_m.append(north_m)
        return True

    def finish(
        self, name: str, frame: LocalFrame, *, geodetic: bool = True, **properties: Any
    ) -> tuple[Route, RecordingSummary]:
        """The smoothed route in ``frame``'s metres, written as lon/lat (``geodetic``) or as
        local metres declaring ``frame``; ``properties`` are Route's (directions,
        speed_limit_mps, description, recorded, vehicle). RecordingError when fewer than 2
        points were kept; ValueError for a bad name or property."""
        if len(self._east_m) < 2:
            raise RecordingError(
                f"recorded {len(self._east_m)} point(s): drive at least "
                f"{self.params.spacing_m:g} m before finishing"
            )
        raw_m = np.column_stack((self._east_m, self._north_m))
        points_m = smooth_along_arc(raw_m, self.params.smoothing_half_window_m)
        route = Route.from_enu(name, points_m, frame, geodetic=geodetic, **properties)
        deltas = np.diff(points_m, axis=0)
        valid = self._received - self._rejected
        summary = RecordingSummary(
            name=name,
            length_m=float(np.sum(np.hypot(deltas[:, 0], deltas[:, 1]))),
            duration_s=(self._last_s or 0.0) - (self._first_s or 0.0),
            fixes_received=self._received,
            fixes_rejected=self._rejected,
            points_kept=len(points_m),
            points_dropped=valid - len(points_m),
            min_radius_m=min_radius_found_m(points_m, SUMMARY_CURVATURE_SPAN_M),
            truncated=self._truncated,
        )
        return route, summary
