"""Qian et al.'s EKF (eqs. 1-10): the pose of the scanners' midpoint in the launcher frame.

State ``(x_m, y_m, yaw_rad)`` of O_f, the point midway between the two scanners (Fig. 7):
chosen there, as the paper says, so that the estimate's uncertainty propagates least to
where it is measured. The update's covariance is the Joseph form (it stays symmetric and
positive where ``(I - KH)P`` of eq. 10 does not), as filterpy's ``ExtendedKalmanFilter``
has it; the prediction is the compounding ``x ⊕ u`` of eq. 2. The algebra is done in
floats (``ekf_floats``): at 3x3 numpy's calls cost several times their arithmetic, and
the tests hold it to filterpy's and numpy's to rounding.

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
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.ekf_floats import joseph_update, nis_2d, propagate
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]
# A measurement model: the state (x, y, yaw) to the predicted measurement and its
# Jacobian, as floats.
Terms = tuple[list[float], list[list[float]]]
Model = Callable[[list[float]], Terms]


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
    z, jac = cylinder_terms(state, landmark_xy, sensor)
    return np.array(z), np.array(jac)


def cylinder_terms(
    state: Sequence[float] | FloatArray, landmark_xy: tuple[float, float], sensor: Pose2D
) -> Terms:
    """`cylinder_measurement` as floats: the association works out the NIS of every
    landmark, and arrays are only needed for the one the filter is updated with."""
    x, y, yaw = float(state[0]), float(state[1]), float(state[2])
    c, s = math.cos(yaw), math.sin(yaw)
    sx = x + c * sensor.x_m - s * sensor.y_m
    sy = y + s * sensor.x_m + c * sensor.y_m
    dsx_dyaw = -s * sensor.x_m - c * sensor.y_m
    dsy_dyaw = c * sensor.x_m - s * sensor.y_m
    dx, dy = landmark_xy[0] - sx, landmark_xy[1] - sy
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    z = [r, wrap_angle_rad(math.atan2(dy, dx) - yaw - sensor.yaw_rad)]
    jac = [
        [-dx / r, -dy / r, -(dx * dsx_dyaw + dy * dsy_dyaw) / r],
        [dy / q, -dx / q, (dy * dsx_dyaw - dx * dsy_dyaw) / q - 1.0],
    ]
    return z, jac


def board_measurement(state: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The front board (the launcher's line x = 0) as (r, α) in the O_f frame, and its
    Jacobian: ``r = -x`` (positive in front of the board), ``α = -ψ``."""
    z, jac = _board_terms(state)
    return np.array(z), np.array(jac)


def _board_terms(state: Sequence[float] | FloatArray) -> Terms:
    """`board_measurement` as floats."""
    return (
        [-float(state[0]), wrap_angle_rad(-float(state[2]))],
        [[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]],
    )


def _cylinder_model(landmark_xy: tuple[float, float], sensor: Pose2D) -> Model:
    return lambda state: cylinder_terms(state, landmark_xy, sensor)


def _well_formed(z: FloatArray, r_cov: FloatArray) -> bool:
    """A 2-vector of finite values and a 2x2 covariance: what an update can use."""
    return (
        z.shape == (2,)
        and r_cov.shape == (2, 2)
        and math.isfinite(float(z[0]))
        and math.isfinite(float(z[1]))
    )


class _Innovation(NamedTuple):
    """A measurement's NIS at the filter's present state, and the model's prediction
    ``z_hat`` and Jacobian ``h`` there."""

    nis: float
    z_hat: list[float]
    h: list[list[float]]
    residual: tuple[float, float]  # z − z_hat, the bearing's wrapped
    r: list[list[float]]  # the measurement's covariance, as floats


class LauncherEkf:
    """The filter: ``reset`` from an initial pose, then ``predict`` and ``update_*``."""

    def __init__(self, params: EkfParams | None = None) -> None:
        self.params = params or EkfParams()
        # χ²(2)'s quantile in closed form: its distribution function is 1 − e^(−x/2).
        self._gate_2d = -2.0 * math.log1p(-self.params.gate_probability)
        self._x: list[float] = [0.0, 0.0, 0.0]
        self._p: list[list[float]] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
        self.t_s: float | None = None
        self.accepted: Counter[str] = Counter()
        self.rejected: Counter[str] = Counter()
        self.inflations = 0
        self._rejection_run: Counter[str] = Counter()
        self.last_nis: dict[str, float] = {}

    @property
    def gate_2d(self) -> float:
        """The NIS beyond which a 2-D measurement (a cylinder, the board) is kept out."""
        return self._gate_2d

    @property
    def initialized(self) -> bool:
        return self.t_s is not None

    @property
    def state(self) -> FloatArray:
        return np.array(self._x)

    @property
    def covariance(self) -> FloatArray:
        return np.array(self._p)

    @property
    def state_floats(self) -> tuple[float, float, float]:
        """`state` as floats, for the callers that do scalar arithmetic with it."""
        x, y, yaw = self._x
        return x, y, yaw

    @property
    def pose(self) -> Pose2D:
        x = self.state
        return Pose2D(float(x[0]), float(x[1]), float(x[2]))

    def reset(
        self, pose: Pose2D | None = None, covariance: FloatArray | None = None, t_s: float = 0.0
    ) -> None:
        """Forget everything; with a pose, start from it (the initial pose, 3.2.3 a)."""
        self._x = [0.0, 0.0, 0.0]
        self._p = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
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
        self._x = [float(pose.x_m), float(pose.y_m), wrap_angle_rad(float(pose.yaw_rad))]
        self._p = np.asarray(covariance, dtype=float).tolist()
        self.t_s = t_s

    def process_noise(self, delta: FloatArray, dt_s: float) -> FloatArray:
        """Q for a motion ``delta`` over ``dt_s``: grows with the distance and the turn."""
        dx_m, dy_m, dyaw_rad = (float(v) for v in delta[:3])
        noise: FloatArray = np.array(self._process_noise(dx_m, dy_m, dyaw_rad, dt_s))
        return noise

    def _process_noise(
        self, dx_m: float, dy_m: float, dyaw_rad: float, dt_s: float
    ) -> list[list[float]]:
        p = self.params
        moved_m = math.hypot(dx_m, dy_m)
        root_dt = math.sqrt(max(dt_s, 0.0))
        sigma_t = p.translation_noise_per_m * moved_m + p.translation_noise_per_sqrt_s_m * root_dt
        sigma_r = (
            p.heading_noise_per_rad * abs(dyaw_rad)
            + p.heading_noise_per_m_rad * moved_m
            + p.heading_noise_per_sqrt_s_rad * root_dt
        )
        t2, r2 = sigma_t**2, sigma_r**2
        return [[t2, 0.0, 0.0], [0.0, t2, 0.0], [0.0, 0.0, r2]]

    def predict(self, t_s: float, motion: BodyMotion) -> bool:
        """Eqs. 2-3: move the estimate to ``t_s`` with the board's motion. False (and
        nothing changes) when ``t_s`` is before the filter's time: out of order.

        The covariance goes through the compounding's Jacobians (``compound``), written
        out here in floats."""
        if self.t_s is None:
            raise RuntimeError("predict before reset: the filter has no initial pose")
        dt_s = t_s - self.t_s
        if dt_s < -self.params.reorder_tolerance_s:
            self.rejected["out_of_order"] += 1
            return False
        if dt_s <= 0.0:
            return True
        vx, vy, vyaw = motion.velocity.tolist()
        dx, dy, dyaw = vx * dt_s, vy * dt_s, vyaw * dt_s
        longest = max(dt_s, motion.correlation_time_s)
        noise = self._process_noise(dx, dy, dyaw, dt_s)
        q_delta = [
            [v * dt_s * longest + n for v, n in zip(row, noise_row, strict=True)]
            for row, noise_row in zip(motion.covariance.tolist(), noise, strict=True)
        ]
        x, y, yaw = self._x
        c, s = math.cos(yaw), math.sin(yaw)
        j_pose = [[1.0, 0.0, -s * dx - c * dy], [0.0, 1.0, c * dx - s * dy], [0.0, 0.0, 1.0]]
        j_delta = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
        self._x = [x + c * dx - s * dy, y + s * dx + c * dy, wrap_angle_rad(yaw + dyaw)]
        self._p = propagate(self._p, j_pose, j_delta, q_delta)
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
            _cylinder_model(landmark_xy, sensor),
        )

    def update_board(self, z: FloatArray, r_cov: FloatArray) -> UpdateOutcome:
        """The front board's (r, α) in the O_f frame, as a measurement of x and ψ."""
        return self._update(
            "board", np.asarray(z, dtype=float), np.asarray(r_cov, dtype=float), _board_terms
        )

    def innovation(
        self, z: FloatArray, r_cov: FloatArray, landmark_xy: tuple[float, float], sensor: Pose2D
    ) -> float:
        """The NIS a cylinder measurement would have against ``landmark_xy``, for
        association: the localizer gives a detected cylinder to the landmark it fits best."""
        z, r_cov = np.asarray(z, dtype=float), np.asarray(r_cov, dtype=float)
        return self._innovations(z, r_cov, [_cylinder_model(landmark_xy, sensor)])[0].nis

    def update_nearest_cylinder(
        self,
        z: FloatArray,
        r_cov: FloatArray,
        landmarks_xy: Sequence[tuple[float, float]],
        sensor: Pose2D,
    ) -> tuple[int, UpdateOutcome]:
        """`update_cylinder` with the landmark of the smallest `innovation` (the first of
        equals): its index and the outcome. The same as choosing with ``innovation`` and
        then updating, without working out the chosen one's NIS, prediction and Jacobian
        twice."""
        if not landmarks_xy:
            raise ValueError("no landmark to associate the cylinder with")
        z = np.asarray(z, dtype=float)
        r_cov = np.asarray(r_cov, dtype=float)
        models = [_cylinder_model(xy, sensor) for xy in landmarks_xy]
        if not _well_formed(z, r_cov):
            return 0, self._update("cylinder", z, r_cov, models[0])
        try:
            found = self._innovations(z, r_cov, models)
        except ZeroDivisionError:
            self.rejected["cylinder:singular"] += 1
            return 0, UpdateOutcome(False, "cylinder", math.nan, "singular innovation covariance")
        best = min(range(len(found)), key=lambda k: found[k].nis)
        return best, self._update("cylinder", z, r_cov, models[best], known=found[best])

    def _innovations(
        self, z: FloatArray, r_cov: FloatArray, models: Sequence[Model]
    ) -> list[_Innovation]:
        """The NIS of a measurement under each model at the present state, with the
        model's prediction and Jacobian there (which the update then reuses: the state
        has not moved). In floats: these are 2x2 and 2x3."""
        state, p, r = self._x, self._p, r_cov.tolist()
        z0, z1 = float(z[0]), float(z[1])
        found = []
        for model in models:
            z_hat, h = model(state)
            y0, y1 = z0 - z_hat[0], wrap_angle_rad(z1 - z_hat[1])
            found.append(_Innovation(nis_2d(h, p, r, y0, y1), z_hat, h, (y0, y1), r))
        return found

    def _update(
        self,
        kind: str,
        z: FloatArray,
        r_cov: FloatArray,
        model: Model,
        known: _Innovation | None = None,
    ) -> UpdateOutcome:
        """``known``: the `_innovations` of ``model`` at the present state, worked out."""
        if self.t_s is None:
            raise RuntimeError("update before reset: the filter has no initial pose")
        if not _well_formed(z, r_cov):
            self.rejected[f"{kind}:malformed"] += 1
            return UpdateOutcome(False, kind, math.nan, "malformed measurement")
        if known is None:
            try:
                known = self._innovations(z, r_cov, [model])[0]
            except ZeroDivisionError:
                self.rejected[f"{kind}:singular"] += 1
                return UpdateOutcome(False, kind, math.nan, "singular innovation covariance")
        nis = known.nis
        self.last_nis[kind] = nis
        if not nis <= self._gate_2d:
            self.rejected[kind] += 1
            self._rejection_run[kind] += 1
            if self._rejection_run[kind] >= self.params.inflate_after_rejections:
                factor = self.params.inflation_factor
                self._p = [[v * factor for v in row] for row in self._p]
                self._rejection_run[kind] = 0
                self.inflations += 1
            return UpdateOutcome(False, kind, nis, f"gated: NIS {nis:.1f} > {self._gate_2d:.1f}")
        # The model's prediction and Jacobian at the present state: `known`'s.
        updated = joseph_update(self._x, self._p, known.h, known.r, known.residual)
        if updated is None:
            self.rejected[f"{kind}:singular"] += 1
            return UpdateOutcome(False, kind, nis, "singular innovation covariance")
        self._rejection_run[kind] = 0
        x, self._p = updated
        x[2] = wrap_angle_rad(x[2])
        self._x = x
        self.accepted[kind] += 1
        return UpdateOutcome(True, kind, nis)
