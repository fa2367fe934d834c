"""Stanley et al.'s route planner: where on the route the array is, and which way to drive it.

The paper's steps, with what each is for:

* **Nearest point by a reduced-density bidirectional search** from the last-known closest
  point: every ``coarse_stride``-th vertex within ``search_window_m`` of arc length both
  ways, then a projection onto the segments of the groups that can still hold the
  nearest point (a vertex search would make the projection, and with it the look-ahead,
  step by a point spacing). The first update after a route or a ``reset()`` searches the
  whole route the same way.
* **A position-change threshold** where the path passes near itself (a crossing, a
  hairpin): the projection may not move along the route further than the vehicle can
  have driven since the last update (``max_speed_mps * dt + jump_margin_m``). A farther
  answer is refused, counted, and replaced by the nearest point within that reach, so
  driving through a crossing stays on the branch being driven.
* **Travel direction from Fig. 5**: the line normal to the path at the projection divides
  "facing along the route" from "facing against it"; the side the heading falls on is the
  direction the operator meant. It is latched for the run (a heading wobble at 90° must
  not reverse the route mid-way) until ``reset()`` or a new route.

Frames: the planner works in whatever frame the route and the anchor point share. With
the continually varying local frame (``appliance.localization.frame_blend``) the cheap
way is to keep the route in ENU and bring the anchor point and heading into ENU with the
applied transform's inverse (distances, cross-track and heading error are the same in
both frames; the path heading differs by the transform's yaw): the route, and all that
is prepared from it once (``travel_path``), then never moves.

Routes: consecutive duplicate points are removed here (``clean_route``); every index in
the output refers to ``RoutePlanner.route_m``, the cleaned route.

Pure: arrays in, frozen outputs out; time is an argument.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from appliance.guidance.path_geometry import PathProjection
from appliance.guidance.travel_path import TravelDirection, TravelPaths
from appliance.localization.compound import wrap_angle_rad

FloatArray = NDArray[np.float64]
AllowedDirections = Literal["forward", "reverse", "both"]
# Above this many coarse groups the coarse pass works on arrays: a long route's first
# search; the window around the last projection is a few dozen, done on floats.
_VECTOR_GROUPS = 64


@dataclass(frozen=True)
class PlannerParams:
    coarse_stride: int = 4  # the coarse pass looks at every this-many-th vertex
    search_window_m: float = 30.0  # arc length searched both ways from the last projection
    # The position-change threshold: the projection may move along the route at most
    # max_speed_mps * dt + jump_margin_m per update. The margin also covers the
    # projection running faster than the vehicle inside a curve (by 1 / (1 - κ d)).
    max_speed_mps: float = 10.0
    jump_margin_m: float = 1.0
    behind_m: float = (
        5.0  # the local path starts this far behind (the tracker looks back a wheelbase)
    )
    ahead_m: float = 30.0  # and reaches this far ahead (longer than any look-ahead)
    duplicate_tolerance_m: float = 1e-6  # consecutive points closer than this are one

    def __post_init__(self) -> None:
        if self.coarse_stride < 1:
            raise ValueError(f"coarse_stride must be at least 1, got {self.coarse_stride}")
        positive = {
            "search_window_m": self.search_window_m,
            "max_speed_mps": self.max_speed_mps,
            "behind_m": self.behind_m,
            "ahead_m": self.ahead_m,
            "duplicate_tolerance_m": self.duplicate_tolerance_m,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value}")
        if not (math.isfinite(self.jump_margin_m) and self.jump_margin_m >= 0.0):
            raise ValueError(f"jump_margin_m must be >= 0, got {self.jump_margin_m}")


@dataclass(frozen=True)
class PlannerOutput:
    """Where the anchor point projects onto the route, seen in the travel direction."""

    segment_index: int  # of the cleaned route: between vertices i and i + 1
    fraction: float  # 0..1 along that segment
    point_m: tuple[float, float]  # the projected point
    arc_length_m: float  # from the route's first point, in route order
    route_length_m: float
    direction: TravelDirection
    progress_m: float  # driven so far in the travel direction
    progress_fraction: float  # 0..1 in the travel direction
    remaining_m: float  # to the end in the travel direction
    cross_track_m: float  # lateral offset of the anchor, left of the travel direction > 0
    path_heading_rad: float  # the path's tangent at the projection, in the travel direction
    heading_error_rad: float  # vehicle heading minus path heading, wrapped to [-π, π)
    distance_to_route_m: float
    jump_refused: bool  # this update's window answer was a jump, and was refused
    jumps_refused: int  # refusals since the last reset
    # The route in travel order, and the local window's extent (behind_m, ahead_m): the
    # window is cut out of the route only when it is asked for.
    paths: TravelPaths = field(repr=False, compare=False)
    window_m: tuple[float, float] = field(repr=False, compare=False)

    @property
    def travel_projection(self) -> PathProjection:
        """The projection on ``paths.path(direction)``: what the tracker consumes."""
        return self.paths.projection(self.direction, self.progress_m)

    @cached_property
    def _local(self) -> tuple[FloatArray, int, float]:
        behind_m, ahead_m = self.window_m
        return self.paths.window(self.arc_length_m, self.direction, behind_m, ahead_m)

    @property
    def local_path_m(self) -> FloatArray:
        """The route from behind_m behind the projection to ahead_m ahead, in travel order
        (Fig. 6's local window)."""
        return self._local[0]

    @property
    def local_segment_index(self) -> int:
        """The projection's segment in ``local_path_m``."""
        return self._local[1]

    @property
    def local_fraction(self) -> float:
        return self._local[2]


@dataclass(frozen=True)
class PlannerRefusal:
    reason: str


def clean_route(points_m: ArrayLike, tolerance_m: float = 1e-6) -> FloatArray:
    """The route as (N, 2) float64 without consecutive duplicates; refuses what is no route."""
    route = np.asarray(points_m, dtype=np.float64)
    if route.ndim != 2 or route.shape[1] != 2:
        raise ValueError(f"a route is an (N, 2) array of points, got shape {route.shape}")
    if not np.all(np.isfinite(route)):
        raise ValueError("a route's points must be finite")
    if len(route) == 0:
        raise ValueError("a route needs at least two distinct points, got none")
    step = np.hypot(*np.diff(route, axis=0).T)
    keep = np.concatenate(([True], step >= tolerance_m))
    cleaned = route[keep]
    if len(cleaned) < 2:
        raise ValueError("a route needs at least two distinct points")
    return np.ascontiguousarray(cleaned)


class RoutePlanner:
    """Projects the anchor point onto one route; ``update`` once per control cycle."""

    def __init__(
        self,
        route_m: ArrayLike,
        params: PlannerParams | None = None,
        allowed: AllowedDirections = "both",
    ) -> None:
        self.params = params or PlannerParams()
        self.set_route(route_m, allowed)

    def set_route(self, route_m: ArrayLike, allowed: AllowedDirections = "both") -> None:
        """A new route: the next update searches all of it and decides the direction anew."""
        if allowed not in ("forward", "reverse", "both"):
            raise ValueError(f"allowed must be forward, reverse or both, got {allowed!r}")
        route = clean_route(route_m, self.params.duplicate_tolerance_m)
        route.flags.writeable = False
        self.route_m: FloatArray = route
        self.allowed: AllowedDirections = allowed
        d = np.diff(route, axis=0)
        self._x, self._y = route[:, 0].copy(), route[:, 1].copy()
        self._dx, self._dy = d[:, 0].copy(), d[:, 1].copy()
        self._len_sq = self._dx**2 + self._dy**2
        self._len = np.sqrt(self._len_sq)
        self._cum_s = np.concatenate(([0.0], np.cumsum(self._len)))
        self.route_length_m = float(self._cum_s[-1])
        # The coarse pass's vertices (every m-th) and the arc length each stands for
        # (the m segments after it).
        stride = self.params.coarse_stride
        starts = np.arange(0, len(d), stride)
        ends = np.minimum(starts + stride, len(d))
        self._coarse_x, self._coarse_y = route[starts, 0].copy(), route[starts, 1].copy()
        self._coarse_span = self._cum_s[ends] - self._cum_s[starts]
        self._coarse_xy_list: list[list[float]] = route[starts].tolist()
        self._coarse_span_list: list[float] = self._coarse_span.tolist()
        # Python lists for the scalar look-ups: a numpy scalar costs more than the sum.
        self._cum_list: list[float] = self._cum_s.tolist()
        self._len_list: list[float] = self._len.tolist()
        self._xy_list: list[list[float]] = route.tolist()
        self._d_list: list[list[float]] = d.tolist()
        self._len_sq_list: list[float] = self._len_sq.tolist()
        self.paths = TravelPaths(route, self._len, self._cum_s)
        self.reset()

    def reset(self) -> None:
        self._last_s: float | None = None
        self._last_time_s = 0.0
        self._direction: TravelDirection | None = None
        self._jumps_refused = 0

    @property
    def jumps_refused(self) -> int:
        return self._jumps_refused

    def update(
        self, point_m: Sequence[float] | FloatArray, heading_rad: float, now_s: float
    ) -> PlannerOutput | PlannerRefusal:
        """Project the anchor point (route frame) and say how it sits on the route."""
        if len(point_m) != 2:
            raise ValueError(f"the anchor point is (x_m, y_m), got {point_m!r}")
        px, py = float(point_m[0]), float(point_m[1])
        if not (math.isfinite(px) and math.isfinite(py)):
            return PlannerRefusal("anchor position not finite")
        if not (math.isfinite(heading_rad) and math.isfinite(now_s)):
            return PlannerRefusal("heading or time not finite")
        if self._last_s is not None and now_s < self._last_time_s:
            return PlannerRefusal("time went backwards")
        segment, fraction, jump_refused = self._search(px, py, now_s)
        s = self._cum_list[segment] + fraction * self._len_list[segment]
        tangent_x, tangent_y = self._tangent(segment, fraction)
        self._last_s, self._last_time_s = s, now_s
        if jump_refused:
            self._jumps_refused += 1

        direction = self._direction
        if direction is None:
            along = math.cos(heading_rad) * tangent_x + math.sin(heading_rad) * tangent_y
            direction = TravelDirection.FORWARD if along > 0.0 else TravelDirection.REVERSE
            if self.allowed not in ("both", direction.value):
                allowed_heading = _angle(tangent_x, tangent_y)
                if self.allowed == "reverse":
                    allowed_heading += math.pi
                facing = math.degrees(abs(wrap_angle_rad(heading_rad - allowed_heading)))
                return PlannerRefusal(
                    f"heading {facing:.0f}° from the route (it may be driven {self.allowed} only)"
                )
            self._direction = direction
        return self._output(px, py, heading_rad, segment, fraction, s, direction, jump_refused)

    # -- the search ---------------------------------------------------------------------

    def _search(self, px: float, py: float, now_s: float) -> tuple[int, float, bool]:
        """(segment, fraction, refused): the bounded search, then the jump threshold."""
        p = self.params
        reach_m = math.inf
        if self._last_s is None:
            lo_v, hi_v = 0, len(self._x) - 1
        else:
            reach_m = p.max_speed_mps * (now_s - self._last_time_s) + p.jump_margin_m
            window_m = max(p.search_window_m, reach_m)
            lo_v, hi_v = self._vertex_range(self._last_s - window_m, self._last_s + window_m)
        first, last = self._coarse(px, py, lo_v, hi_v)
        segment, fraction = self._project(px, py, first, last)
        if self._last_s is None:
            return segment, fraction, False
        s = self._cum_list[segment] + fraction * self._len_list[segment]
        if abs(s - self._last_s) <= reach_m:
            return segment, fraction, False
        s_min, s_max = self._last_s - reach_m, self._last_s + reach_m
        lo_v, hi_v = self._vertex_range(s_min, s_max)
        segment, fraction = self._project(px, py, lo_v, hi_v - 1, s_min, s_max)
        return segment, fraction, True

    def _coarse(self, px: float, py: float, lo_v: int, hi_v: int) -> tuple[int, int]:
        """The segments (first, last) that may hold the nearest point of those in the
        window lo_v..hi_v-1 (widened to whole groups), from every m-th vertex alone.

        Vertex v stands for the m segments after it: none of their points is nearer to
        the anchor than |p − v| less the arc length they span. Every group whose bound
        beats the nearest coarse vertex is kept and only those are projected onto: exact
        (a long segment whose middle is nearest is not missed), and reduced density.
        """
        stride = self.params.coarse_stride
        g_lo, g_hi = lo_v // stride, (hi_v - 1) // stride + 1
        if g_hi - g_lo > _VECTOR_GROUPS:  # the whole route (the first search): numpy
            distance = np.hypot(self._coarse_x[g_lo:g_hi] - px, self._coarse_y[g_lo:g_hi] - py)
            kept = np.flatnonzero(distance - self._coarse_span[g_lo:g_hi] <= distance.min())
            first_kept, last_kept = g_lo + int(kept[0]), g_lo + int(kept[-1])
        else:  # the window around the last projection, each cycle: Python floats
            coarse, span = self._coarse_xy_list, self._coarse_span_list
            distances = [math.hypot(x - px, y - py) for x, y in coarse[g_lo:g_hi]]
            nearest = min(distances)
            kept_groups = [
                g_lo + k for k, d in enumerate(distances) if d - span[g_lo + k] <= nearest
            ]
            first_kept, last_kept = kept_groups[0], kept_groups[-1]
        first = first_kept * stride
        last = min((last_kept + 1) * stride, len(self._dx)) - 1
        return first, last

    def _vertex_range(self, s_min: float, s_max: float) -> tuple[int, int]:
        """(lo, hi): segments lo..hi-1 cover arc lengths [s_min, s_max] (clipped to the route)."""
        last_vertex = len(self._x) - 1
        lo = min(max(bisect.bisect_right(self._cum_list, s_min) - 1, 0), last_vertex - 1)
        hi = min(max(bisect.bisect_left(self._cum_list, s_max), lo + 1), last_vertex)
        return lo, hi

    def _project(
        self,
        px: float,
        py: float,
        first: int,
        last: int,
        s_min: float = -math.inf,
        s_max: float = math.inf,
    ) -> tuple[int, float]:
        """The nearest point on segments first..last whose arc length is in [s_min, s_max].

        A loop over Python floats: the coarse pass leaves a few groups of segments, and
        on so few numpy's cost per call is most of the work."""
        xy, d, len_sq = self._xy_list, self._d_list, self._len_sq_list
        bounded = not (math.isinf(s_min) and math.isinf(s_max))
        best, best_t, best_d2 = first, 0.0, math.inf
        for i in range(first, last + 1):
            ax, ay = xy[i]
            dx, dy = d[i]
            t = ((px - ax) * dx + (py - ay) * dy) / len_sq[i]
            if bounded:
                s0, length = self._cum_list[i], self._len_list[i]
                t_lo = min(max((s_min - s0) / length, 0.0), 1.0)
                t_hi = min(max((s_max - s0) / length, 0.0), 1.0)
                t = min(max(t, t_lo), t_hi)
            else:
                t = 0.0 if t < 0.0 else 1.0 if t > 1.0 else t
            ex, ey = ax + t * dx - px, ay + t * dy - py
            d2 = ex * ex + ey * ey
            if d2 < best_d2:
                best, best_t, best_d2 = i, t, d2
        return best, best_t

    def _tangent(self, segment: int, fraction: float) -> tuple[float, float]:
        """The unit tangent in route order; at an inner vertex, the two segments' mean."""
        (dx, dy), length = self._d_list[segment], self._len_list[segment]
        tx, ty = dx / length, dy / length
        other = segment - 1 if fraction <= 0.0 else segment + 1 if fraction >= 1.0 else -1
        if 0 <= other < len(self._d_list):
            (ox, oy), other_length = self._d_list[other], self._len_list[other]
            mx, my = tx + ox / other_length, ty + oy / other_length
            norm = math.hypot(mx, my)
            if norm > 1e-9:  # a reversal has no mean direction: keep the segment's own
                return mx / norm, my / norm
        return tx, ty

    # -- the output ---------------------------------------------------------------------

    def _output(
        self,
        px: float,
        py: float,
        heading_rad: float,
        segment: int,
        fraction: float,
        s: float,
        direction: TravelDirection,
        jump_refused: bool,
    ) -> PlannerOutput:
        (ax, ay), (dx, dy) = self._xy_list[segment], self._d_list[segment]
        qx, qy = ax + fraction * dx, ay + fraction * dy
        tx, ty = self._tangent(segment, fraction)
        lateral_m = tx * (py - qy) - ty * (px - qx)  # left of the route order
        total = self.route_length_m
        if direction is TravelDirection.FORWARD:
            progress_m, sign = s, 1.0
        else:
            progress_m, sign, tx, ty = total - s, -1.0, -tx, -ty
        path_heading = _angle(tx, ty)
        return PlannerOutput(
            segment_index=segment,
            fraction=fraction,
            point_m=(qx, qy),
            arc_length_m=s,
            route_length_m=total,
            direction=direction,
            progress_m=progress_m,
            progress_fraction=progress_m / total,
            remaining_m=total - progress_m,
            cross_track_m=sign * lateral_m,
            path_heading_rad=path_heading,
            heading_error_rad=wrap_angle_rad(heading_rad - path_heading),
            distance_to_route_m=math.hypot(px - qx, py - qy),
            jump_refused=jump_refused,
            jumps_refused=self._jumps_refused,
            paths=self.paths,
            window_m=(self.params.behind_m, self.params.ahead_m),
        )


def _angle(x: float, y: float) -> float:
    return math.atan2(y, x)


def engagement_check(
    output: PlannerOutput | PlannerRefusal,
    max_distance_m: float = 10.0,
    max_heading_error_rad: float = math.radians(45.0),
) -> tuple[str, ...]:
    """Why the route may not be engaged now, in the operator's words; empty if it may."""
    if isinstance(output, PlannerRefusal):
        return (output.reason,)
    reasons: list[str] = []
    if output.distance_to_route_m > max_distance_m:
        reasons.append(f"{output.distance_to_route_m:.1f} m from route, limit {max_distance_m:g} m")
    if abs(output.heading_error_rad) > max_heading_error_rad:
        reasons.append(f"heading {math.degrees(abs(output.heading_error_rad)):.0f}° from the route")
    return tuple(reasons)
