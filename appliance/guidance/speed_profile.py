"""The target speed along the route ahead: the set speed, lowered where it has to be.

The operator's set speed (the cruise set point, Stanley et al.'s plus/minus buttons) is
what the vehicle drives at unless something ahead asks for less:

* the route's **speed limit**;
* **curvature**: on a curve of curvature κ the lateral acceleration v²·|κ| stays below
  ``lateral_accel_mps2``, so ``v ≤ v_curve = sqrt(a_lat / |κ|)`` there;
* the **end of the route**: the vehicle is to be stopped ``stop_margin_m`` before it.

A nine-ton truck cannot slow at once, so a limit ``d`` metres ahead is turned into a
limit now by a **braking curve** (``braking_curve_mps``): the speed from which, holding it
for the speed loop's response time ``t_r`` and then braking at the comfortable
``comfort_decel_mps2`` (a_dec), the vehicle arrives at the limit exactly there:
``v·t_r + (v² - v_f²) / (2·a_dec) = d``. With ``t_r = 0`` this is the textbook
``sqrt(v_f² + 2·a_dec·d)`` (and ``sqrt(2·a_dec·d)`` to a stop); the response time is
there because the pedal loop lags a falling target (its reference is jerk limited, the
throttle closes and the brake builds at bounded rates): in the closed loop on the
simulated Husky, t_r = 0 reached a 15 m arc at 4.35 m/s instead of 3.87 and stopped
0.1 m from the route's end, t_r = 1.5 s reaches the arc at 3.81 m/s and stops 0.5 m
before the end (the margin). Near the end the curve becomes ``v ≈ d / t_r``: a gentle
final approach instead of the square root's steep one. The curvature is looked at over
``preview_m`` ahead, which must cover the braking distance from the highest set speed
(``braking_distance_m``: 20 m plus 6.7 m of response from 10 mph; the preview is 40 m).

``target_speed_mps`` is that rule, pure. ``SpeedTarget`` adds what a rule over positions
cannot: a limit on how fast the target may rise and fall over *time*, so a set-speed
change or a speed limit does not arrive as a step. The fall limit is set above the
planning deceleration, so the braking curves above pass through it unchanged; anything
more urgent is a stop request to the pedal controller, not a target.

Defaults, for the Husky (tall, nine tons, an array on its nose): a_lat = 1.0 m/s² (0.1 g;
a tall truck's rollover threshold is around 0.4 g, and off road the slope and the bumps
take a share of it): a 15 m arc is taken at sqrt(15) = 3.9 m/s, a 20 m arc at 10 mph;
a_dec = 0.5 m/s², a gentle service brake (the pedal controller's comfortable stop is
0.8 m/s², so it can follow); target rises at 0.35 m/s² (what the engine gives at the
throttle limit) and falls at up to 0.8 m/s².

``path_curvature`` gives the signed curvature of a polyline from the circle through each
point and its neighbours (positive turning left, i.e. counter-clockwise in ENU).
``CurveSpeedTable`` is the curve rule for one route driven one way, with what depends
only on the route (each point's curve speed) worked out once: each cycle is then a table
search and a few array operations on the preview's points.
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass, fields
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

_DUPLICATE_M = 1e-6  # points closer than this are one point


class SpeedLimiter(StrEnum):
    """Which rule set the target (for status: why is it slower than I asked?)."""

    SET_SPEED = "set speed"
    SPEED_LIMIT = "speed limit"
    CURVE = "curve ahead"
    ROUTE_END = "end of route"


@dataclass(frozen=True)
class SpeedProfileParams:
    lateral_accel_mps2: float = 1.0
    comfort_decel_mps2: float = 0.5
    preview_m: float = 40.0
    stop_margin_m: float = 0.5
    response_time_s: float = 1.5
    target_rise_mps2: float = 0.35
    target_fall_mps2: float = 0.8
    max_step_dt_s: float = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            may_be_zero = f.name in ("stop_margin_m", "response_time_s")
            minimum_ok = value >= 0.0 if may_be_zero else value > 0.0
            if not (math.isfinite(value) and minimum_ok):
                raise ValueError(f"{f.name} must be finite and positive (got {value})")


def braking_distance_m(speed_mps: float, params: SpeedProfileParams) -> float:
    """How far it takes to lose ``speed_mps`` (response time, then the comfortable
    deceleration): the least preview that lets a curve's limit be met in time."""
    return speed_mps * params.response_time_s + speed_mps**2 / (2.0 * params.comfort_decel_mps2)


def braking_curve_mps(
    final_mps: FloatArray, distance_m: FloatArray, params: SpeedProfileParams
) -> FloatArray:
    """The speed now from which ``final_mps`` is reached ``distance_m`` ahead: holding the
    speed for the response time ``t_r``, then braking at ``a`` (comfortable), i.e. the
    root of ``v·t_r + (v² - v_f²) / (2a) = d``, and never below ``v_f`` itself.
    With ``t_r = 0`` it is the plain ``sqrt(v_f² + 2·a·d)``."""
    a_mps2 = params.comfort_decel_mps2
    lag_mps = a_mps2 * params.response_time_s
    now_mps = -lag_mps + np.sqrt(lag_mps**2 + final_mps**2 + 2.0 * a_mps2 * distance_m)
    result: FloatArray = np.maximum(now_mps, final_mps)
    return result


def path_curvature(points_m: ArrayLike) -> FloatArray:
    """Signed curvature (1/m) at each point of an (N, 2) polyline, from the circle through
    the point and its neighbours: ``κ = 2·(a × b) / (|a|·|b|·|a + b|)`` with ``a``, ``b``
    the segments before and after. Repeated points (a recorder standing still) are merged
    first and get their representative's value; the two ends take their neighbour's value
    (a circle needs three points); a path reversing on itself gets the tightest circle
    through the three points, ``2/|a|``. Fewer than three distinct points: zeros."""
    points = np.asarray(points_m, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 2:
        raise ValueError(f"points_m must have shape (N, 2), got {points.shape}")
    if not np.all(np.isfinite(points)):
        raise ValueError("points_m must be finite")
    n = len(points)
    if n == 0:
        return np.zeros(0)
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    new_point = np.concatenate(([True], step > _DUPLICATE_M))
    representative = np.cumsum(new_point) - 1  # index into the distinct points
    distinct = points[new_point]
    if len(distinct) < 3:
        return np.zeros(n)
    before = distinct[1:-1] - distinct[:-2]
    after = distinct[2:] - distinct[1:-1]
    cross = before[:, 0] * after[:, 1] - before[:, 1] * after[:, 0]
    len_before = np.linalg.norm(before, axis=1)
    len_after = np.linalg.norm(after, axis=1)
    chord = np.linalg.norm(before + after, axis=1)
    reversing = chord <= _DUPLICATE_M
    safe_chord = np.where(reversing, 1.0, chord)
    inner = 2.0 * cross / (len_before * len_after * safe_chord)
    inner = np.where(reversing, 2.0 / np.minimum(len_before, len_after), inner)
    kappa = np.concatenate(([inner[0]], inner, [inner[-1]]))
    result: FloatArray = kappa[representative]
    return result


def curvature_preview(
    points_m: ArrayLike, along_m: float, preview_m: float, curvature_1pm: ArrayLike | None = None
) -> FloatArray:
    """(distance_m, curvature_1pm) rows for the route from ``along_m`` (arc length of the
    vehicle's projection) to ``preview_m`` beyond it. The last point at or behind the
    vehicle is included at distance 0: the vehicle is on the segment that leaves it."""
    points = np.asarray(points_m, dtype=np.float64)
    kappa = (
        path_curvature(points)
        if curvature_1pm is None
        else np.asarray(curvature_1pm, dtype=np.float64)
    )
    if kappa.shape != (len(points),):
        raise ValueError("curvature_1pm must have one value per point")
    if not (math.isfinite(along_m) and math.isfinite(preview_m) and preview_m >= 0.0):
        raise ValueError("along_m and preview_m must be finite, preview_m not negative")
    if len(points) == 0:
        return np.zeros((0, 2))
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))))
    distance = arc - along_m
    ahead = (distance > 0.0) & (distance <= preview_m)
    behind = np.flatnonzero(distance <= 0.0)
    if len(behind):
        ahead[behind[-1]] = True
    return np.column_stack((np.maximum(distance[ahead], 0.0), kappa[ahead]))


def curve_speed_limit_mps(curvature: ArrayLike, params: SpeedProfileParams) -> float:
    """The highest speed now from which every curve in the preview is reached at no more
    than its lateral-acceleration speed, along the braking curve. ``inf``: no curve."""
    rows = np.asarray(curvature, dtype=np.float64)
    if rows.size == 0:
        return math.inf
    if rows.ndim != 2 or rows.shape[1] != 2:
        raise ValueError(f"curvature_ahead must have shape (M, 2), got {rows.shape}")
    if not np.all(np.isfinite(rows)):
        raise ValueError("curvature_ahead must be finite")
    distance = np.maximum(rows[:, 0], 0.0)
    in_view = distance <= params.preview_m
    kappa = np.abs(rows[in_view, 1])
    curved = kappa > 0.0
    if not np.any(curved):
        return math.inf
    with np.errstate(over="ignore"):  # a curvature so slight its speed overflows: straight
        curve_mps = np.sqrt(params.lateral_accel_mps2 / kappa[curved])
    allowed = braking_curve_mps(curve_mps, distance[in_view][curved], params)
    return float(np.min(allowed))


class CurveSpeedTable:
    """``curve_speed_limit_mps`` of the rows ``curvature_preview`` gives, for one path
    (arc length and curvature at each point) and one set of parameters.

    Each point's curve speed does not depend on where the vehicle is, so it is worked
    out once; a cycle finds the preview's points by the arc length and applies the
    braking curve to them alone. A different path or parameters is a different table.
    """

    def __init__(
        self, arc_m: ArrayLike, curvature_1pm: ArrayLike, params: SpeedProfileParams
    ) -> None:
        arc = np.asarray(arc_m, dtype=np.float64)
        kappa = np.abs(np.asarray(curvature_1pm, dtype=np.float64))
        if arc.ndim != 1 or kappa.shape != arc.shape or len(arc) == 0:
            raise ValueError("arc_m and curvature_1pm must be one value per point, not empty")
        if not (np.all(np.isfinite(arc)) and np.all(np.isfinite(kappa))):
            raise ValueError("arc_m and curvature_1pm must be finite")
        if np.any(np.diff(arc) < 0.0):
            raise ValueError("arc_m must not decrease")
        self.params = params
        self._arc = arc
        self._arc_list: list[float] = arc.tolist()
        curved = kappa > 0.0
        curve_mps = np.full_like(kappa, math.inf)
        with np.errstate(over="ignore"):  # so slight its speed overflows: straight
            curve_mps[curved] = np.sqrt(params.lateral_accel_mps2 / kappa[curved])
        self._curve_mps = curve_mps
        self._lag_mps = params.comfort_decel_mps2 * params.response_time_s
        # braking_curve_mps's terms that do not depend on the distance (inf: straight)
        with np.errstate(over="ignore"):
            self._root_base = self._lag_mps**2 + curve_mps**2
        self._two_a_mps2 = 2.0 * params.comfort_decel_mps2

    def limit_mps(self, along_m: float) -> float:
        """The curve limit for a vehicle ``along_m`` along the path. ``inf``: no curve."""
        if not math.isfinite(along_m):
            raise ValueError("along_m must be finite")
        arc, preview_m = self._arc_list, self.params.preview_m
        first = max(bisect.bisect_right(arc, along_m) - 1, 0)
        last = bisect.bisect_right(arc, along_m + preview_m)
        while last > first and arc[last - 1] - along_m > preview_m:
            last -= 1  # rounding: in view means no more than preview_m ahead
        if last <= first:
            return math.inf
        distance = np.maximum(self._arc[first:last] - along_m, 0.0)
        now_mps = -self._lag_mps + np.sqrt(
            self._root_base[first:last] + self._two_a_mps2 * distance
        )
        return float(np.min(np.maximum(now_mps, self._curve_mps[first:last])))


def route_end_speed_limit_mps(remaining_m: float, params: SpeedProfileParams) -> float:
    """The braking curve that ends at zero ``stop_margin_m`` before the route's end."""
    if math.isnan(remaining_m):
        raise ValueError("remaining_m must not be NaN")
    to_stop_m = max(remaining_m - params.stop_margin_m, 0.0)
    # braking_curve_mps to a stop, on floats (one value: numpy would cost more than it)
    a_mps2 = params.comfort_decel_mps2
    lag_mps = a_mps2 * params.response_time_s
    return max(-lag_mps + math.sqrt(lag_mps**2 + 2.0 * a_mps2 * to_stop_m), 0.0)


def target_with_reason(
    set_speed_mps: float,
    speed_limit_mps: float | None,
    curvature_ahead: ArrayLike,
    remaining_m: float | None,
    params: SpeedProfileParams,
) -> tuple[float, SpeedLimiter]:
    """The target speed and the rule that set it. ``remaining_m=None``: no end in view
    (a loop). Negative speeds mean zero: reversing is not decided here."""
    _check_speeds(set_speed_mps, speed_limit_mps)
    curve_mps = curve_speed_limit_mps(curvature_ahead, params)
    return lowest_target(set_speed_mps, speed_limit_mps, curve_mps, remaining_m, params)


def _check_speeds(set_speed_mps: float, speed_limit_mps: float | None) -> None:
    limit_ok = speed_limit_mps is None or math.isfinite(speed_limit_mps)
    if not (math.isfinite(set_speed_mps) and limit_ok):
        raise ValueError("set_speed_mps and speed_limit_mps must be finite")


def lowest_target(
    set_speed_mps: float,
    speed_limit_mps: float | None,
    curve_limit_mps: float,
    remaining_m: float | None,
    params: SpeedProfileParams,
) -> tuple[float, SpeedLimiter]:
    """``target_with_reason`` with the curve rule's answer given (``curve_speed_limit_mps``
    or a ``CurveSpeedTable``'s)."""
    _check_speeds(set_speed_mps, speed_limit_mps)
    candidates = [(max(set_speed_mps, 0.0), SpeedLimiter.SET_SPEED)]
    if speed_limit_mps is not None:
        candidates.append((max(speed_limit_mps, 0.0), SpeedLimiter.SPEED_LIMIT))
    candidates.append((curve_limit_mps, SpeedLimiter.CURVE))
    if remaining_m is not None:
        candidates.append((route_end_speed_limit_mps(remaining_m, params), SpeedLimiter.ROUTE_END))
    return min(candidates, key=lambda c: c[0])  # the first wins a tie


def target_speed_mps(
    set_speed_mps: float,
    speed_limit_mps: float | None,
    curvature_ahead: ArrayLike,
    remaining_m: float | None,
    params: SpeedProfileParams,
) -> float:
    """The target speed at this point of the route (see the module)."""
    speed, _ = target_with_reason(
        set_speed_mps, speed_limit_mps, curvature_ahead, remaining_m, params
    )
    return speed


class SpeedTarget:
    """``target_speed_mps`` with the target's rise and fall limited over time."""

    def __init__(self, params: SpeedProfileParams | None = None) -> None:
        self.params = params if params is not None else SpeedProfileParams()
        self.reset()

    def reset(self, speed_mps: float = 0.0) -> None:
        """Start from ``speed_mps`` (the vehicle's speed at engagement: no jump)."""
        self._target_mps = max(speed_mps, 0.0) if math.isfinite(speed_mps) else 0.0
        self._last_now_s: float | None = None
        self.limited_by = SpeedLimiter.SET_SPEED
        self.unlimited_mps = self._target_mps

    def update(
        self,
        set_speed_mps: float,
        speed_limit_mps: float | None,
        curvature_ahead: ArrayLike,
        remaining_m: float | None,
        now_s: float,
    ) -> float:
        wanted = target_with_reason(
            set_speed_mps, speed_limit_mps, curvature_ahead, remaining_m, self.params
        )
        return self._follow(wanted, now_s)

    def update_with_curve_limit(
        self,
        set_speed_mps: float,
        speed_limit_mps: float | None,
        curve_limit_mps: float,
        remaining_m: float | None,
        now_s: float,
    ) -> float:
        """``update`` with the curve rule's answer given (a ``CurveSpeedTable``'s)."""
        wanted = lowest_target(
            set_speed_mps, speed_limit_mps, curve_limit_mps, remaining_m, self.params
        )
        return self._follow(wanted, now_s)

    def _follow(self, wanted: tuple[float, SpeedLimiter], now_s: float) -> float:
        """The target moved towards ``wanted`` within its rise and fall limits."""
        p = self.params
        self.unlimited_mps, self.limited_by = wanted
        if not math.isfinite(now_s):
            raise ValueError("now_s must be finite")
        last, self._last_now_s = self._last_now_s, now_s
        dt_s = 0.0 if last is None else min(max(now_s - last, 0.0), p.max_step_dt_s)
        change = min(
            max(self.unlimited_mps - self._target_mps, -p.target_fall_mps2 * dt_s),
            p.target_rise_mps2 * dt_s,
        )
        self._target_mps += change
        return self._target_mps
