"""Has the steering servo's torque changed since the look-ahead was tuned? (Fig. 21)

Stanley et al.: tracking stability "was a function of the torque of the steering servo";
when a voltage change lowered it, the look-ahead had to move further out. So the schedule
is tied to the servo it was tuned with, and this compares the servo's telemetry now with a
baseline recorded at tuning time. Two things can change:

* What the wheel needs. The torque the servo applies while the wheel moves is the load:
  friction, self-centring growing with the wheel angle, and whatever grows with the rate.
  It is fitted as ``|torque| = c0 + c_wheel |wheel| + c_rate |rate|`` (least squares over
  the samples where the wheel moves), and the two fits are compared at one operating point,
  the baseline's hard one (the 90th percentiles of its |wheel| and |rate|). Why a fit and
  not percentiles of |torque| per rate bin: the load depends on the wheel angle, so two
  recordings of the same servo driven differently differ by up to 17 % in such percentiles
  (measured on the simulated servo under random sweeps), while the fit compares like with
  like.
* What the servo can give. A servo that lost torque but still has more than the wheel needs
  shows nothing (nor, in the simulated servo, in tracking: its position loop slews as fast as
  before); once it runs short it stalls, pushing without moving. The share of its working
  samples that are stalls is the second measure.

Re-tuning is flagged when the needed torque moved by more than ``max_change`` or the stall
fraction rose by more than ``max_stall_increase``. The 15 % is a choice (the paper gives no
number): fits of the noise-free simulated servo under different sweeps agree within 0.1 %,
so the margin is for real telemetry's noise and for load terms the fit does not have.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.fit_inputs import FloatArray, count, positive, same_length, sample_array

IDLE = "idle"
METHOD = (
    "|torque| = c0 + c_wheel |wheel| + c_rate |rate| over moving samples, compared at the "
    "baseline's 90th-percentile wheel angle and rate; and the stall fraction"
)


@dataclass(frozen=True)
class TorqueParams:
    active_torque_nm: float = 0.5  # the simulated coupling's free play takes 0.3 N m
    # Slower than this while pushing is a stall: 1 % of the servo's slew.
    stall_rate_rad_per_s: float = 0.05
    min_moving_samples: int = 50
    max_change: float = 0.15
    # A healthy servo stalls well under 1 % of its working time (reversals near the lock).
    max_stall_increase: float = 0.05

    def __post_init__(self) -> None:
        for name in ("stall_rate_rad_per_s", "max_change", "max_stall_increase"):
            positive(name, getattr(self, name))
        if self.min_moving_samples < 4:
            raise ValueError("min_moving_samples must be at least 4 (three coefficients)")


@dataclass(frozen=True)
class TorqueStats:
    coeffs: tuple[float, float, float]  # c0 [N m], c_wheel [N m/rad], c_rate [N m s/rad]
    residual_rms_nm: float
    hard_wheel_rad: float  # 90th percentile of |wheel| while moving
    hard_rate_rad_per_s: float  # 90th percentile of |rate| while moving
    moving: int
    stalls: int
    stall_fraction: float
    rejected: dict[str, int]  # samples, by reason ("idle": below the working torque)

    def needed_torque_nm(self, wheel_rad: float, rate_rad_per_s: float) -> float:
        c0, c_wheel, c_rate = self.coeffs
        return c0 + c_wheel * abs(wheel_rad) + c_rate * abs(rate_rad_per_s)


def torque_stats(
    wheel_rad: FloatArray,
    wheel_rate_rad_per_s: FloatArray,
    torque_nm: FloatArray,
    params: TorqueParams = TorqueParams(),
) -> TorqueStats:
    """The statistics of one recording (see the module's method)."""
    wheel = sample_array("wheel_rad", wheel_rad)
    rate = sample_array("wheel_rate_rad_per_s", wheel_rate_rad_per_s)
    torque = sample_array("torque_nm", torque_nm)
    same_length({"wheel_rad": wheel, "wheel_rate_rad_per_s": rate, "torque_nm": torque})
    rejected: dict[str, int] = {}
    working = np.abs(torque) >= params.active_torque_nm
    count(rejected, IDLE, int(np.sum(~working)))
    moving = working & (np.abs(rate) >= params.stall_rate_rad_per_s)
    stalls = int(np.sum(working)) - int(np.sum(moving))
    if np.sum(moving) < params.min_moving_samples:
        raise ValueError(
            f"{int(np.sum(moving))} samples with the wheel moving under torque, at least "
            f"{params.min_moving_samples} needed: steer more while recording"
        )
    w, r, t = np.abs(wheel[moving]), np.abs(rate[moving]), np.abs(torque[moving])
    design = np.stack([np.ones_like(w), w, r], axis=1)
    coeffs, *_ = np.linalg.lstsq(design, t, rcond=None)
    residuals = t - design @ coeffs
    return TorqueStats(
        coeffs=(float(coeffs[0]), float(coeffs[1]), float(coeffs[2])),
        residual_rms_nm=float(np.sqrt(np.mean(residuals**2))),
        hard_wheel_rad=float(np.percentile(w, 90.0)),
        hard_rate_rad_per_s=float(np.percentile(r, 90.0)),
        moving=int(w.size),
        stalls=stalls,
        stall_fraction=stalls / int(np.sum(working)),
        rejected=rejected,
    )


class TorqueRecorder:
    """Collects (wheel, rate, torque) samples; shows how many are usable while they come."""

    def __init__(self, params: TorqueParams = TorqueParams()) -> None:
        self._params = params
        self._columns: tuple[list[float], list[float], list[float]] = ([], [], [])

    def reset(self) -> None:
        for column in self._columns:
            column.clear()

    def update(self, wheel_rad: float, wheel_rate_rad_per_s: float, torque_nm: float) -> None:
        values = (wheel_rad, wheel_rate_rad_per_s, torque_nm)
        if not all(math.isfinite(v) for v in values):
            raise ValueError(f"non-finite sample: {values}")
        for column, value in zip(self._columns, values, strict=True):
            column.append(value)

    def coverage(self) -> tuple[int, int]:
        """(moving, stalled) working samples so far: moving ones are what the fit needs."""
        _, rate, torque = (np.array(c) for c in self._columns)
        working = np.abs(torque) >= self._params.active_torque_nm
        moving = working & (np.abs(rate) >= self._params.stall_rate_rad_per_s)
        return int(np.sum(moving)), int(np.sum(working & ~moving))

    def stats(self) -> TorqueStats:
        wheel, rate, torque = (np.array(c) for c in self._columns)
        return torque_stats(wheel, rate, torque, self._params)


@dataclass(frozen=True)
class TorqueComparison:
    baseline_needed_nm: float  # at the baseline's hard wheel angle and rate
    current_needed_nm: float  # the same point, by the current fit
    relative_change: float
    stall_fraction_change: float
    retune: bool
    reasons: tuple[str, ...]
    method: str = METHOD


def compare_torque(
    baseline: TorqueStats, current: TorqueStats, params: TorqueParams = TorqueParams()
) -> TorqueComparison:
    """Flag re-tuning the look-ahead when the servo's torque changed beyond the thresholds."""
    point = (baseline.hard_wheel_rad, baseline.hard_rate_rad_per_s)
    then, now = baseline.needed_torque_nm(*point), current.needed_torque_nm(*point)
    change = (now - then) / then
    reasons: list[str] = []
    if abs(change) > params.max_change:
        reasons.append(
            f"the wheel needs {now:.2f} N m at {point[0]:.1f} rad and {point[1]:.1f} rad/s, "
            f"against {then:.2f} N m at tuning ({100 * change:+.0f} %, limit "
            f"{100 * params.max_change:.0f} %)"
        )
    stall_change = current.stall_fraction - baseline.stall_fraction
    if stall_change > params.max_stall_increase:
        reasons.append(
            f"the servo stalls {100 * current.stall_fraction:.0f} % of its working time "
            f"(baseline {100 * baseline.stall_fraction:.0f} %): it runs short of torque"
        )
    return TorqueComparison(then, now, change, stall_change, bool(reasons), tuple(reasons))
