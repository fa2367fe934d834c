"""The counter-steer ratio k = φr / φf (Stanley et al.: 0.63 measured, 0.6 from the linkage).

Two measurements, as in the paper ("extracting the value from a palm tree test using vehicle
heading and wheel angle, then adjusting the value based on simple turning tests"):

* From the palm tree's arcs, which give both tyre angles per arc: a weighted regression of
  φr on φf through the origin (k is a ratio: no offset), each arc weighted by its rear
  angle's sigma. Arcs nearer straight than ``min_front_rad`` are left out: their ratio is
  noise over noise.
* From steady turns at a constant wheel angle: the yaw rate (the heading's slope in time)
  over the speed is the centre's path curvature, ``cos β (tan φf + tan kφf) / L · G_ss``;
  with φf from the tyre map this is solved for k per turn (the curvature grows with k for
  tyre angles below 45 deg, so the root is unique), and the turns are averaged.

Each reports its sigma as the larger of the propagated one and the one the scatter of its
points implies: the first is honest with few points, the second catches what the model
misses.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import numpy.typing as npt
import scipy.optimize

from calibration.fit_inputs import (
    FloatArray,
    count,
    positive,
    same_length,
    sample_array,
    strictly_increasing,
)
from calibration.palm_tree import PalmTreeFit
from calibration.tyre_map import TyreMap

NEAR_STRAIGHT = "near_straight"
WHEEL_UNSTEADY = "wheel_unsteady"
SPEED_UNSTEADY = "speed_unsteady"
TOO_SLOW = "too_slow"
OUTSIDE_MAP = "outside_map"
NO_K_IN_RANGE = "no_k_in_range"


@dataclass(frozen=True)
class KRatioParams:
    min_front_rad: float = math.radians(5.0)
    min_arcs: int = 4
    # 1 % of 0.63: the value within 2 % at two sigma.
    max_k_sigma: float = 0.006
    sigma_floor_rad: float = math.radians(0.02)  # no arc weighs more than this allows
    # The linkage's k, to compare with; the paper's 0.63 and 0.6 differ by 5 %, twice that
    # points at a wrong tyre map or a bent linkage.
    linkage_k: float | None = None
    linkage_tolerance: float = 0.1  # relative


@dataclass(frozen=True)
class KRatioFit:
    k: float
    k_sigma: float
    arcs_used: int
    residuals_rad: FloatArray  # φr - k φf per arc used
    residual_rms_deg: float
    rejected: dict[str, int]
    accepted: bool
    reasons: tuple[str, ...]
    method: str = "weighted least squares of φr on φf through the origin"


def _combined_sigma(weights: FloatArray, residuals: FloatArray, leverage: float) -> float:
    propagated = math.sqrt(1.0 / leverage)
    if residuals.size < 2:
        return propagated
    scatter = math.sqrt(float(np.sum(weights * residuals**2)) / (residuals.size - 1) / leverage)
    return max(propagated, scatter)


def fit_k_from_arcs(
    front_rad: npt.ArrayLike,
    rear_rad: npt.ArrayLike,
    rear_sigma_rad: npt.ArrayLike,
    params: KRatioParams = KRatioParams(),
) -> KRatioFit:
    """k from per-arc tyre angles (any order: the result does not depend on it)."""
    front = sample_array("front_rad", front_rad)
    rear = sample_array("rear_rad", rear_rad)
    sigma = sample_array("rear_sigma_rad", rear_sigma_rad)
    same_length({"front_rad": front, "rear_rad": rear, "rear_sigma_rad": sigma})
    if np.any(sigma < 0.0):
        raise ValueError("rear_sigma_rad must not be negative")
    rejected: dict[str, int] = {}
    usable = np.abs(front) >= params.min_front_rad
    count(rejected, NEAR_STRAIGHT, int(np.sum(~usable)))
    f, r = front[usable], rear[usable]
    weights = 1.0 / (sigma[usable] ** 2 + params.sigma_floor_rad**2)
    reasons: list[str] = []
    if f.size == 0:
        reasons.append(f"no arc turns more than {math.degrees(params.min_front_rad):.1f} deg")
        empty = np.zeros(0)
        return KRatioFit(math.nan, math.inf, 0, empty, math.nan, rejected, False, tuple(reasons))
    leverage = float(np.sum(weights * f * f))
    k = float(np.sum(weights * f * r)) / leverage
    residuals = r - k * f
    k_sigma = _combined_sigma(weights, residuals, leverage)
    if f.size < params.min_arcs:
        reasons.append(f"{f.size} arcs used, at least {params.min_arcs} needed")
    if k_sigma > params.max_k_sigma:
        reasons.append(f"k sigma {k_sigma:.4f} above {params.max_k_sigma}")
    if params.linkage_k is not None:
        off = abs(k - params.linkage_k) / params.linkage_k
        if off > params.linkage_tolerance:
            reasons.append(
                f"k {k:.3f} is {100 * off:.0f} % from the linkage's {params.linkage_k} "
                f"(limit {100 * params.linkage_tolerance:.0f} %)"
            )
    return KRatioFit(
        k=k,
        k_sigma=k_sigma,
        arcs_used=int(f.size),
        residuals_rad=residuals,
        residual_rms_deg=math.degrees(float(np.sqrt(np.mean(residuals**2)))),
        rejected=rejected,
        accepted=not reasons,
        reasons=tuple(reasons),
    )


def fit_k_from_palm_tree(palm: PalmTreeFit, params: KRatioParams = KRatioParams()) -> KRatioFit:
    """:func:`fit_k_from_arcs` over the palm tree's accepted arcs."""
    if not palm.arcs:
        raise ValueError("the palm tree has no accepted arcs to take k from")
    arcs = palm.arcs
    return fit_k_from_arcs(
        [a.front_rad for a in arcs],
        [a.rear_rad for a in arcs],
        [a.rear_sigma_rad for a in arcs],
        params,
    )


@dataclass(frozen=True)
class SteadyTurn:
    """One steady turn, driven forward at a held wheel angle; checked on creation."""

    t_s: FloatArray
    heading_rad: FloatArray
    speed_mps: FloatArray  # of the geometric centre (the vehicle's speed), forward
    wheel_rad: FloatArray

    def __post_init__(self) -> None:
        checked = {
            f.name: sample_array(f.name, getattr(self, f.name), min_samples=10)
            for f in fields(self)
        }
        same_length(checked)
        strictly_increasing("t_s", checked["t_s"])
        for name, array in checked.items():
            object.__setattr__(self, name, array)


@dataclass(frozen=True)
class TurnParams:
    wheelbase_m: float
    characteristic_speed_mps: float | None = None
    hold_tolerance_rad: float = 0.05  # as the palm tree's
    min_speed_mps: float = 0.5
    max_speed_spread: float = 0.1  # relative standard deviation: G_ss and the mean hold
    min_front_rad: float = math.radians(5.0)
    max_k: float = 1.5  # the calibration file's bound
    min_turns: int = 2
    max_k_sigma: float = 0.006  # as from the palm tree

    def __post_init__(self) -> None:
        positive("wheelbase_m", self.wheelbase_m)


@dataclass(frozen=True)
class TurnK:
    wheel_rad: float
    front_rad: float
    yaw_rate_rad_per_s: float
    speed_mps: float
    k: float
    k_sigma: float


@dataclass(frozen=True)
class TurningKFit:
    k: float
    k_sigma: float
    turns: tuple[TurnK, ...]  # used
    rejected: dict[str, int]
    accepted: bool
    reasons: tuple[str, ...]
    method: str = "k solved per turn from yaw rate / speed and the tyre map, weighted mean"


def centre_curvature_per_m(front_rad: float, k: float, wheelbase_m: float, gain: float) -> float:
    """The model's path curvature at the geometric centre for φf and φr = k φf."""
    tan_f, tan_r = math.tan(front_rad), math.tan(k * front_rad)
    beta = math.atan((tan_f - tan_r) / 2.0)
    return math.cos(beta) * (tan_f + tan_r) / wheelbase_m * gain


def centre_speed_ratio(
    antenna_speed_mps: float,
    yaw_rate_rad_per_s: float,
    antenna_forward_m: float,
    antenna_left_m: float,
    sideslip_rad: float,
) -> float:
    """The geometric centre's speed over the antenna's in a steady turn.

    A receiver reports its antenna's speed; the model's curvature is the centre's. Both
    circle the same instantaneous centre of rotation, which lies ``R_c`` from the centre
    at right angles to its velocity (at the sideslip β from the heading), so with the
    antenna at (a, l) in the body frame and ``R_a = v_a / |ω|``:
    ``R_a² = R_c² + 2 R_c (a sin β - l cos β) + a² + l²`` (a left turn; a right turn is
    its mirror, l and β negated), solved for the positive ``R_c``. 1 for an antenna at
    the centre, whatever the turn.
    """
    if yaw_rate_rad_per_s == 0.0 or antenna_speed_mps <= 0.0:
        return 1.0
    side = 1.0 if yaw_rate_rad_per_s > 0.0 else -1.0
    a, lat, beta = antenna_forward_m, side * antenna_left_m, side * sideslip_rad
    r_a = antenna_speed_mps / abs(yaw_rate_rad_per_s)
    b = a * math.sin(beta) - lat * math.cos(beta)
    c = a * a + lat * lat - r_a * r_a
    discriminant = b * b - c
    if discriminant < 0.0:
        raise ValueError("no centre circle fits this antenna circle and offset")
    r_c = -b + math.sqrt(discriminant)
    if r_c <= 0.0:
        raise ValueError("the turn is tighter than the antenna's offset from the centre")
    return r_c / r_a


def _turn_k(turn: SteadyTurn, tyre_map: TyreMap, p: TurnParams) -> TurnK | str:
    wheel = float(np.mean(turn.wheel_rad))
    if np.max(np.abs(turn.wheel_rad - wheel)) > p.hold_tolerance_rad:
        return WHEEL_UNSTEADY
    speed = float(np.mean(turn.speed_mps))
    if speed < p.min_speed_mps:
        return TOO_SLOW
    if float(np.std(turn.speed_mps)) > p.max_speed_spread * speed:
        return SPEED_UNSTEADY
    tolerance = p.hold_tolerance_rad
    if not tyre_map.wheel_min_rad - tolerance <= wheel <= tyre_map.wheel_max_rad + tolerance:
        return OUTSIDE_MAP
    front = float(tyre_map.tyre_rad(wheel))
    if abs(front) < p.min_front_rad:
        return NEAR_STRAIGHT
    heading = np.unwrap(turn.heading_rad)
    t = turn.t_s - turn.t_s[0]
    (yaw_rate, _), cov = np.polyfit(t, heading, 1, cov=True)
    yaw_sigma = math.sqrt(max(float(cov[0, 0]), 0.0))
    gain = 1.0
    if p.characteristic_speed_mps is not None:
        gain = float(np.mean(1.0 / (1.0 + (turn.speed_mps / p.characteristic_speed_mps) ** 2)))
    kappa = float(yaw_rate) / speed

    def misfit(k: float) -> float:
        return centre_curvature_per_m(front, k, p.wheelbase_m, gain) - kappa

    low, high = misfit(0.0), misfit(p.max_k)
    if not low * high < 0.0:
        return NO_K_IN_RANGE
    k = float(scipy.optimize.brentq(misfit, 0.0, p.max_k, xtol=1e-12))
    step = 1e-6
    slope = (misfit(k + step) - misfit(k - step)) / (2 * step)
    speed_sigma = float(np.std(turn.speed_mps, ddof=1)) / math.sqrt(turn.speed_mps.size)
    kappa_sigma = abs(kappa) * math.hypot(yaw_sigma / float(yaw_rate), speed_sigma / speed)
    return TurnK(wheel, front, float(yaw_rate), speed, k, kappa_sigma / abs(slope))


def fit_k_from_turns(
    turns: Sequence[SteadyTurn], tyre_map: TyreMap, params: TurnParams
) -> TurningKFit:
    """k from steady turns, given the front tyre map (the palm tree's)."""
    if not turns:
        raise ValueError("no steady turns given")
    rejected: dict[str, int] = {}
    used: list[TurnK] = []
    for turn in turns:
        outcome = _turn_k(turn, tyre_map, params)
        if isinstance(outcome, str):
            count(rejected, outcome)
        else:
            used.append(outcome)
    reasons: list[str] = []
    if len(used) < params.min_turns:
        reasons.append(f"{len(used)} turns used, at least {params.min_turns} needed")
    if not used:
        return TurningKFit(math.nan, math.inf, (), rejected, False, tuple(reasons))
    ks = np.array([t.k for t in used])
    weights = 1.0 / np.maximum(np.array([t.k_sigma for t in used]), 1e-9) ** 2
    k = float(np.sum(weights * ks) / np.sum(weights))
    k_sigma = _combined_sigma(weights, ks - k, float(np.sum(weights)))
    if k_sigma > params.max_k_sigma:
        reasons.append(f"k sigma {k_sigma:.4f} above {params.max_k_sigma}")
    return TurningKFit(k, k_sigma, tuple(used), rejected, not reasons, tuple(reasons))


@dataclass(frozen=True)
class KCheck:
    palm_tree_k: float
    turning_k: float
    relative_difference: float  # (turning - palm tree) / palm tree
    agree: bool
    reasons: tuple[str, ...]


def check_k(palm: KRatioFit, turning: TurningKFit, tolerance: float = 0.02) -> KCheck:
    """Do the two measurements agree within ``tolerance`` (relative; 2 %: the accuracy each
    one is held to, so a larger difference means one of them, or the tyre map, is off)?"""
    relative = (turning.k - palm.k) / palm.k
    reasons: list[str] = []
    if not math.isfinite(relative):
        reasons.append("one of the two has no k")
    elif abs(relative) > tolerance:
        reasons.append(
            f"the turning tests' k {turning.k:.3f} is {100 * relative:+.1f} % from the palm "
            f"tree's {palm.k:.3f} (limit {100 * tolerance:.0f} %)"
        )
    return KCheck(palm.k, turning.k, relative, not reasons, tuple(reasons))
