"""The first pose, with no prior (Qian et al. 3.2.3 a): from the front board in view.

The front board is the one line of its width (3 m by default) whose two ends are true
ends, facing the vehicle: its (r, α) fixes x and ψ (in the O_f frame the board is
``(r, α) = (-x, -ψ)``), and its midpoint is the launcher's origin, which fixes y. Each
scanner gives its own answer; with both in view they must agree, and the answer is their
information-weighted mean. Refusal is the safe default, with a reason a person can act
on: a board partly hidden (a person walking past, the default site has one) has an
occluded end and is not taken; two candidates are ambiguous; a board too far or too
close is out of range.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.launcher_map import LauncherMap
from appliance.perception.types import LineFeature, ScanFeatures
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class InitialPoseParams:
    # The board's visible length may differ from its width by this much (ends are cut by
    # the beam spacing and the footprint), plus a fraction of the width.
    length_tolerance_m: float = 0.12
    length_tolerance_fraction: float = 0.04
    min_range_m: float = 0.5
    max_range_m: float = 15.0  # the "automatic navigation zone" is about 10 m out
    max_heading_rad: float = math.radians(30.0)
    # Both scanners' answers must agree this well.
    agree_position_m: float = 0.10
    agree_heading_rad: float = math.radians(1.0)
    # How well a board end is known along the board (``board_end_sigma_m``): the beam
    # spacing and the LMS111's footprint (8 mm + 15 mrad x range), stretched by grazing
    # incidence (capped at this cosine), plus a floor.
    beam_step_rad: float = math.radians(0.25)
    footprint_exit_m: float = 0.008
    footprint_divergence_rad: float = 0.015
    min_cos_incidence: float = 0.2
    end_sigma_floor_m: float = 0.005
    # The scanners' answers agree when their difference passes this χ² gate (3 dof).
    agree_probability: float = 0.999
    # The scanners' systematic errors, unless calibrated: ±30 mm range, a few tenths of
    # a degree of mount yaw. They enter as a floor on the covariance.
    systematic_range_sigma_m: float = 0.02
    systematic_yaw_sigma_rad: float = math.radians(0.3)


@dataclass(frozen=True)
class InitialPose:
    pose: Pose2D  # O_f in the launcher frame
    covariance: FloatArray
    sensors: tuple[str, ...]


@dataclass(frozen=True)
class InitialPoseRefusal:
    reason: str


def _candidates(
    features: ScanFeatures, launcher: LauncherMap, params: InitialPoseParams
) -> tuple[list[LineFeature], str]:
    width = launcher.front_board_width_m
    tolerance = params.length_tolerance_m + params.length_tolerance_fraction * width
    whole, partial, far = [], 0, 0
    for line in features.lines:
        if abs(wrap_angle_rad(line.alpha_rad)) > params.max_heading_rad:
            continue  # not facing the vehicle: a side board, a wall beside
        if not params.min_range_m <= line.r_m <= params.max_range_m:
            far += 1 if abs(line.length_m - width) <= tolerance else 0
            continue
        if abs(line.length_m - width) <= tolerance:
            if line.start_occluded or line.end_occluded:
                partial += 1
            else:
                whole.append(line)
        elif line.length_m < width and (line.start_occluded or line.end_occluded):
            partial += 1
    if whole:
        return whole, ""
    if far:
        return [], "launcher out of range"
    if partial:
        return [], "front board partly hidden"
    return [], "launcher not in view"


def board_end_sigma_m(
    end_xy_m: tuple[float, float],
    sensor: Pose2D,
    normal: FloatArray | tuple[float, float],
    params: InitialPoseParams,
) -> float:
    """How well a board's true end is known along the board.

    The end lies somewhere between two beams, and the beam's footprint makes the board
    look longer by up to half a footprint; both stretch along the board as the beam
    grazes it (divided by the cosine of the incidence). So an end seen head-on and near
    is worth far more than one seen at a slant and far.
    """
    ray_x, ray_y = end_xy_m[0] - sensor.x_m, end_xy_m[1] - sensor.y_m
    range_m = math.hypot(ray_x, ray_y)
    facing = ray_x * float(normal[0]) + ray_y * float(normal[1])
    cos_incidence = max(abs(facing) / max(range_m, 1e-9), params.min_cos_incidence)
    spread_m = range_m * params.beam_step_rad + 0.5 * (
        params.footprint_exit_m + params.footprint_divergence_rad * range_m
    )
    return 0.5 * spread_m / cos_incidence + params.end_sigma_floor_m


def _pose_from_board(
    line: LineFeature, sensor: Pose2D, half_width_m: float, params: InitialPoseParams
) -> tuple[FloatArray, FloatArray]:
    """O_f's pose and covariance from a whole board: its centre is the launcher's origin.

    The centre is found from each end (the end, half the known width inwards) and the
    two are weighted by how well each end is known, rather than taking the midpoint:
    the ends' errors are not alike (one near and head-on, one far and grazing).
    """
    yaw = wrap_angle_rad(-line.alpha_rad)
    normal = np.array([math.cos(line.alpha_rad), math.sin(line.alpha_rad)])
    direction = np.array([-normal[1], normal[0]])
    ends = sorted((line.start_xy_m, line.end_xy_m), key=lambda p: float(direction @ np.array(p)))
    low, high = (np.array(p) for p in ends)
    centres = (low + direction * half_width_m, high - direction * half_width_m)
    weights = [1.0 / board_end_sigma_m(p, sensor, normal, params) ** 2 for p in ends]
    mid = (weights[0] * centres[0] + weights[1] * centres[1]) / sum(weights)
    # Across the board the centre is on the fitted line.
    mid = mid - normal * (float(normal @ mid) - line.r_m)
    var_along = 1.0 / sum(weights)
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    d_rot = np.array([[-s, -c], [c, -s]])
    xy = -rot @ mid
    var_r = float(line.covariance[0, 0]) + params.systematic_range_sigma_m**2
    var_alpha = float(line.covariance[1, 1]) + params.systematic_yaw_sigma_rad**2
    cov_mid = var_r * np.outer(normal, normal) + var_along * np.outer(direction, direction)
    j_yaw = -d_rot @ mid  # ∂xy/∂ψ, and ψ = -α
    covariance = np.zeros((3, 3))
    covariance[:2, :2] = rot @ cov_mid @ rot.T + var_alpha * np.outer(j_yaw, j_yaw)
    covariance[:2, 2] = covariance[2, :2] = var_alpha * j_yaw
    covariance[2, 2] = var_alpha
    return np.array([xy[0], xy[1], yaw]), covariance


def initial_pose(
    features: Mapping[str, ScanFeatures],
    sensors: Mapping[str, Pose2D],
    launcher: LauncherMap,
    params: InitialPoseParams | None = None,
) -> InitialPose | InitialPoseRefusal:
    """The pose of O_f from each scanner's features (in the O_f frame) and its pose there."""
    params = params or InitialPoseParams()
    answers: dict[str, tuple[FloatArray, FloatArray]] = {}
    reasons: dict[str, str] = {}
    for name, scan in features.items():
        found, reason = _candidates(scan, launcher, params)
        if len(found) > 1:
            reasons[name] = "ambiguous: more than one board-sized line"
        elif found:
            half = launcher.half_width_m
            answers[name] = _pose_from_board(found[0], sensors[name], half, params)
        else:
            reasons[name] = reason
    if not answers:
        ordered = sorted(set(reasons.values()))
        return InitialPoseRefusal("; ".join(ordered) or "no scan")
    if any(r.startswith("ambiguous") for r in reasons.values()):
        return InitialPoseRefusal("ambiguous: more than one board-sized line")
    poses = list(answers.values())
    gate = chi2_3dof_quantile(params.agree_probability)
    for other in poses[1:]:
        gap = other[0] - poses[0][0]
        gap[2] = wrap_angle_rad(float(gap[2]))
        distance = float(gap @ np.linalg.solve(other[1] + poses[0][1], gap))
        far = math.hypot(gap[0], gap[1]) > params.agree_position_m
        if distance > gate or far or abs(float(gap[2])) > params.agree_heading_rad:
            return InitialPoseRefusal("ambiguous: the scanners disagree on the board")
    information = sum(np.linalg.inv(cov) for _, cov in poses)
    covariance = np.linalg.inv(information)
    reference = poses[0][0]
    weighted = np.zeros(3)
    for state, cov in poses:
        offset = state - reference
        offset[2] = wrap_angle_rad(float(offset[2]))
        weighted += np.linalg.inv(cov) @ offset
    mean = reference + covariance @ weighted
    covariance = 0.5 * (covariance + covariance.T)
    pose = Pose2D(float(mean[0]), float(mean[1]), wrap_angle_rad(float(mean[2])))
    return InitialPose(pose, covariance, tuple(sorted(answers)))


def chi2_3dof_cdf(x: float) -> float:
    """The chi-square CDF with 3 degrees of freedom, in closed form: what a pose's
    (x, y, heading) Mahalanobis distance is compared with."""
    if x <= 0.0:
        return 0.0
    return math.erf(math.sqrt(x / 2.0)) - math.sqrt(2.0 * x / math.pi) * math.exp(-x / 2.0)


def chi2_3dof_quantile(probability: float) -> float:
    """The gate for a probability, by bisection on the closed-form CDF.

    Why not ``scipy.stats.chi2.ppf``: importing ``scipy.stats`` costs more than half a
    second, paid by every ``dbw`` command and every daemon start for one number.
    """
    if not 0.0 < probability < 1.0:
        raise ValueError(f"a probability strictly between 0 and 1, not {probability}")
    low, high = 0.0, 1.0
    while chi2_3dof_cdf(high) < probability:
        high *= 2.0
    for _ in range(200):
        middle = 0.5 * (low + high)
        if chi2_3dof_cdf(middle) < probability:
            low = middle
        else:
            high = middle
        if high - low <= 1e-12 * high:
            break
    return 0.5 * (low + high)
