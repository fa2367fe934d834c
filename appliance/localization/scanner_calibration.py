"""Each LMS111's range offset and mount yaw, from scans taken at rest at the docked pose.

Why at the docked pose: there the vehicle's pose on the launcher is known without any
scanner (the teeth sit in their troughs: ±1 cm lateral, the heading to about ±0.3°, the
front end touching the board), so what the scanners see of the launcher's front board
and cylinders measures the scanners themselves. The data sheet allows each unit a
systematic range error of ±30 mm and a bracket sits a few millimetres and tenths of a
degree off its drawing; uncalibrated, that is the localizer's largest error.

The method (``calibrate_scanner``):

1. Each scan's features are extracted at the configured mount (vehicle frame), and the
   lines and circles are associated with the front board and the cylinders predicted
   from the docked pose. The points of their beam index ranges are kept, less
   ``edge_beams`` at each end (mixed echoes), less any nearer than the LMS111's
   operating range (0.5 m), farther than ``point_gate_m`` from their landmark, or
   within ``corner_margin_m`` of the board's ends (the corners with the side boards).
2. A weighted nonlinear least squares fit at the point level (``scipy.optimize.
   least_squares``): a board point's residual is its distance from the board line
   x = 0 in the launcher frame, a cylinder point's its distance from the cylinder's
   centre less the radius, each weighted by the range noise projected on the surface
   normal. The parameters are the range offset δr (subtracted from every range), the
   mount's yaw error δψ, and its position errors δx, δy *along the vehicle's axes*.
   Vehicle axes because at the docked pose they split cleanly: x is across the board,
   where the board's distance shows the scanner's x, and y along it, which only the
   cylinders show. Points more than ``outlier_sigmas`` off are dropped and the fit
   repeated. The statistical covariance is the inverse normal matrix of the Jacobian,
   scaled by the residuals' own variance.
3. The docked pose's uncertainty is propagated exactly rather than by refitting: the
   points fix the scanner's pose in the launcher frame (and δr, which no pose error
   touches); the mount is that pose seen from the vehicle, so a vehicle displaced by
   (ex, ey, eψ) about the front end's centre moves the fitted mount by the same
   composition. Refitting at the displaced pose gives that shift to rounding; it is
   added as a covariance, each tolerance taken as one σ (conservative for a vehicle
   anywhere within ±tolerance).
4. Observability. δψ carries the whole heading tolerance (0.3°: the data cannot tell a
   turned bracket from a turned vehicle), but δψ is what the localizer needs to say
   "heading 0" exactly where the vehicle docked, and the part that comes from the
   vehicle is common to both scanners; it is reported with both σ. The position
   offsets are only worth applying if known better than the bracket tolerance they
   correct (``mount_position_tolerance_m``): δy carries the 1 cm lateral tolerance and
   δx the heading's lever (1.5 m × 0.3° ≈ 8 mm), so with the troughs' tolerances
   neither is observable: they stay free in the fit (the shift the cylinders show is
   attributed to where the vehicle stands; fixing δy at 0 instead would push that shift
   into δr and δψ, the cylinder lying mostly beside the scanner), and are reported as
   None, so the calibrated mount keeps the configured position.

Pure: numpy and scipy, plain parameters (the launcher map, poses, arrays); the command
(``dbw calibrate scanners``) reads recordings and the vehicle file and does the wiring.
This module runs the steps; each lives beside it: what the fit is given (the docked pose,
the thresholds) in ``scanner_calibration_params``, step 1 in ``scanner_calibration_points``,
steps 2 and 3 in ``scanner_calibration_fit``, step 4 and the result in
``scanner_calibration_verdict``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType
from typing import Final

import numpy as np
import numpy.typing as npt

from appliance.localization.launcher_map import LauncherMap
from appliance.localization.scanner_calibration_fit import FitFailed, solve
from appliance.localization.scanner_calibration_params import CalibrationParams, DockedPose
from appliance.localization.scanner_calibration_points import (
    LandmarkPoints,
    concatenate_points,
    landmark_names,
    landmark_points,
)
from appliance.localization.scanner_calibration_verdict import (
    ScannerCalibrationResult,
    point_shortfalls,
    refused,
    scanner_estimate,
    verdict_reasons,
)
from drivers.geometry import Pose2D

METHOD: Final = "docked-pose point fit (appliance.localization.scanner_calibration)"


def calibrated_mount(
    configured: Pose2D, mount_yaw_offset_rad: float, lateral_offset_m: float | None = None
) -> Pose2D:
    """The mount to use: the configured one turned by δψ and, if known, moved by δy along
    the vehicle's y (never along x: see the module's observability note)."""
    return Pose2D(
        configured.x_m,
        configured.y_m + (lateral_offset_m or 0.0),
        configured.yaw_rad + mount_yaw_offset_rad,
    )


def calibrate_scanner(
    scans: Sequence[tuple[npt.ArrayLike, npt.ArrayLike]],
    configured_mount: Pose2D,
    docked: DockedPose,
    launcher: LauncherMap,
    params: CalibrationParams | None = None,
) -> ScannerCalibrationResult:
    """Fit one scanner from its ``scans``: (ranges_m, angles_rad) pairs, angles in the
    sensor frame (x out of the window), 0 = no echo. Never raises for bad scans: they are
    refused, with the reasons."""
    p = params or CalibrationParams()
    names = landmark_names(launcher)
    empty = dict.fromkeys(names, 0)
    if not scans:
        return refused(["no scans"], empty, 0)
    collected: list[LandmarkPoints] = []
    scans_used = 0
    rejections: dict[str, int] = {}
    for index, (ranges, angles) in enumerate(scans):
        ranges_m = np.asarray(ranges, dtype=np.float64)
        angles_rad = np.asarray(angles, dtype=np.float64)
        if ranges_m.ndim != 1 or angles_rad.shape != ranges_m.shape:
            return refused(
                [f"scan {index}: ranges and angles are not 1-D arrays of one length"],
                empty,
                0,
            )
        found = landmark_points(ranges_m, angles_rad, configured_mount, docked, launcher, p)
        for key, count in found[1].items():
            rejections[key] = rejections.get(key, 0) + count
        if found[0].ranges_m.size:
            scans_used += 1
            collected.append(found[0])
    points = concatenate_points(collected, names)
    return _fit_and_judge(points, configured_mount, docked, launcher, p, scans_used, rejections)


def _fit_and_judge(
    points: LandmarkPoints,
    mount: Pose2D,
    docked: DockedPose,
    launcher: LauncherMap,
    p: CalibrationParams,
    scans_used: int,
    rejections: Mapping[str, int],
) -> ScannerCalibrationResult:
    counts = points.counts()
    cylinder_names = [c.name for c in launcher.cylinders]
    reasons = point_shortfalls(counts, cylinder_names, p, rejections)
    if reasons:
        return refused(reasons, counts, scans_used)
    try:
        fit = solve(points, docked.centre, mount)
        for _ in range(p.outlier_rounds):
            limit = p.outlier_sigmas * max(fit.scale, 1.0) * points.sigmas_m
            keep = np.abs(fit.residuals_m) <= limit
            if bool(np.all(keep)):
                break
            points = points.subset(keep)
            counts = points.counts()
            reasons = point_shortfalls(counts, cylinder_names, p, {})
            if reasons:
                return refused([*reasons, "after dropping outliers"], counts, scans_used)
            fit = solve(points, docked.centre, mount)
    except FitFailed as exc:
        return refused([f"the fit failed: {exc}"], counts, scans_used)
    estimate, notes = scanner_estimate(fit, mount, docked, p)
    reasons = verdict_reasons(fit, estimate, p)
    if reasons:
        return refused(reasons, counts, scans_used, notes, estimate)
    return ScannerCalibrationResult(
        True, (), tuple(notes), MappingProxyType(counts), scans_used, estimate
    )
