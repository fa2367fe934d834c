"""The palm tree (Stanley et al., Figs. 18-19): wheel angle to tyre angles from driven arcs.

The maneuver: wheel at full left, drive an eighth to a half of a circle forward, reverse
back; half a turn right; again, until full right. Each held wheel angle draws a circle whose
radius and sideslip give both tyre angles through the vehicle model
(``appliance/sim/vehicle.py``, Stanley et al.'s eq. for the yaw rate with Kuwata's gain):

    curvature = cos β (tan φf + tan φr) / L · G_ss,   G_ss = 1 / (1 + (v / V_char)²)
    tan β     = (tan φf - tan φr) / 2   (β at the geometric centre, midway between axles)

so ``tan φf + tan φr = L κ / (cos β G_ss)`` and ``tan φf - tan φr = 2 tan β``, with β the
angle from the heading to the circle's tangent at the centre point (``φr`` positive in the
counter-steer direction, as in the simulator).

The method, step by step:

1. Samples whose fix sigma exceeds ``max_fix_sigma_m`` are dropped (counted).
2. Breaks between consecutive kept samples: a time gap, a position jump or a heading jump.
   A jump is a step that differs from the median step of its neighbours (velocity times
   time) by more than a threshold: the vehicle's own motion changes smoothly over a second,
   a threshold-switching jump (the paper's 0.3 m, the GNSS twin's) happens in one epoch.
   Each piece between breaks is fitted on its own ("removed discontinuous segments").
3. Within a piece, a new arc starts whenever the wheel leaves ``hold_tolerance_rad`` of the
   arc's first reading; samples below ``min_speed_mps`` are dropped (counted as stopped),
   and a stretch where the vehicle never moved (the wheel being turned) is no arc at all.
4. Each arc: the reference points moved to the geometric centre, a circle fitted
   (``calibration.circle_fit``), its curvature signed by the heading, β as the mean angle
   from heading to tangent, the tyre angles solved from the two equations above with their
   sigmas propagated, and the arc accepted or rejected by the first failed check.
5. The accepted arcs' (wheel, front tyre) points give the map (``calibration.tyre_map``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.ndimage

from calibration.circle_fit import (
    arc_length_m,
    fit_circle,
    mean_tangent_offset_rad,
    signed_curvature_per_m,
)
from calibration.fit_inputs import FloatArray, IndexArray, count, positive
from calibration.palm_tree_samples import PalmTreeSamples
from calibration.tyre_map import TyreMapFit, fit_tyre_map

# Reasons an arc is rejected (keys of PalmTreeFit.rejected and, for its samples, of
# PalmTreeFit.rejected_samples, which also counts FIX_SIGMA and STOPPED samples).
FIX_SIGMA = "fix_sigma"
STOPPED = "stopped"
TOO_FEW_SAMPLES = "too_few_samples"
FIT_FAILED = "fit_failed"
TOO_SHORT = "too_short"
NOT_A_CIRCLE = "not_a_circle"
IMPRECISE = "imprecise"
# Kinds of break between samples (PalmTreeFit.breaks).
TIME_GAP = "time_gap"
POSITION_JUMP = "position_jump"
HEADING_JUMP = "heading_jump"
METHOD = (
    "arcs between breaks with the wheel held, each a circle through the geometric centre's "
    "points (Pratt, then geometric least squares with a soft-L1 loss); curvature and the "
    "heading-to-tangent sideslip give tan φf ± tan φr; a polynomial map through the arcs"
)


@dataclass(frozen=True)
class PalmTreeParams:
    """The vehicle's geometry, and thresholds with the reason for each."""

    wheelbase_m: float
    antenna_forward_m: float = 0.0  # reference point ahead of the geometric centre
    antenna_left_m: float = 0.0
    characteristic_speed_mps: float | None = None  # V_char; None: no sideslip gain (G = 1)
    # 0.05 rad of wheel is 0.16 deg of tyre at 18:1, half the map's target error.
    hold_tolerance_rad: float = 0.05
    # Slower is the stop before reversing: points piling up on one spot would weigh it.
    min_speed_mps: float = 0.2
    # RTK-fixed-class fixes only: at 3 cm the step between two fixes has a sigma of 4.2 cm
    # and the jump test's 0.15 m sits at 3.5 sigma; noisier fixes would break every arc.
    max_fix_sigma_m: float = 0.03
    max_gap_s: float = 0.5  # five missed epochs at 10 Hz: a dropout, not a late epoch
    # Half the paper's 0.3 m jump, and 5 sigma of the step between two fixes of 2 cm.
    jump_threshold_m: float = 0.15
    # 10 sigma of a step between two headings of 0.1 deg noise; a turn at walking pace
    # changes the heading by 0.04 rad an epoch, which the neighbours' median absorbs.
    heading_jump_rad: float = 0.03
    jump_window: int = 9  # epochs in the median a step is compared with (odd)
    # Fewer points leave the sigmas, taken from their scatter, unreliable themselves.
    min_arc_samples: int = 20
    # A quick first cut: shorter arcs (30 deg at the lock's 4 m radius) fail the tyre
    # sigma check anyway.
    min_arc_length_m: float = 2.0
    # A circle's residual RMS should be the fix noise; twice that (at least 1 cm) means a
    # missed jump, a wheel that moved or a heading that does not belong to the points.
    max_residual_ratio: float = 2.0
    min_residual_floor_m: float = 0.01
    # A third of the map's 0.3 deg target, so the map's error is not the points' noise.
    max_tyre_sigma_rad: float = math.radians(0.1)
    min_arcs: int = 5
    map_powers: tuple[int, ...] = (1, 3, 5)
    max_map_residual_deg: float = 0.3  # the target: the tyre-angle map within 0.3 deg

    def __post_init__(self) -> None:
        positive("wheelbase_m", self.wheelbase_m)
        if self.characteristic_speed_mps is not None:
            positive("characteristic_speed_mps", self.characteristic_speed_mps)
        if self.jump_window < 3 or self.jump_window % 2 == 0:
            raise ValueError(f"jump_window must be odd and at least 3 (got {self.jump_window})")


# Wheel-angle magnitudes closer than this are one for the map's coefficients (the paper's
# arcs are half a turn apart).
MAGNITUDE_GAP_RAD = 0.5


@dataclass(frozen=True)
class Arc:
    """One held wheel angle's circle and the tyre angles it gives (the per-arc table)."""

    first_index: int  # into the samples
    last_index: int
    samples: int  # moving samples fitted
    wheel_rad: float  # mean over the fitted samples
    wheel_spread_rad: float  # their standard deviation
    front_rad: float
    front_sigma_rad: float
    rear_rad: float  # positive: counter-steer
    rear_sigma_rad: float
    curvature_per_m: float  # positive: centre to the left
    curvature_sigma_per_m: float
    radius_m: float
    sideslip_rad: float  # β at the geometric centre
    sideslip_sigma_rad: float
    sideslip_gain: float  # the G_ss used (1 without V_char)
    arc_length_m: float
    residual_rms_m: float
    fix_sigma_m: float  # median over the fitted samples


@dataclass(frozen=True)
class PalmTreeFit:
    arcs: tuple[Arc, ...]  # accepted, in time order
    rejected: dict[str, int]  # arcs, by reason
    rejected_samples: dict[str, int]  # samples, by reason (an arc's reason for its samples)
    breaks: dict[str, int]  # discontinuities found, by kind
    samples_used: int
    tyre_map: TyreMapFit | None  # None when too few arcs for the powers asked
    accepted: bool
    reasons: tuple[str, ...]  # why not accepted (empty when accepted)
    method: str = METHOD


def _centre_points(s: PalmTreeSamples, p: PalmTreeParams) -> tuple[FloatArray, FloatArray]:
    cos_h, sin_h = np.cos(s.heading_rad), np.sin(s.heading_rad)
    cx = s.x_m - p.antenna_forward_m * cos_h + p.antenna_left_m * sin_h
    cy = s.y_m - p.antenna_forward_m * sin_h - p.antenna_left_m * cos_h
    return cx, cy


def _break_kinds(s: PalmTreeSamples, idx: IndexArray, p: PalmTreeParams) -> list[str | None]:
    """For each step between consecutive kept samples, the kind of break or None."""
    if idx.size < 2:
        return []
    dt = np.diff(s.t_s[idx])
    steps = {
        "x": np.diff(s.x_m[idx]),
        "y": np.diff(s.y_m[idx]),
        "h": np.remainder(np.diff(s.heading_rad[idx]) + math.pi, math.tau) - math.pi,
    }
    typical = {
        k: scipy.ndimage.median_filter(v / dt, size=p.jump_window, mode="nearest") * dt
        for k, v in steps.items()
    }
    position_off = np.hypot(steps["x"] - typical["x"], steps["y"] - typical["y"])
    heading_off = np.abs(steps["h"] - typical["h"])
    kinds: list[str | None] = []
    for gap, pos, head in zip(dt, position_off, heading_off, strict=True):
        if gap > p.max_gap_s:
            kinds.append(TIME_GAP)
        elif pos > p.jump_threshold_m:
            kinds.append(POSITION_JUMP)
        elif head > p.heading_jump_rad:
            kinds.append(HEADING_JUMP)
        else:
            kinds.append(None)
    return kinds


def _segments(s: PalmTreeSamples, p: PalmTreeParams, breaks: dict[str, int]) -> list[list[int]]:
    """Runs of kept samples with no break between them and the wheel held."""
    kept = np.flatnonzero(s.fix_sigma_m <= p.max_fix_sigma_m)
    kinds = _break_kinds(s, kept, p)
    segments: list[list[int]] = []
    for pos, i in enumerate(kept):
        kind = kinds[pos - 1] if pos else None
        if kind is not None:
            count(breaks, kind)
        moved = bool(segments) and (
            abs(s.wheel_rad[i] - s.wheel_rad[segments[-1][0]]) > p.hold_tolerance_rad
        )
        if not segments or kind is not None or moved:
            segments.append([int(i)])
        else:
            segments[-1].append(int(i))
    return segments


def _sideslip_gain(s: PalmTreeSamples, ii: IndexArray, ratio: float, p: PalmTreeParams) -> float:
    """G_ss averaged over the arc, weighted by distance (what the circle averages over)."""
    if p.characteristic_speed_mps is None:
        return 1.0
    speed = np.abs(s.speed_mps[ii]) * ratio
    gain = 1.0 / (1.0 + (speed / p.characteristic_speed_mps) ** 2)
    return float(np.sum(gain * speed) / np.sum(speed))


def _fit_arc(
    s: PalmTreeSamples, ii: IndexArray, cx: FloatArray, cy: FloatArray, p: PalmTreeParams
) -> Arc | str:
    """The arc through samples ``ii`` (moving, held wheel), or the reason it is rejected."""
    n = ii.size
    if n < p.min_arc_samples:
        return TOO_FEW_SAMPLES
    x, y, heading = cx[ii], cy[ii], s.heading_rad[ii]
    sigma_fix = float(np.median(s.fix_sigma_m[ii]))
    scale = max(3.0 * sigma_fix, p.min_residual_floor_m)
    try:
        circle = fit_circle(x, y, robust_scale_m=scale)
    except ValueError:
        return FIT_FAILED
    if not circle.converged:
        return FIT_FAILED
    length = arc_length_m(circle, x, y)
    if length < p.min_arc_length_m:
        return TOO_SHORT
    if circle.rms_m > max(p.max_residual_ratio * sigma_fix, p.min_residual_floor_m):
        return NOT_A_CIRCLE
    kappa = signed_curvature_per_m(circle, x, y, heading)
    beta, beta_sigma = mean_tangent_offset_rad(circle, x, y, heading)
    # Both points turn about the same centre: speeds scale with the distance from it.
    if circle.a_per_m == 0.0:
        ratio = 1.0
    else:
        ccx, ccy = circle.centre_m
        ratio = circle.radius_m / float(np.mean(np.hypot(s.x_m[ii] - ccx, s.y_m[ii] - ccy)))
    gain = _sideslip_gain(s, ii, ratio, p)
    sum_tan = p.wheelbase_m * kappa / (math.cos(beta) * gain)
    diff_tan = 2.0 * math.tan(beta)
    tan_front, tan_rear = 0.5 * (sum_tan + diff_tan), 0.5 * (sum_tan - diff_tan)
    sum_sigma = p.wheelbase_m * circle.curvature_sigma_per_m / (math.cos(beta) * gain)
    diff_sigma = 2.0 * beta_sigma / math.cos(beta) ** 2
    tan_sigma = 0.5 * math.hypot(sum_sigma, diff_sigma)
    front_sigma = tan_sigma / (1.0 + tan_front**2)
    if not front_sigma <= p.max_tyre_sigma_rad:
        return IMPRECISE
    wheel = s.wheel_rad[ii]
    return Arc(
        first_index=int(ii[0]),
        last_index=int(ii[-1]),
        samples=n,
        wheel_rad=float(np.mean(wheel)),
        wheel_spread_rad=float(np.std(wheel)),
        front_rad=math.atan(tan_front),
        front_sigma_rad=front_sigma,
        rear_rad=math.atan(tan_rear),
        rear_sigma_rad=tan_sigma / (1.0 + tan_rear**2),
        curvature_per_m=kappa,
        curvature_sigma_per_m=circle.curvature_sigma_per_m,
        radius_m=circle.radius_m,
        sideslip_rad=beta,
        sideslip_sigma_rad=beta_sigma,
        sideslip_gain=gain,
        arc_length_m=length,
        residual_rms_m=circle.rms_m,
        fix_sigma_m=sigma_fix,
    )


def fit_palm_tree(samples: PalmTreeSamples, params: PalmTreeParams) -> PalmTreeFit:
    """Arcs, tyre angles and the wheel to front-tyre map from one palm-tree recording."""
    cx, cy = _centre_points(samples, params)
    rejected: dict[str, int] = {}
    rejected_samples: dict[str, int] = {}
    breaks: dict[str, int] = {}
    count(rejected_samples, FIX_SIGMA, int(np.sum(samples.fix_sigma_m > params.max_fix_sigma_m)))
    arcs: list[Arc] = []
    used = 0
    for segment in _segments(samples, params, breaks):
        idx = np.asarray(segment, dtype=np.intp)
        moving = idx[np.abs(samples.speed_mps[idx]) >= params.min_speed_mps]
        count(rejected_samples, STOPPED, idx.size - moving.size)
        if moving.size == 0:
            continue  # the wheel being turned at a standstill: no arc was driven
        outcome = _fit_arc(samples, moving, cx, cy, params)
        if isinstance(outcome, str):
            count(rejected, outcome)
            count(rejected_samples, outcome, moving.size)
        else:
            arcs.append(outcome)
            used += moving.size
    tyre_map, reasons = _map_and_verdict(arcs, params)
    return PalmTreeFit(
        arcs=tuple(arcs),
        rejected=rejected,
        rejected_samples=rejected_samples,
        breaks=breaks,
        samples_used=used,
        tyre_map=tyre_map,
        accepted=not reasons,
        reasons=tuple(reasons),
    )


def _map_and_verdict(arcs: list[Arc], p: PalmTreeParams) -> tuple[TyreMapFit | None, list[str]]:
    reasons: list[str] = []
    if len(arcs) < p.min_arcs:
        reasons.append(f"{len(arcs)} arcs accepted, at least {p.min_arcs} needed")
    wheel = np.array([a.wheel_rad for a in arcs])
    if not (
        wheel.size and wheel.min() < -p.hold_tolerance_rad < p.hold_tolerance_rad < wheel.max()
    ):
        reasons.append("no accepted arc on one side: the map needs left and right turns")
    if len(arcs) <= len(p.map_powers) or not np.any(wheel != 0.0):
        reasons.append(f"{len(arcs)} arcs cannot fit the powers {p.map_powers} with a residual")
        return None, reasons
    pinned = _distinct_magnitudes(wheel, p.hold_tolerance_rad)
    if pinned < len(p.map_powers):
        # An odd map: an arc and its mirror image pin the same coefficient, and the
        # straight-ahead arc none; fewer magnitudes than powers leave the map free to
        # swing between them (5 arcs at 0, ±π, ±2.3π fit a ratio of 4.6 for 18).
        reasons.append(
            f"the arcs' wheel angles pin {pinned} of the map's {len(p.map_powers)} "
            f"coefficients (an arc and its mirror count once, straight ahead none): drive "
            "at more wheel angles"
        )
        return None, reasons
    fit = fit_tyre_map(
        wheel,
        [a.front_rad for a in arcs],
        [a.front_sigma_rad for a in arcs],
        powers=p.map_powers,
    )
    if not fit.monotonic:
        reasons.append("the fitted map is not monotonic over the measured wheel angles")
    if fit.residual_max_deg > p.max_map_residual_deg:
        reasons.append(
            f"an arc lies {fit.residual_max_deg:.2f} deg off the map (limit "
            f"{p.max_map_residual_deg} deg)"
        )
    return fit, reasons


def _distinct_magnitudes(wheel_rad: np.ndarray, tolerance_rad: float) -> int:
    """How many distinct wheel-angle magnitudes off straight ahead the arcs were driven at
    (closer than ``MAGNITUDE_GAP_RAD`` is one: it barely pins a second coefficient)."""
    magnitudes = np.sort(np.abs(wheel_rad[np.abs(wheel_rad) > tolerance_rad]))
    if magnitudes.size == 0:
        return 0
    return 1 + int(np.count_nonzero(np.diff(magnitudes) > MAGNITUDE_GAP_RAD))
