"""Stanley et al.'s continually varying local frame (Fig. 11): the vehicle smooth, the path moving.

A globally referenced path followed with GNSS fixes jumps with every jump of the fix (the
Husky's threshold switching between LGPR and GPS moved it by 0.3 m), and a jump of the
path under a pure pursuit tracker is a jerk of the wheel. So the tracker works in a
local frame in which the vehicle's pose is dead-reckoned (``dead_reckoning``, smooth by
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
* **Gate and regimes**: a fix farther from the prediction than ``gate_sigma`` σ (or with
  a heading off by more than ``heading_gate_rad``) is not taken. One such fix is dropped;
  when ``jump_persist_fixes`` in a row agree with each other the fix has jumped, and the
  place it jumped to becomes a *regime*, remembered as a vector from the trusted regime
  (see ``_trusted_offset``). A fix that lands on a known regime's offset is taken into
  that regime; changing regime takes ``jump_persist_fixes`` fixes in a row. Every
  regime's fixes are fitted (their own offsets, one drift rate), but the estimate is the
  *trusted* regime's; a regime the fixes have stayed in for ``adopt_after_s``
  becomes the trusted one, and the path then moves to it under the rate bounds below.
  The Husky's LGPR/GPS threshold switching flips the fix between two places and back
  within seconds to tens of seconds: following each flip would carry the vehicle 0.3 m
  off the route for half of the time (measured: 15 cm RMS at the anchor, against 3 cm
  without jumps), while a fix that has moved for good is followed after the wait.
* **Apply**: the transform the tracker sees moves towards the estimate at most
  ``max_translation_rate_mps`` at the vehicle and ``max_rotation_rate_rps`` (rotating
  about the vehicle, not about the far-away ENU origin), so a step in the estimate becomes
  a ramp: the path near the vehicle moves no faster than v + ω r.

Pure: no I/O; time is an argument; ``current(now_s)`` advances the ramp to ``now_s``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import cast

import numpy as np
from numpy.typing import ArrayLike, NDArray

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.fix_pairs import PairColumns
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]


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
    # A regime the fixes keep to for this long is believed (see the module).
    adopt_after_s: float = 30.0
    # Until the window holds this many fixes the estimate is young: refitted at every fix
    # and taken without the fade. Each next estimate is then better than the last, not
    # noise about the same value, and fading in a 5 cm error of the first few fixes over
    # blend_s would steer the vehicle to it (measured: a 0.5 m offset at 10 mph converged
    # below 0.1 m only after 14 m in one of six runs). The ramp still bounds the path's
    # speed.
    settle_fixes: int = 50

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
            "adopt_after_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite, got {value}")
        if self.max_pairs < 2 or self.jump_persist_fixes < 1 or self.max_extrapolation_s < 0:
            raise ValueError("max_pairs >= 2, jump_persist_fixes >= 1, max_extrapolation_s >= 0")
        if self.settle_fixes < 0:
            raise ValueError(f"settle_fixes must be >= 0, got {self.settle_fixes}")


class FixVerdict(StrEnum):
    ACCEPTED = "accepted"  # in the trusted regime
    OUTLIER = "outlier"  # beyond the gate: held back, not (yet) followed
    JUMP_HELD = "jump_held"  # in another regime (new or known): fitted, not followed yet
    JUMP_FOLLOWED = "jump_followed"  # that regime has lasted: the estimate moves to it
    OUT_OF_ORDER = "out_of_order"  # older than the newest fix taken: ignored


@dataclass(frozen=True)
class _Pair:
    time_s: float
    global_xy: tuple[float, float]
    local_xy: tuple[float, float]
    yaw_diff_rad: float  # local heading minus global heading
    weight: float  # 1 / σ²
    segment: int  # which offset it shares: the regime it was taken into


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
        self._pairs = PairColumns(self.params.max_pairs)
        # Fixes that did not land on the current regime: (pair, nearest regime or None,
        # residual), waiting for ``jump_persist_fixes`` in a row to agree.
        self._candidates: list[tuple[_Pair, int | None, tuple[float, float]]] = []
        self._segment = 0  # the newest regime's number
        # Each regime's residual against the trusted one (local frame, m); trusted: 0.
        self._regimes: dict[int, tuple[float, float]] = {0: (0.0, 0.0)}
        self._regime_fixes: dict[int, int] = {}
        self._regime_support: dict[int, int] = {}  # fixes of the fit its vector is from
        self._trusted = 0
        self._current = 0  # the regime of the newest fix taken,
        self._current_since_s = -math.inf  # and since when the fixes stay in it
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
        self.jumps_held = 0  # fixes taken into a regime that is not (yet) trusted
        self.jumps_followed = 0  # regimes adopted

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
        regime = self._regime_of(offset, yaw_off, sigma)
        if regime == self._current:
            self._candidates.clear()
            return self._taken(self._into(pair, regime, offset), now_s)
        # Another regime, or none: the fixes must say so ``jump_persist_fixes`` times in a
        # row before the current regime changes. One fix in the overlap of two regimes'
        # gates (5 cm fixes and a 0.3 m flip: a few in a thousand) is dropped, not taken
        # into the wrong regime, where it would pull that regime's fit.
        if regime is None:
            self.outliers += 1
        self._candidates.append((pair, regime, offset))
        if len(self._candidates) < self.params.jump_persist_fixes:
            return FixVerdict.OUTLIER
        labels = {label for _, label, _ in self._candidates}
        if len(labels) > 1 or (regime is None and not self._candidates_agree()):
            self._candidates.pop(0)
            return FixVerdict.OUTLIER
        if regime is None:  # a new place: a new regime
            self._segment += 1
            regime = self._segment
        if regime != self._trusted:
            # Remembered by the mean residual of the fixes that went there, and measured
            # again by the fits from now on: a regime entered again is a new episode. A
            # jump drawn anew can land inside the gate of an old regime's vector (two
            # 0.3 m jumps 39° apart are 0.2 m apart, a 4 σ gate of 5 cm fixes), and that
            # old vector, kept, would be a word on the trusted offset wrong by as much
            # once the window holds only the jump's fixes (measured: 16 cm RMS at the
            # anchor on one of three off-road miles, against 4 cm).
            mean = np.mean(np.array([o for _, _, o in self._candidates]), axis=0)
            self._regimes[regime] = (float(mean[0]), float(mean[1]))
            self._regime_fixes[regime] = 0
            self._regime_support.pop(regime, None)
        held, self._candidates = self._candidates, []
        self._current, self._current_since_s = regime, held[0][0].time_s
        for candidate, _, candidate_offset in held[:-1]:
            self._take(self._into(candidate, regime, candidate_offset))
        return self._taken(self._into(pair, regime, offset), now_s)

    def _into(self, pair: _Pair, regime: int, offset: tuple[float, float]) -> _Pair:
        """``pair`` as one of ``regime``'s; a regime not trusted keeps the mean of its
        fixes' residuals as its vector."""
        if regime != self._trusted:
            count = self._regime_fixes.get(regime, 0) + 1
            vx, vy = self._regimes[regime]
            self._regimes[regime] = (vx + (offset[0] - vx) / count, vy + (offset[1] - vy) / count)
            self._regime_fixes[regime] = count
        return replace(pair, segment=regime)

    def _regime_of(self, offset: tuple[float, float], yaw_off: float, sigma: float) -> int | None:
        """The regime whose offset the residual lands nearest, within the gate, or None."""
        if abs(yaw_off) > self.params.heading_gate_rad:
            return None
        gate = self.params.gate_sigma * sigma
        misses = {
            regime: math.hypot(offset[0] - vx, offset[1] - vy)
            for regime, (vx, vy) in self._regimes.items()
        }
        # the nearest: a flip of 0.3 m is inside a 4-sigma gate of 5 cm fixes more often
        # than not, and taking it into the trusted regime would drag the estimate over
        nearest = min(misses, key=misses.__getitem__)
        return nearest if misses[nearest] <= gate else None

    def _taken(self, pair: _Pair, now_s: float) -> FixVerdict:
        """Take a gated pair; adopt its regime once the fixes have kept to it long enough."""
        self._take(pair)
        if pair.segment == self._trusted:
            if now_s >= self._estimated_at_s + self.params.estimate_period_s or self._young:
                self._fit(now_s)
            return FixVerdict.ACCEPTED
        if now_s - self._current_since_s < self.params.adopt_after_s:
            self.jumps_held += 1
            if now_s >= self._estimated_at_s + self.params.estimate_period_s:
                self._fit(now_s)
            return FixVerdict.JUMP_HELD
        vx, vy = self._regimes[pair.segment]
        self._regimes = {r: (x - vx, y - vy) for r, (x, y) in self._regimes.items()}
        self._regime_fixes.pop(pair.segment, None)
        self._regime_support.clear()
        self._trusted = pair.segment
        self.jumps_followed += 1
        self._fit(now_s)
        return FixVerdict.JUMP_FOLLOWED

    @property
    def _young(self) -> bool:
        return len(self._pairs) < self.params.settle_fixes

    def _take(self, pair: _Pair) -> None:
        self._pairs.append(
            pair.time_s, pair.global_xy, pair.local_xy, pair.yaw_diff_rad, pair.weight, pair.segment
        )
        self._pairs.drop_older_than(pair.time_s - self.params.window_s)

    def _residual(self, pair: _Pair, time_s: float) -> tuple[tuple[float, float], float]:
        """Where the estimate puts the fix, less where odometry says it was (local frame)."""
        yaw, tx, ty = self._goal(time_s)
        c, s = math.cos(yaw), math.sin(yaw)
        gx, gy = pair.global_xy
        lx, ly = pair.local_xy
        offset = (c * gx - s * gy + tx - lx, s * gx + c * gy + ty - ly)
        return offset, wrap_angle_rad(pair.yaw_diff_rad - yaw)

    def _candidates_agree(self) -> bool:
        residuals = [self._residual(c, c.time_s) for c, _, _ in self._candidates]
        offsets = np.array([r[0] for r in residuals])
        yaws = np.array([r[1] for r in residuals])
        spread = np.hypot(*(offsets - offsets.mean(axis=0)).T)
        gates = [self.params.gate_sigma / math.sqrt(c.weight) for c, _, _ in self._candidates]
        return bool(
            np.all(spread <= gates)
            and np.all(np.abs(yaws - yaws.mean()) <= self.params.heading_gate_rad)
        )

    # -- the estimate -------------------------------------------------------------------

    def _fit(self, now_s: float) -> None:
        """Lines in time, one offset per segment and one drift rate, at the newest pair."""
        p = self.params
        pairs = self._pairs
        times = pairs.time_s
        t_ref = float(times[-1])
        tau = times - t_ref
        w = pairs.weight
        regimes, seg, counts = pairs.segments()
        yaw_diff = pairs.yaw_diff_rad
        ref = float(yaw_diff[-1])
        yaw = ref + ((yaw_diff - ref + math.pi) % math.tau - math.pi)  # wrap_angle_rad
        mean_w = np.add.reduce(w) / len(w)  # w.mean(), without its wrapper
        yaw_groups = _Groups(w / (mean_w * p.heading_sigma_rad**2), seg, tau)
        yaw_rate = yaw_groups.shared_rate(yaw, p.yaw_drift_prior_rps)
        yaw_i = yaw_groups.per_pair(yaw_groups.offsets(yaw, yaw_rate)) + yaw_rate * tau
        # Each pair's word on where the newest fix's global point is in the local frame
        # at t_ref. A yaw drift turns the local frame about its origin, which moves that
        # point by yaw_rate × J R (g − g_ref) per second: integrated along the fixes, so
        # a gyro bias is no translation drift and the rate below is odometry's own.
        # (x and y as separate columns: the fit is many small array operations.)
        global_x, global_y = pairs.global_x, pairs.global_y
        centre = (float(global_x[-1]), float(global_y[-1]))
        rel_x, rel_y = global_x - centre[0], global_y - centre[1]
        cos, sin = np.cos(yaw_i), np.sin(yaw_i)
        turned_x, turned_y = cos * rel_x - sin * rel_y, sin * rel_x + cos * rel_y
        step_s = tau[1:] - tau[:-1]
        m_x = pairs.local_x - turned_x - yaw_rate * _integral_to_end(step_s, -turned_y)
        m_y = pairs.local_y - turned_y - yaw_rate * _integral_to_end(step_s, turned_x)
        prior = p.translation_drift_prior_mps
        groups = _Groups(w, seg, tau)
        velocity = (groups.shared_rate(m_x, prior), groups.shared_rate(m_y, prior))
        trusted = self._trusted_offset(
            regimes,
            counts,
            groups.total,
            groups.offsets(m_x, velocity[0]),
            groups.offsets(m_y, velocity[1]),
        )
        before = self._target(now_s) if self._estimate is not None else None
        self._estimate = _Estimate(
            t_ref,
            float(yaw_i[-1]),
            float(yaw_rate),
            centre,
            trusted,
            velocity,
        )
        self._estimated_at_s = now_s
        if before is not None and not self._young:
            # the fade: the old less the new, as a turn about the vehicle and a shift of it
            new_yaw, tx, ty = _extrapolated(self._estimate, now_s - t_ref)
            qx, qy = self._pivot
            c, s = math.cos(new_yaw), math.sin(new_yaw)
            gx, gy = c * (qx - tx) + s * (qy - ty), -s * (qx - tx) + c * (qy - ty)
            c, s = math.cos(before[0]), math.sin(before[0])
            shift = (c * gx - s * gy + before[1] - qx, s * gx + c * gy + before[2] - qy)
            self._blend = (wrap_angle_rad(before[0] - new_yaw), qx, qy, *shift)

    def _trusted_offset(
        self,
        regimes: list[int],
        counts: NDArray[np.intp],
        weights: FloatArray,
        offset_x: FloatArray,
        offset_y: FloatArray,
    ) -> tuple[float, float]:
        """The trusted regime's intercept, from every regime in the window.

        A regime's fixes see the global points moved by J, so its intercept is the
        trusted one less R J, and R J is the vector it is remembered by: each regime's
        intercept plus its vector is a word on the trusted one, weighted by its fixes.
        A vector is measured again from the fit while both regimes have fixes in the
        window, and kept from the fit that had the most of both: at the change-over
        both sides are long and the shared drift rate pins the difference to about a
        centimetre, while later fits see one side shrink to a few old fixes."""
        index = {regime: i for i, regime in enumerate(regimes)}
        if self._trusted in index:
            t = index[self._trusted]
            for regime, i in index.items():
                support = int(min(counts[t], counts[i]))
                if regime != self._trusted and support >= self._regime_support.get(regime, 0):
                    self._regime_support[regime] = support
                    self._regimes[regime] = (
                        float(offset_x[t] - offset_x[i]),
                        float(offset_y[t] - offset_y[i]),
                    )
        vx = np.array([self._regimes[r][0] for r in regimes])
        vy = np.array([self._regimes[r][1] for r in regimes])
        total = float(weights.sum())
        return (
            float(weights @ (offset_x + vx) / total),
            float(weights @ (offset_y + vy) / total),
        )

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


class _Groups:
    """Weighted means per segment over one set of weights and times: what the weights
    and the times alone give (each segment's total weight, the times about their
    segment's mean) is worked out once per fit, not once per fitted quantity."""

    def __init__(self, w: FloatArray, seg: NDArray[np.intp], tau: FloatArray) -> None:
        self.w, self.seg, self.tau = w, seg, tau
        self.total = cast(FloatArray, np.bincount(seg, weights=w))  # weighted: floats
        self._one = len(self.total) == 1
        self._tc = tau - self.per_pair(self.means(tau))
        self._wtc = w * self._tc
        self._wtc_tc = float(self._wtc @ self._tc)

    def per_pair(self, per_segment: FloatArray) -> FloatArray:
        """Each pair's segment's value (one segment: broadcast as it is)."""
        return per_segment if self._one else per_segment[self.seg]

    def means(self, values: FloatArray) -> FloatArray:
        result: FloatArray = np.bincount(self.seg, weights=self.w * values) / self.total
        return result

    def shared_rate(self, y: FloatArray, prior_sigma: float) -> float:
        """The slope of y in time shared by each segment's line: weighted least squares
        with a zero-mean prior of σ ``prior_sigma`` on it, so a short window fits no rate
        from noise."""
        yc = y - self.per_pair(self.means(y))
        return float(self._wtc @ yc / (self._wtc_tc + prior_sigma**-2))

    def offsets(self, y: FloatArray, rate: float) -> FloatArray:
        """Each segment's value at tau = 0, given the shared rate."""
        return self.means(y - rate * self.tau)


_ZERO = np.zeros(1)


def _integral_to_end(step_s: FloatArray, h: FloatArray) -> FloatArray:
    """∫ h dt from each sample's time to the last one (trapezoids between samples
    ``step_s`` apart)."""
    pieces = 0.5 * (h[:-1] + h[1:]) * step_s
    return np.concatenate((pieces[::-1].cumsum()[::-1], _ZERO))


def _extrapolated(e: _Estimate, tau_s: float) -> tuple[float, float, float]:
    """An estimate carried ``tau_s`` on by its drift rates, as (yaw, tx, ty)."""
    yaw = e.yaw_rad + e.yaw_rate_rps * tau_s
    mx = e.centre_local[0] + e.centre_velocity_mps[0] * tau_s
    my = e.centre_local[1] + e.centre_velocity_mps[1] * tau_s
    c, s = math.cos(yaw), math.sin(yaw)
    cx, cy = e.centre
    return yaw, mx - (c * cx - s * cy), my - (s * cx + c * cy)
