"""Qian et al.'s EKF (eqs. 1-10): the pose of the scanners' midpoint in the launcher frame.

State ``(x_m, y_m, yaw_rad)`` of O_f, the point midway between the two scanners (Fig. 7):
chosen there, as the paper says, so that the estimate's uncertainty propagates least to
where it is measured. Built on filterpy's ``ExtendedKalmanFilter`` for the update (its
update is the Joseph form, which stays symmetric and positive where ``(I - KH)P`` of
eq. 10 does not); the prediction is our own, because filterpy's ``predict()`` is linear
and the motion here is the compounding ``x ⊕ u`` of eq. 2.

What this adds to the paper, and why:
- the covariance is propagated with the compounding's Jacobians, not by ``P + Q`` (eq. 3
  holds only near ψ = 0; a filter that must also pass ψ = ±π cannot use it);
- every measurement is gated by the χ² quantile of its own dimension before it is used,
  and every rejection is counted by kind, so a false cylinder (a post, a person next to
  a landmark) cannot pull the pose, and the count says how often it tried;
- after a long run of rejections the covariance is inflated instead of the filter
  rejecting forever on its own overconfidence (the classic lock-out);
- the front board is a measurement (it fixes x and ψ directly: in the vehicle frame the
  board is the line ``(r, α) = (-x, -ψ)``), not only the control input, so the jumps the
  paper saw between estimates are smoothed rather than passed through;
- ψ is wrapped after every step, bearing residuals are wrapped before they are used.
Time is an argument: ``predict`` moves the filter to a measurement's time, and a
measurement older than the filter (another scanner's scan already used) is refused.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numpy.typing import NDArray
from scipy.stats import chi2

from appliance.localization.compound import compound, compound_jacobians, wrap_angle_rad
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class EkfParams:
    # A measurement is used when its NIS is below this quantile of χ²(dim z).
    gate_probability: float = 0.999
    # Process noise grows with the motion (Qian et al.: Q "decided by the value of u"):
    # σ of translation per metre moved, σ of heading per radian turned and per metre.
    translation_noise_per_m: float = 0.02
    heading_noise_per_rad: float = 0.02
    heading_noise_per_m_rad: float = 0.002
    # And with time, for what the motion input misses (a jerk of the hydraulics).
    translation_noise_per_sqrt_s_m: float = 0.002
    heading_noise_per_sqrt_s_rad: float = 0.0002
    # After this many consecutive rejections of one kind, inflate P by this factor.
    inflate_after_rejections: int = 10
    inflation_factor: float = 4.0
    # A measurement older than the filter by more than this is out of order.
    reorder_tolerance_s: float = 0.002

    def __post_init__(self) -> None:
        if not 0.5 < self.gate_probability < 1.0:
            raise ValueError(f"gate_probability must be in (0.5, 1), got {self.gate_probability}")
        if self.inflate_after_rejections < 1 or not self.inflation_factor > 1.0:
            raise ValueError("inflation needs inflate_after_rejections >= 1 and a factor > 1")


@dataclass(frozen=True)
class BodyMotion:
    """The vehicle's motion as the front board shows it: O_f's velocity in its own frame
    (vx, vy in m/s, yaw rate in rad/s) and that estimate's 3×3 covariance.

    ``correlation_time_s``: how long the velocity's error stays the same. A velocity read
    over a window keeps its error for the window's length, so integrated over ``dt`` it
    adds ``cov · dt · T`` of variance per step, not ``cov · dt²`` (which would let the
    filter believe that the same error averages out over the window's steps)."""

    velocity: FloatArray
    covariance: FloatArray
    correlation_time_s: float = 0.0

    @staticmethod
    def still(sigma_mps: float = 0.05, sigma_radps: float = 0.005) -> BodyMotion:
        """No motion known: standing still, with the uncertainty of a vehicle that might
        be creeping (used before two board lines have been seen)."""
        return BodyMotion(
            np.zeros(3), np.diag([sigma_mps**2, sigma_mps**2, sigma_radps**2]).astype(float)
        )


@dataclass(frozen=True)
class UpdateOutcome:
    accepted: bool
    kind: str
    nis: float
    reason: str = ""


def cylinder_measurement(
    state: FloatArray, landmark_xy: tuple[float, float], sensor: Pose2D
) -> tuple[FloatArray, FloatArray]:
    """Eq. 5: range and bearing of a landmark from a scanner, and their Jacobian.

    ``sensor`` is the scanner's pose in the O_f frame (its own offset, as the paper's
    ``(x_L, y_L)``); the bearing is in the scanner's frame (x out of its window), so the
    paper's ``+ π/2`` (the device's angle convention) is already taken out upstream.
    """
    x, y, yaw = float(state[0]), float(state[1]), float(state[2])
    c, s = math.cos(yaw), math.sin(yaw)
    sx = x + c * sensor.x_m - s * sensor.y_m
    sy = y + s * sensor.x_m + c * sensor.y_m
    dsx_dyaw = -s * sensor.x_m - c * sensor.y_m
    dsy_dyaw = c * sensor.x_m - s * sensor.y_m
    dx, dy = landmark_xy[0] - sx, landmark_xy[1] - sy
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    z = np.array([r, wrap_angle_rad(math.atan2(dy, dx) - yaw - sensor.yaw_rad)])
    jac = np.array(
        [
            [-dx / r, -dy / r, -(dx * dsx_dyaw + dy * dsy_dyaw) / r],
            [dy / q, -dx / q, (dy * dsx_dyaw - dx * dsy_dyaw) / q - 1.0],
        ]
    )
    return z, jac


def board_measurement(state: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The front board (the launcher's line x = 0) as (r, α) in the O_f frame, and its
    Jacobian: ``r = -x`` (positive in front of the board), ``α = -ψ``."""
    z = np.array([-float(state[0]), wrap_angle_rad(-float(state[2]))])
    return z, np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def _residual(z: FloatArray, z_hat: FloatArray) -> FloatArray:
    return np.array([z[0] - z_hat[0], wrap_angle_rad(float(z[1] - z_hat[1]))])


def _cylinder_model(
    landmark_xy: tuple[float, float], sensor: Pose2D
) -> Callable[[FloatArray], tuple[FloatArray, FloatArray]]:
    return lambda state: cylinder_measurement(state, landmark_xy, sensor)


class LauncherEkf:
    """The filter: ``reset`` from an initial pose, then ``predict`` and ``update_*``."""

    def __init__(self, params: EkfParams | None = None) -> None:
        self.params = params or EkfParams()
        self._gate_2d = float(chi2.ppf(self.params.gate_probability, 2))
        self._kf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
        self.t_s: float | None = None
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.inflations = 0
        self._rejection_run: Counter[str] = Counter()
        self.last_nis: dict[str, float] = {}

    @property
    def initialized(self) -> bool:
        return self.t_s is not None

    @property
    def state(self) -> FloatArray:
        return np.asarray(self._kf.x, dtype=float).reshape(3).copy()

    @property
    def covariance(self) -> FloatArray:
        return np.asarray(self._kf.P, dtype=float).copy()

    @property
    def pose(self) -> Pose2D:
        x = self.state
        return Pose2D(float(x[0]), float(x[1]), float(x[2]))

    def reset(
        self, pose: Pose2D | None = None, covariance: FloatArray | None = None, t_s: float = 0.0
    ) -> None:
        """Forget everything; with a pose, start from it (the initial pose, 3.2.3 a)."""
        self._kf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
        self.accepted.clear()
        self.rejected.clear()
        self._rejection_run.clear()
        self.last_nis.clear()
        self.inflations = 0
        if pose is None:
            self.t_s = None
            return
        if covariance is None or np.shape(covariance) != (3, 3):
            raise ValueError("an initial pose needs its 3x3 covariance")
        self._kf.x = np.array([pose.x_m, pose.y_m, wrap_angle_rad(pose.yaw_rad)])
        self._kf.P = np.array(covariance, dtype=float)
        self.t_s = t_s

    def process_noise(self, delta: FloatArray, dt_s: float) -> FloatArray:
        """Q for a motion ``delta`` over ``dt_s``: grows with the distance and the turn."""
        p = self.params
        moved_m = math.hypot(float(delta[0]), float(delta[1]))
        root_dt = math.sqrt(max(dt_s, 0.0))
        sigma_t = p.translation_noise_per_m * moved_m + p.translation_noise_per_sqrt_s_m * root_dt
        sigma_r = (
            p.heading_noise_per_rad * abs(float(delta[2]))
            + p.heading_noise_per_m_rad * moved_m
            + p.heading_noise_per_sqrt_s_rad * root_dt
        )
        return np.diag([sigma_t**2, sigma_t**2, sigma_r**2])

    def predict(self, t_s: float, motion: BodyMotion) -> bool:
        """Eqs. 2-3: move the estimate to ``t_s`` with the board's motion. False (and
        nothing changes) when ``t_s`` is before the filter's time: out of order."""
        if self.t_s is None:
            raise RuntimeError("predict before reset: the filter has no initial pose")
        dt_s = t_s - self.t_s
        if dt_s < -self.params.reorder_tolerance_s:
            self.rejected["out_of_order"] += 1
            return False
        if dt_s <= 0.0:
            return True
        delta = np.asarray(motion.velocity, dtype=float) * dt_s
        q_delta = (
            np.asarray(motion.covariance, dtype=float) * dt_s * max(dt_s, motion.correlation_time_s)
        )
        q_delta = q_delta + self.process_noise(delta, dt_s)
        x = self.state
        j_pose, j_delta = compound_jacobians(x, delta)
        self._kf.x = compound(x, delta)
        self._kf.P = j_pose @ self._kf.P @ j_pose.T + j_delta @ q_delta @ j_delta.T
        self.t_s = t_s
        return True

    def update_cylinder(
        self,
        z: FloatArray,
        r_cov: FloatArray,
        landmark_xy: tuple[float, float],
        sensor: Pose2D,
        kind: str = "cylinder",
    ) -> UpdateOutcome:
        """Eqs. 5-10 for one cylinder's (range, bearing) seen by one scanner."""
        return self._update(
            kind,
            np.asarray(z, dtype=float),
            np.asarray(r_cov, dtype=float),
            lambda state: cylinder_measurement(state, landmark_xy, sensor),
        )

    def update_board(self, z: FloatArray, r_cov: FloatArray) -> UpdateOutcome:
        """The front board's (r, α) in the O_f frame, as a measurement of x and ψ."""
        return self._update(
            "board", np.asarray(z, dtype=float), np.asarray(r_cov, dtype=float), board_measurement
        )

    def innovation(
        self, z: FloatArray, r_cov: FloatArray, landmark_xy: tuple[float, float], sensor: Pose2D
    ) -> float:
        """The NIS a cylinder measurement would have against ``landmark_xy``, for
        association: the localizer gives a detected cylinder to the landmark it fits best."""
        return self._nis(z, r_cov, _cylinder_model(landmark_xy, sensor))

    def update_nearest_cylinder(
        self,
        z: FloatArray,
        r_cov: FloatArray,
        landmarks_xy: Sequence[tuple[float, float]],
        sensor: Pose2D,
    ) -> tuple[int, UpdateOutcome]:
        """`update_cylinder` with the landmark of the smallest `innovation` (the first of
        equals): its index and the outcome. The same as choosing with ``innovation`` and
        then updating, without working out the chosen one's NIS twice."""
        if not landmarks_xy:
            raise ValueError("no landmark to associate the cylinder with")
        z = np.asarray(z, dtype=float)
        r_cov = np.asarray(r_cov, dtype=float)
        models = [_cylinder_model(xy, sensor) for xy in landmarks_xy]
        if z.shape != (2,) or r_cov.shape != (2, 2) or not np.all(np.isfinite(z)):
            return 0, self._update("cylinder", z, r_cov, models[0])
        nis = [self._nis(z, r_cov, model) for model in models]
        best = min(range(len(nis)), key=nis.__getitem__)
        return best, self._update("cylinder", z, r_cov, models[best], known_nis=nis[best])

    def _nis(
        self,
        z: FloatArray,
        r_cov: FloatArray,
        model: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
    ) -> float:
        z_hat, h = model(self.state)
        y = _residual(np.asarray(z, dtype=float), z_hat)
        s = h @ self._kf.P @ h.T + r_cov
        return float(y @ np.linalg.solve(s, y))

    def _update(
        self,
        kind: str,
        z: FloatArray,
        r_cov: FloatArray,
        model: Callable[[FloatArray], tuple[FloatArray, FloatArray]],
        known_nis: float | None = None,
    ) -> UpdateOutcome:
        """``known_nis``: the NIS of ``model`` at the present state, already worked out."""
        if self.t_s is None:
            raise RuntimeError("update before reset: the filter has no initial pose")
        if z.shape != (2,) or r_cov.shape != (2, 2) or not np.all(np.isfinite(z)):
            self.rejected[f"{kind}:malformed"] += 1
            return UpdateOutcome(False, kind, math.nan, "malformed measurement")
        if known_nis is not None:
            nis = known_nis
        else:
            try:
                nis = self._nis(z, r_cov, model)
            except np.linalg.LinAlgError:
                self.rejected[f"{kind}:singular"] += 1
                return UpdateOutcome(False, kind, math.nan, "singular innovation covariance")
        self.last_nis[kind] = nis
        if not nis <= self._gate_2d:
            self.rejected[kind] += 1
            self._rejection_run[kind] += 1
            if self._rejection_run[kind] >= self.params.inflate_after_rejections:
                self._kf.P = self._kf.P * self.params.inflation_factor
                self._rejection_run[kind] = 0
                self.inflations += 1
            return UpdateOutcome(False, kind, nis, f"gated: NIS {nis:.1f} > {self._gate_2d:.1f}")
        self._rejection_run[kind] = 0
        self._kf.x = self.state
        self._kf.update(
            z,
            lambda state: model(state)[1],
            lambda state: model(state)[0],
            R=r_cov,
            residual=_residual,
        )
        x = self.state
        x[2] = wrap_angle_rad(float(x[2]))
        self._kf.x = x
        p = self._kf.P
        self._kf.P = 0.5 * (p + p.T)
        self.accepted[kind] += 1
        return UpdateOutcome(True, kind, nis)
