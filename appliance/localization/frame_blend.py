"""Stanley et al.'s continually varying local frame (Fig. 11): the vehicle smooth, the path moving.

A globally referenced path followed with GNSS fixes jumps with every jump of the fix (the
Husky's threshold switching between LGPR and GPS moved it by 0.3 m), and a jump of the
path under a pure pursuit tracker is a jerk of the wheel. So the tracker works in a
local frame in which the vehicle's pose is dead-reckoned (``DeadReckoning``, smooth by
construction), and the route is brought into it by a transform T (local ← global) that
is estimated slowly and applied smoothly (``LocalGlobalTransform``):

* **Estimate** (every ``estimate_period_s``, 0.5 Hz in the paper): a weighted least
  squares fit (weights 1/σ²) over the fix/odometry pairs of the last ``window_s``, so
  white fix noise averages out instead of wiggling the path. The rotation is the
  difference between the dead-reckoned heading and the receiver's true heading (the
  INS's HDT/THS), not the track's direction, so it is known standing still. Odometry
  drifts, so each component is fitted as a line in time (a zero-mean prior on the rate
  keeps noise from posing as drift) and evaluated at the newest pair, then extrapolated:
  the estimate moves with the drift instead of lagging half a window behind it. A gyro
  bias turns the local frame about its origin; the translation that turn causes is
  integrated along the fixes and taken out, so it needs no translation rate at all.
  What a rigid transform cannot absorb is a speed scale error on curves (the local
  track is then a scaled copy): dead-reckon from the INS's speed, or calibrate it.
  A new estimate is faded in over ``blend_s`` (its drift at once, its offset
  gradually), so estimate-to-estimate noise moves the path by millimetres per second
  rather than in steps.
* **Gate**: a fix farther from the prediction than ``gate_sigma`` σ (or with a heading
  off by more than ``heading_gate_rad``) is not taken. One such fix is dropped; when
  ``jump_persist_fixes`` in a row agree with each other, the fix has jumped for real and
  the estimate follows at once: the pairs after the jump get their own offset in the fit
  (the drift rate stays fitted over all pairs), so the old pairs neither pull the new
  estimate back nor are lost for the drift.
* **Apply**: the transform the tracker sees moves towards the estimate at most
  ``max_translation_rate_mps`` at the vehicle and ``max_rotation_rate_rps`` (rotating
  about the vehicle, not about the far-away ENU origin), so a step in the estimate becomes
  a ramp: the path near the vehicle moves no faster than v + ω r.

Pure: no I/O; time is an argument; ``current(now_s)`` advances the ramp to ``now_s``.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from appliance.localization.compound import wrap_angle_rad
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]
_ORIGIN = Pose2D(0.0, 0.0, 0.0)


@dataclass(frozen=True)
class DeadReckoningParams:
    history_s: float = 2.0  # how far back ``pose_at`` reaches: the fix latency and then some


class DeadReckoning:
    """The vehicle in the local frame, integrated from speed and heading or yaw rate.

    Each step moves along the arc of constant curvature joining the two samples (speed
    and yaw rate averaged over the step): exact for a constant turn, and continuous
    whatever the inputs, which is all the local frame must be.
    """

    def __init__(self, params: DeadReckoningParams | None = None) -> None:
        self.params = params or DeadReckoningParams()
        self.reset()

    def reset(self, pose: Pose2D = _ORIGIN) -> None:
        self._x_m, self._y_m, self._yaw_rad = pose.x_m, pose.y_m, pose.yaw_rad
        self._time_s: float | None = None
        self._speed_mps = 0.0
        self._yaw_rate_rps = 0.0
        self._times_s: list[float] = []
        self._poses: list[tuple[float, float, float]] = []  # yaw unwrapped, for interpolation

    @property
    def pose(self) -> Pose2D:
        return Pose2D(self._x_m, self._y_m, wrap_angle_rad(self._yaw_rad))

    def update(
        self,
        speed_mps: float,
        now_s: float,
        *,
        heading_rad: float | None = None,
        yaw_rate_rps: float | None = None,
    ) -> Pose2D:
        """Advance to ``now_s``; give exactly one of ``heading_rad`` and ``yaw_rate_rps``."""
        if (heading_rad is None) == (yaw_rate_rps is None):
            raise ValueError("give exactly one of heading_rad and yaw_rate_rps")
        turn = heading_rad if heading_rad is not None else yaw_rate_rps
        assert turn is not None
        if not all(math.isfinite(v) for v in (speed_mps, now_s, turn)):
            raise ValueError("dead reckoning needs finite speed, time and heading")
        if self._time_s is None:
            if heading_rad is not None:
                self._yaw_rad = heading_rad
        else:
            dt_s = now_s - self._time_s
            if dt_s < 0.0:
                raise ValueError(f"time went backwards by {-dt_s} s")
            if heading_rad is not None:
                delta_rad = wrap_angle_rad(heading_rad - self._yaw_rad)
            else:
                assert yaw_rate_rps is not None
                delta_rad = 0.5 * (self._yaw_rate_rps + yaw_rate_rps) * dt_s
            distance_m = 0.5 * (self._speed_mps + speed_mps) * dt_s
            half = 0.5 * delta_rad
            chord_m = distance_m * (math.sin(half) / half if abs(half) > 1e-9 else 1.0)
            self._x_m += chord_m * math.cos(self._yaw_rad + half)
            self._y_m += chord_m * math.sin(self._yaw_rad + half)
            self._yaw_rad += delta_rad
        self._time_s, self._speed_mps = now_s, speed_mps
        if yaw_rate_rps is not None:
            self._yaw_rate_rps = yaw_rate_rps
        self._remember(now_s)
        return self.pose

    def _remember(self, now_s: float) -> None:
        self._times_s.append(now_s)
        self._poses.append((self._x_m, self._y_m, self._yaw_rad))
        cut = bisect.bisect_left(self._times_s, now_s - self.params.history_s)
        if cut > 1:  # keep one sample at or before the cut, to interpolate from
            del self._times_s[: cut - 1], self._poses[: cut - 1]

    def pose_at(self, time_s: float) -> Pose2D | None:
        """The pose at a past time (a fix's measurement time); None outside the history."""
        if not self._times_s or not self._times_s[0] <= time_s <= self._times_s[-1]:
            return None
        i = bisect.bisect_left(self._times_s, time_s)
        if self._times_s[i] == time_s:
            x, y, yaw = self._poses[i]
            return Pose2D(x, y, wrap_angle_rad(yaw))
        t0, t1 = self._times_s[i - 1], self._times_s[i]
        f = (time_s - t0) / (t1 - t0)
        (x0, y0, a0), (x1, y1, a1) = self._poses[i - 1], self._poses[i]
        return Pose2D(x0 + f * (x1 - x0), y0 + f * (y1 - y0), wrap_angle_rad(a0 + f * (a1 - a0)))


@dataclass(frozen=True)
class FrameBlendParams:
    estimate_period_s: float = 2.0  # the paper's 0.5 Hz route conversion
    blend_s: float = 2.0  # a new estimate is faded in over this long
    window_s: float = 20.0
    max_pairs: int = 2000
    # Odometry's drift as priors on the fitted rates (zero mean): what a window of white
    # fix noise may not talk the estimate into. The heading's noise weighs the yaw fit.
    heading_sigma_rad: float = math.radians(0.2)
    yaw_drift_prior_rps: float = math.radians(0.1)
    translation_drift_prior_mps: float = 0.02
    max_extrapolation_s: float = 10.0  # without fixes, the drift is extrapolated this far
    max_translation_rate_mps: float = 0.2
    max_rotation_rate_rps: float = math.radians(1.0)
    gate_sigma: float = 4.0
    sigma_floor_m: float = 0.02  # a fix claiming σ = 0 is weighted and gated as this
    heading_gate_rad: float = math.radians(3.0)
    jump_persist_fixes: int = 3

    def __post_init__(self) -> None:
        for name in (
            "estimate_period_s",
            "blend_s",
            "window_s",
            "heading_sigma_rad",
            "yaw_drift_prior_rps",
            "translation_drift_prior_mps",
            "max_translation_rate_mps",
            "max_rotation_rate_rps",
            "gate_sigma",
            "sigma_floor_m",
            "heading_gate_rad",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value}")
        if self.max_pairs < 2 or self.jump_persist_fixes < 1 or self.max_extrapolation_s < 0:
            raise ValueError("max_pairs >= 2, jump_persist_fixes >= 1, max_extrapolation_s >= 0")


class FixVerdict(StrEnum):
    ACCEPTED = "accepted"
    OUTLIER = "outlier"  # beyond the gate: held back, not (yet) followed
    JUMP_FOLLOWED = "jump_followed"  # the last fixes agreed on a new place: re-anchored
    OUT_OF_ORDER = "out_of_order"  # older than the newest fix taken: ignored


@dataclass(frozen=True)
class _Pair:
    time_s: float
    global_xy: tuple[float, float]
    local_xy: tuple[float, float]
    yaw_diff_rad: float  # local heading minus global heading
    weight: float  # 1 / σ²
    segment: int  # which offset it shares: incremented at each followed jump


@dataclass(frozen=True)
class _Estimate:
    """T at ``time_s`` as the local position of the global point ``centre``, with rates."""

    time_s: float
    yaw_rad: float
    yaw_rate_rps: float
    centre: tuple[float, float]  # global
    centre_local: tuple[float, float]
    centre_velocity_mps: tuple[float, float]


class LocalGlobalTransform:
    """T (local ← global) as a ``Pose2D``: ``T.apply(*p_global) == p_local``."""

    def __init__(self, params: FrameBlendParams | None = None) -> None:
        self.params = params or FrameBlendParams()
        self.reset()

    def reset(self) -> None:
        self._pairs: deque[_Pair] = deque(maxlen=self.params.max_pairs)
        self._candidates: list[_Pair] = []
        self._segment = 0
        self._estimate: _Estimate | None = None
        self._estimated_at_s = -math.inf
        # The last estimate less the new, as a turn about the vehicle and a shift of it:
        # (turn_rad, pivot_x_m, pivot_y_m, shift_x_m, shift_y_m), faded out over blend_s.
        self._blend = (0.0, 0.0, 0.0, 0.0, 0.0)
        self._applied: tuple[float, float, float] = (0.0, 0.0, 0.0)  # yaw, tx, ty
        self._applied_at_s = -math.inf
        self._pivot = (0.0, 0.0)  # local: the vehicle at the newest fix
        self._last_fix_s = -math.inf
        self.outliers = 0  # fixes beyond the gate, whether later followed or not
        self.jumps_followed = 0

    @property
    def ready(self) -> bool:
        return self._estimate is not None

    def update_fix(
        self, global_pose: Pose2D, sigma_m: float, local_pose_at_fix: Pose2D, now_s: float
    ) -> FixVerdict:
        """One fix (ENU pose, its σ) with the dead-reckoned pose at its measurement time."""
        values = (*global_pose, *local_pose_at_fix, sigma_m, now_s)
        if not all(math.isfinite(v) for v in values) or sigma_m < 0.0:
            raise ValueError(f"a fix needs finite poses, time and σ >= 0, got {values}")
        if now_s < self._last_fix_s:
            return FixVerdict.OUT_OF_ORDER
        self._last_fix_s = now_s
        sigma = max(sigma_m, self.params.sigma_floor_m)
        pair = _Pair(
            now_s,
            (global_pose.x_m, global_pose.y_m),
            (local_pose_at_fix.x_m, local_pose_at_fix.y_m),
            wrap_angle_rad(local_pose_at_fix.yaw_rad - global_pose.yaw_rad),
            1.0 / sigma**2,
            self._segment,
        )
        self._pivot = pair.local_xy
        if self._estimate is None:
            self._take(pair)
            self._fit(now_s)
            self._applied, self._applied_at_s = self._target(now_s), now_s
            return FixVerdict.ACCEPTED
        offset, yaw_off = self._residual(pair, now_s)
        if math.hypot(*offset) <= self.params.gate_sigma * sigma and (
            abs(yaw_off) <= self.params.heading_gate_rad
        ):
            self._candidates.clear()
            self._take(pair)
            if now_s >= self._estimated_at_s + self.params.estimate_period_s:
                self._fit(now_s)
            return FixVerdict.ACCEPTED
        self.outliers += 1
        self._candidates.append(pair)
        if len(self._candidates) < self.params.jump_persist_fixes:
            return FixVerdict.OUTLIER
        if not self._candidates_agree():
            self._candidates.pop(0)
            return FixVerdict.OUTLIER
        self._segment += 1
        for candidate in self._candidates:
            self._take(replace(candidate, segment=self._segment))
        self._candidates.clear()
        self.jumps_followed += 1
        self._fit(now_s)
        return FixVerdict.JUMP_FOLLOWED

    def _take(self, pair: _Pair) -> None:
        self._pairs.append(pair)
        while self._pairs[0].time_s < pair.time_s - self.params.window_s:
            self._pairs.popleft()

    def _residual(self, pair: _Pair, time_s: float) -> tuple[tuple[float, float], float]:
        """Where the estimate puts the fix, less where odometry says it was (local frame)."""
        yaw, tx, ty = self._goal(time_s)
        c, s = math.cos(yaw), math.sin(yaw)
        gx, gy = pair.global_xy
        lx, ly = pair.local_xy
        offset = (c * gx - s * gy + tx - lx, s * gx + c * gy + ty - ly)
        return offset, wrap_angle_rad(pair.yaw_diff_rad - yaw)

    def _candidates_agree(self) -> bool:
        residuals = [self._residual(c, c.time_s) for c in self._candidates]
        offsets = np.array([r[0] for r in residuals])
        yaws = np.array([r[1] for r in residuals])
        spread = np.hypot(*(offsets - offsets.mean(axis=0)).T)
        gates = [self.params.gate_sigma / math.sqrt(c.weight) for c in self._candidates]
        return bool(
            np.all(spread <= gates)
            and np.all(np.abs(yaws - yaws.mean()) <= self.params.heading_gate_rad)
        )

    # -- the estimate -------------------------------------------------------------------

    def _fit(self, now_s: float) -> None:
        """Lines in time, one offset per segment and one drift rate, at the newest pair."""
        p = self.params
        pairs = list(self._pairs)
        t_ref = pairs[-1].time_s
        tau = np.array([q.time_s - t_ref for q in pairs])
        w = np.array([q.weight for q in pairs])
        seg = np.unique([q.segment for q in pairs], return_inverse=True)[1].reshape(-1)
        ref = pairs[-1].yaw_diff_rad
        yaw = np.array([ref + wrap_angle_rad(q.yaw_diff_rad - ref) for q in pairs])
        yaw_w = w / (w.mean() * p.heading_sigma_rad**2)
        yaw_rate = _shared_rate(tau, yaw, yaw_w, seg, p.yaw_drift_prior_rps)
        yaw_i = _offsets(tau, yaw, yaw_w, seg, yaw_rate)[seg] + yaw_rate * tau
        # Each pair's word on where the newest fix's global point is in the local frame
        # at t_ref. A yaw drift turns the local frame about its origin, which moves that
        # point by yaw_rate × J R (g − g_ref) per second: integrated along the fixes, so
        # a gyro bias is no translation drift and the rate below is odometry's own.
        g = np.array([q.global_xy for q in pairs])
        centre = g[-1]
        rel = g - centre
        cos, sin = np.cos(yaw_i), np.sin(yaw_i)
        turned = np.column_stack(
            [cos * rel[:, 0] - sin * rel[:, 1], sin * rel[:, 0] + cos * rel[:, 1]]
        )
        swept = _integral_to_end(tau, np.column_stack([-turned[:, 1], turned[:, 0]]))
        m = np.array([q.local_xy for q in pairs]) - turned - yaw_rate * swept
        prior = p.translation_drift_prior_mps
        velocity = (
            _shared_rate(tau, m[:, 0], w, seg, prior),
            _shared_rate(tau, m[:, 1], w, seg, prior),
        )
        before = self._target(now_s) if self._estimate is not None else None
        self._estimate = _Estimate(
            t_ref,
            float(yaw_i[-1]),
            float(yaw_rate),
            (float(centre[0]), float(centre[1])),
            (
                float(_offsets(tau, m[:, 0], w, seg, velocity[0])[-1]),
                float(_offsets(tau, m[:, 1], w, seg, velocity[1])[-1]),
            ),
            velocity,
        )
        self._estimated_at_s = now_s
        if before is not None:
            # the fade: the old less the new, as a turn about the vehicle and a shift of it
            new_yaw, tx, ty = _extrapolated(self._estimate, now_s - t_ref)
            qx, qy = self._pivot
            c, s = math.cos(new_yaw), math.sin(new_yaw)
            gx, gy = c * (qx - tx) + s * (qy - ty), -s * (qx - tx) + c * (qy - ty)
            c, s = math.cos(before[0]), math.sin(before[0])
            shift = (c * gx - s * gy + before[1] - qx, s * gx + c * gy + before[2] - qy)
            self._blend = (wrap_angle_rad(before[0] - new_yaw), qx, qy, *shift)

    def _goal(self, time_s: float) -> tuple[float, float, float]:
        """The newest estimate at ``time_s``, carried on by its drift: (yaw, tx, ty)."""
        e = self._estimate
        assert e is not None
        return _extrapolated(e, min(time_s - e.time_s, self.params.max_extrapolation_s))

    def _target(self, time_s: float) -> tuple[float, float, float]:
        """The estimate at ``time_s`` as (yaw, tx, ty): cross-faded from where the last
        one stood when it came, so even a new estimate moves the path gradually."""
        goal = self._goal(time_s)
        keep = 1.0 - (time_s - self._estimated_at_s) / self.params.blend_s
        if keep <= 0.0:
            return goal
        keep = min(keep, 1.0)  # the drift goes on with the new rates; the old offset fades
        turn, qx, qy, shift_x, shift_y = self._blend
        yaw, tx, ty = goal
        c, s = math.cos(keep * turn), math.sin(keep * turn)
        return (
            yaw + keep * turn,
            qx + c * (tx - qx) - s * (ty - qy) + keep * shift_x,
            qy + s * (tx - qx) + c * (ty - qy) + keep * shift_y,
        )

    def estimate(self, now_s: float) -> Pose2D:
        """The newest estimate itself, neither faded in nor ramped: what ``current`` is
        heading for (and what the gate measures fixes against)."""
        if self._estimate is None:
            raise RuntimeError("no fix yet: the local↔global transform is unknown")
        yaw, tx, ty = self._goal(now_s)
        return Pose2D(tx, ty, wrap_angle_rad(yaw))

    # -- the applied transform ----------------------------------------------------------

    def current(self, now_s: float) -> Pose2D:
        """The transform the tracker uses at ``now_s``: the estimate, reached by ramps."""
        if self._estimate is None:
            raise RuntimeError("no fix yet: the local↔global transform is unknown")
        dt_s = now_s - self._applied_at_s
        if dt_s > 0.0:
            self._applied = self._ramp(dt_s, self._target(now_s))
            self._applied_at_s = now_s
        yaw, tx, ty = self._applied
        return Pose2D(tx, ty, wrap_angle_rad(yaw))

    def _ramp(self, dt_s: float, target: tuple[float, float, float]) -> tuple[float, float, float]:
        """One bounded step: rotate about the vehicle (the pivot stays put), then shift it."""
        yaw, tx, ty = self._applied
        goal_yaw, goal_tx, goal_ty = target
        qx, qy = self._pivot
        limit = self.params.max_rotation_rate_rps * dt_s
        turn = min(max(wrap_angle_rad(goal_yaw - yaw), -limit), limit)
        c, s = math.cos(turn), math.sin(turn)
        tx, ty = qx + c * (tx - qx) - s * (ty - qy), qy + s * (tx - qx) + c * (ty - qy)
        yaw += turn
        # the global point now at the pivot, and where the estimate puts it
        c, s = math.cos(yaw), math.sin(yaw)
        gx, gy = c * (qx - tx) + s * (qy - ty), -s * (qx - tx) + c * (qy - ty)
        c, s = math.cos(goal_yaw), math.sin(goal_yaw)
        ex, ey = c * gx - s * gy + goal_tx - qx, s * gx + c * gy + goal_ty - qy
        step_m = math.hypot(ex, ey)
        limit = self.params.max_translation_rate_mps * dt_s
        if step_m > limit:
            ex, ey = ex * limit / step_m, ey * limit / step_m
        return yaw, tx + ex, ty + ey

    def to_local(self, points_global_m: ArrayLike, now_s: float) -> FloatArray:
        """(N, 2) ENU points in the local frame (the route, as the tracker sees it)."""
        t = self.current(now_s)
        p = _points(points_global_m)
        c, s = math.cos(t.yaw_rad), math.sin(t.yaw_rad)
        return np.column_stack(
            [c * p[:, 0] - s * p[:, 1] + t.x_m, s * p[:, 0] + c * p[:, 1] + t.y_m]
        )

    def to_global(self, points_local_m: ArrayLike, now_s: float) -> FloatArray:
        """(N, 2) local points in ENU: ``to_local``'s inverse at the same ``now_s``."""
        t = self.current(now_s)
        p = _points(points_local_m)
        c, s = math.cos(t.yaw_rad), math.sin(t.yaw_rad)
        dx, dy = p[:, 0] - t.x_m, p[:, 1] - t.y_m
        return np.column_stack([c * dx + s * dy, -s * dx + c * dy])


def _points(points_m: ArrayLike) -> FloatArray:
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"points are an (N, 2) array, got shape {p.shape}")
    return p


def _segment_means(values: FloatArray, w: FloatArray, seg: NDArray[np.int_]) -> FloatArray:
    return np.bincount(seg, weights=w * values) / np.bincount(seg, weights=w)


def _shared_rate(
    tau: FloatArray, y: FloatArray, w: FloatArray, seg: NDArray[np.int_], prior_sigma: float
) -> float:
    """The slope of y in time shared by each segment's line: weighted least squares with a
    zero-mean prior of σ ``prior_sigma`` on it, so a short window fits no rate from noise."""
    tc = tau - _segment_means(tau, w, seg)[seg]
    yc = y - _segment_means(y, w, seg)[seg]
    return float((w * tc) @ yc / ((w * tc) @ tc + prior_sigma**-2))


def _integral_to_end(tau: FloatArray, h: FloatArray) -> FloatArray:
    """∫ h dt from each sample's time to the last one (trapezoids between samples)."""
    pieces = 0.5 * (h[:-1] + h[1:]) * np.diff(tau)[:, None]
    out = np.zeros_like(h)
    out[:-1] = np.cumsum(pieces[::-1], axis=0)[::-1]
    return out


def _offsets(
    tau: FloatArray, y: FloatArray, w: FloatArray, seg: NDArray[np.int_], rate: float
) -> FloatArray:
    """Each segment's value at tau = 0, given the shared rate."""
    return _segment_means(y - rate * tau, w, seg)


def _extrapolated(e: _Estimate, tau_s: float) -> tuple[float, float, float]:
    """An estimate carried ``tau_s`` on by its drift rates, as (yaw, tx, ty)."""
    yaw = e.yaw_rad + e.yaw_rate_rps * tau_s
    mx = e.centre_local[0] + e.centre_velocity_mps[0] * tau_s
    my = e.centre_local[1] + e.centre_velocity_mps[1] * tau_s
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = e.centre
    return yaw, mx - (c * cx - s * cy), my - (s * cx + c * cy)
