"""Step 4 of the scanner calibration and its verdict: what of the fit is known well enough
to apply, the reasons to refuse it, and the result a caller reports.

Each parameter's σ is reported from the points alone and with the docked pose's
tolerance, because the two answer different questions: the points' σ says whether the
scans determine the parameter, the total whether it is worth applying (the observability
note in :mod:`appliance.localization.scanner_calibration`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np

from appliance.localization.scanner_calibration_fit import (
    LATERAL,
    LONGITUDINAL,
    MOUNT_YAW,
    PARAMETER_NAMES,
    RANGE_OFFSET,
    PointFit,
    pose_covariance,
)
from appliance.localization.scanner_calibration_params import CalibrationParams, DockedPose
from appliance.localization.scanner_calibration_points import BOARD
from drivers.geometry import Pose2D


@dataclass(frozen=True)
class ParameterEstimate:
    """One fitted parameter: its value, and σ from the points alone, from the docked
    pose's tolerance, and both. ``observable``: known well enough to apply (the range
    offset and yaw always are; `calibrated_mount` applies the lateral offset when it is,
    and never the longitudinal one, whose σ carries the heading's lever)."""

    name: str
    value: float
    sigma: float
    statistical_sigma: float
    pose_sigma: float
    observable: bool


@dataclass(frozen=True)
class ScannerEstimate:
    """The fit's result (always finite). ``lateral_offset_m`` is None when it is not
    observable; ``lateral_offset_sigma_m`` is then the σ that said so."""

    range_offset_m: float
    range_offset_sigma_m: float
    mount_yaw_offset_rad: float
    mount_yaw_offset_sigma_rad: float
    mount_yaw_offset_statistical_sigma_rad: float  # without the heading tolerance
    lateral_offset_m: float | None
    lateral_offset_sigma_m: float
    residual_rms_m: float
    parameters: tuple[ParameterEstimate, ...]

    def parameter(self, name: str) -> ParameterEstimate:
        for estimate in self.parameters:
            if estimate.name == name:
                return estimate
        raise KeyError(name)


@dataclass(frozen=True)
class ScannerCalibrationResult:
    """The verdict on one scanner, why, and the estimate (None if no fit was possible)."""

    accepted: bool
    reasons: tuple[str, ...]  # why it was refused; empty when accepted
    notes: tuple[str, ...]  # what the caller should know either way (observability)
    points_used: Mapping[str, int]  # per landmark name, over all scans
    scans_used: int  # scans that gave at least one landmark point
    estimate: ScannerEstimate | None

    @property
    def range_offset_m(self) -> float | None:
        return None if self.estimate is None else self.estimate.range_offset_m

    @property
    def mount_yaw_offset_rad(self) -> float | None:
        return None if self.estimate is None else self.estimate.mount_yaw_offset_rad

    @property
    def lateral_offset_m(self) -> float | None:
        return None if self.estimate is None else self.estimate.lateral_offset_m

    @property
    def residual_rms_m(self) -> float | None:
        return None if self.estimate is None else self.estimate.residual_rms_m


def refused(
    reasons: Sequence[str],
    counts: Mapping[str, int],
    scans_used: int,
    notes: Sequence[str] = (),
    estimate: ScannerEstimate | None = None,
) -> ScannerCalibrationResult:
    """A refusal, with the points counted so far and the estimate if there was a fit."""
    return ScannerCalibrationResult(
        False, tuple(reasons), tuple(notes), MappingProxyType(dict(counts)), scans_used, estimate
    )


def point_shortfalls(
    counts: Mapping[str, int],
    cylinder_names: Sequence[str],
    p: CalibrationParams,
    rejections: Mapping[str, int],
) -> list[str]:
    """Why the points are too few to fit (the board's, the best cylinder's), with what the
    extractor said of the cylinders it did not find; empty when they suffice."""
    reasons = []
    if counts[BOARD] < p.min_board_points:
        reasons.append(f"too few points on the front board: {counts[BOARD]} < {p.min_board_points}")
    best = max((counts[name] for name in cylinder_names), default=0)
    if best < p.min_cylinder_points:
        seen = ", ".join(f"{name} {counts[name]}" for name in cylinder_names)
        why = ", ".join(f"{key} ×{n}" for key, n in sorted(rejections.items()))
        reasons.append(
            f"too few points on any cylinder ({seen}; need {p.min_cylinder_points} on one)"
            + (f"; scans without it: {why}" if why else "")
        )
    return reasons


def scanner_estimate(
    fit: PointFit, mount: Pose2D, docked: DockedPose, p: CalibrationParams
) -> tuple[ScannerEstimate, list[str]]:
    """The fit with the docked pose's tolerance added, which position offsets are
    observable, and notes saying what is not and why."""
    pose_cov = pose_covariance(mount, docked)
    total = fit.covariance + pose_cov
    stat = np.sqrt(np.maximum(np.diag(fit.covariance), 0.0))
    pose = np.sqrt(np.maximum(np.diag(pose_cov), 0.0))
    sigma = np.sqrt(np.maximum(np.diag(total), 0.0))
    limit = p.observable_fraction * p.mount_position_tolerance_m
    observable = [True, True, bool(sigma[LONGITUDINAL] <= limit), bool(sigma[LATERAL] <= limit)]
    parameters = tuple(
        ParameterEstimate(
            name,
            float(fit.theta[i]),
            float(sigma[i]),
            float(stat[i]),
            float(pose[i]),
            observable[i],
        )
        for i, name in enumerate(PARAMETER_NAMES)
    )
    notes = []
    for i, label in ((LATERAL, "lateral"), (LONGITUDINAL, "longitudinal")):
        if not observable[i]:
            notes.append(
                f"{label} mount offset not observable: σ {sigma[i] * 1e3:.1f} mm "
                f"(points {stat[i] * 1e3:.2f} mm, docked pose {pose[i] * 1e3:.1f} mm) > "
                f"{limit * 1e3:.1f} mm; fixed at 0, the {fit.theta[i] * 1e3:+.1f} mm the points "
                "show is taken as where the vehicle stood"
            )
    if pose[MOUNT_YAW] > stat[MOUNT_YAW]:
        notes.append(
            f"mount yaw σ {math.degrees(sigma[MOUNT_YAW]):.3f}° is mostly the docked heading's "
            f"tolerance ({math.degrees(pose[MOUNT_YAW]):.3f}°, common to both scanners); the "
            f"points alone give {math.degrees(stat[MOUNT_YAW]):.4f}°"
        )
    rms = float(np.sqrt(np.mean(fit.residuals_m**2)))
    estimate = ScannerEstimate(
        range_offset_m=float(fit.theta[RANGE_OFFSET]),
        range_offset_sigma_m=float(sigma[RANGE_OFFSET]),
        mount_yaw_offset_rad=float(fit.theta[MOUNT_YAW]),
        mount_yaw_offset_sigma_rad=float(sigma[MOUNT_YAW]),
        mount_yaw_offset_statistical_sigma_rad=float(stat[MOUNT_YAW]),
        lateral_offset_m=float(fit.theta[LATERAL]) if observable[LATERAL] else None,
        lateral_offset_sigma_m=float(sigma[LATERAL]),
        residual_rms_m=rms,
        parameters=parameters,
    )
    return estimate, notes


def verdict_reasons(fit: PointFit, estimate: ScannerEstimate, p: CalibrationParams) -> list[str]:
    """Why an estimate is refused (too large, too poorly determined by the points, the
    points too far off the model); empty when it is accepted."""
    reasons = []
    if not estimate.residual_rms_m <= p.max_residual_rms_m:
        reasons.append(
            f"residual rms {estimate.residual_rms_m * 1e3:.1f} mm > "
            f"{p.max_residual_rms_m * 1e3:.1f} mm"
        )
    if not abs(estimate.range_offset_m) <= p.max_range_offset_m:
        reasons.append(
            f"range offset {estimate.range_offset_m * 1e3:+.1f} mm is beyond "
            f"±{p.max_range_offset_m * 1e3:.0f} mm"
        )
    if not abs(estimate.mount_yaw_offset_rad) <= p.max_yaw_offset_rad:
        reasons.append(
            f"mount yaw offset {math.degrees(estimate.mount_yaw_offset_rad):+.2f}° is beyond "
            f"±{math.degrees(p.max_yaw_offset_rad):.1f}°"
        )
    stat_range = math.sqrt(max(float(fit.covariance[RANGE_OFFSET, RANGE_OFFSET]), 0.0))
    if not stat_range <= p.max_statistical_range_sigma_m:
        reasons.append(
            f"the points determine the range offset only to σ {stat_range * 1e3:.1f} mm "
            f"(> {p.max_statistical_range_sigma_m * 1e3:.1f} mm)"
        )
    stat_yaw = estimate.mount_yaw_offset_statistical_sigma_rad
    if not stat_yaw <= p.max_statistical_yaw_sigma_rad:
        reasons.append(
            f"the points determine the yaw only to σ {math.degrees(stat_yaw):.3f}° "
            f"(> {math.degrees(p.max_statistical_yaw_sigma_rad):.2f}°)"
        )
    return reasons
