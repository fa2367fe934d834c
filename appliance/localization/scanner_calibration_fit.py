"""Steps 2 and 3 of the scanner calibration: the measurement model, the weighted least
squares fit of (δr, δψ, δx, δy) to the kept points, and what the docked pose's tolerance
adds to the fit's covariance.

The parameters are the range offset δr (subtracted from every range), the mount's yaw
error δψ, and its position errors δx, δy along the *vehicle's* axes, which at the docked
pose split cleanly (see :mod:`appliance.localization.scanner_calibration`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from appliance.localization.scanner_calibration_params import DockedPose
from appliance.localization.scanner_calibration_points import LandmarkPoints
from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]

PARAMETER_NAMES: Final = ("range_offset", "mount_yaw", "longitudinal", "lateral")
RANGE_OFFSET, MOUNT_YAW, LONGITUDINAL, LATERAL = range(4)  # indices into θ
# The normal matrix's condition beyond which a parameter is not determined at all (metres
# and radians at ranges of metres are of one scale, so this is a geometric statement).
MAX_CONDITION: Final = 1e12


def point_residuals(
    theta: FloatArray, points: LandmarkPoints, vehicle: Pose2D, mount: Pose2D
) -> tuple[FloatArray, FloatArray]:
    """Each point's residual (m) under θ = (δr, δψ, δx, δy), and its Jacobian (N, 4).

    The scanner sits at ``vehicle ∘ (mount + (δx, δy, δψ))``; the point is its range less
    δr along its beam. A board point's residual is its x in the launcher frame, a
    cylinder point's its distance from the centre less the radius.
    """
    d_range, d_yaw, d_x, d_y = (float(v) for v in theta)
    c, s = math.cos(vehicle.yaw_rad), math.sin(vehicle.yaw_rad)
    mx, my = mount.x_m + d_x, mount.y_m + d_y
    sx = vehicle.x_m + c * mx - s * my
    sy = vehicle.y_m + s * mx + c * my
    beam = points.angles_rad + (vehicle.yaw_rad + mount.yaw_rad + d_yaw)
    wx, wy = np.cos(beam), np.sin(beam)
    r = points.ranges_m - d_range
    px, py = sx + r * wx, sy + r * wy
    gx = np.ones_like(px)
    gy = np.zeros_like(py)
    residual = px.copy()
    cyl = ~points.is_board
    if np.any(cyl):
        dx = px[cyl] - points.centres[cyl, 0]
        dy = py[cyl] - points.centres[cyl, 1]
        dist = np.maximum(np.hypot(dx, dy), 1e-12)
        residual[cyl] = dist - points.radii_m[cyl]
        gx[cyl], gy[cyl] = dx / dist, dy / dist
    jac = np.empty((px.size, 4))
    jac[:, RANGE_OFFSET] = -(gx * wx + gy * wy)
    jac[:, MOUNT_YAW] = r * (gy * wx - gx * wy)  # g · perp(beam)
    jac[:, LONGITUDINAL] = gx * c + gy * s  # g · R(vehicle yaw) e_x
    jac[:, LATERAL] = -gx * s + gy * c  # g · R(vehicle yaw) e_y
    return residual, jac


@dataclass(frozen=True)
class PointFit:
    """θ fitted to the points, with its covariance from the points alone."""

    theta: FloatArray
    covariance: FloatArray  # statistical, scaled by the residuals' variance
    residuals_m: FloatArray
    scale: float  # rms of the whitened residuals


class FitFailed(Exception):
    """The points gave no finite, determined fit; the message says which."""


def solve(points: LandmarkPoints, vehicle: Pose2D, mount: Pose2D) -> PointFit:
    """θ from the points whitened by their σ's (from θ = 0); the covariance is the inverse
    normal matrix scaled by the whitened residuals' own variance."""
    weights = 1.0 / points.sigmas_m

    def fun(theta: FloatArray) -> FloatArray:
        residual, _ = point_residuals(theta, points, vehicle, mount)
        whitened: FloatArray = residual * weights
        return whitened

    def jac(theta: FloatArray) -> FloatArray:
        _, jacobian = point_residuals(theta, points, vehicle, mount)
        whitened: FloatArray = jacobian * weights[:, None]
        return whitened

    try:
        solution = least_squares(fun, np.zeros(4), jac=jac, method="trf", x_scale="jac")
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise FitFailed(str(exc)) from None
    theta = np.asarray(solution.x, dtype=np.float64)
    residual, jacobian = point_residuals(theta, points, vehicle, mount)
    whitened = jacobian * weights[:, None]
    normal = whitened.T @ whitened
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(normal))):
        raise FitFailed("the fit did not stay finite")
    degenerate = "the points do not determine the parameters (degenerate geometry)"
    try:
        if not np.linalg.cond(normal) <= MAX_CONDITION:
            raise FitFailed(degenerate)
        inverse = np.asarray(np.linalg.inv(normal), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise FitFailed(degenerate) from None
    dof = max(residual.size - theta.size, 1)
    scale = math.sqrt(float(np.sum((residual * weights) ** 2)) / dof)
    covariance: FloatArray = inverse * scale**2
    return PointFit(theta, covariance, residual, scale)


def pose_covariance(mount: Pose2D, docked: DockedPose) -> FloatArray:
    """What the docked pose's tolerance does to (δr, δψ, δx, δy): a vehicle moved by
    (ex, ey) and turned by eψ about the pivot moves the fitted mount by the same, in the
    vehicle's axes (the scanners' pose on the launcher is what the points fix)."""
    jac = np.zeros((4, 3))  # rows δr, δψ, δx, δy; columns ex, ey, eψ
    jac[LONGITUDINAL, 0] = 1.0
    jac[LATERAL, 1] = 1.0
    jac[MOUNT_YAW, 2] = 1.0
    jac[LONGITUDINAL, 2] = -mount.y_m
    jac[LATERAL, 2] = mount.x_m - docked.pivot_forward_m
    tolerances = np.array(
        [docked.longitudinal_tolerance_m, docked.lateral_tolerance_m, docked.heading_tolerance_rad]
    )
    result: FloatArray = jac @ np.diag(tolerances**2) @ jac.T
    return result
