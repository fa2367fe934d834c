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
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from appliance.localization.launcher_map import CylinderLandmark, LauncherMap
from appliance.perception.cylinders import CircleParams, fit_cylinder
from appliance.perception.features import FeatureParams, extract_features
from appliance.perception.points import ScanPoints, scan_points
from appliance.perception.types import CircleFeature, FitRejection, LineFeature
from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]

BOARD: Final = "front_board"
PARAMETER_NAMES: Final = ("range_offset", "mount_yaw", "longitudinal", "lateral")
_RANGE, _YAW, _LONG, _LAT = range(4)
METHOD: Final = "docked-pose point fit (appliance.localization.scanner_calibration)"
# The normal matrix's condition beyond which a parameter is not determined at all (metres
# and radians at ranges of metres are of one scale, so this is a geometric statement).
MAX_CONDITION: Final = 1e12


def calibration_feature_params(launcher: LauncherMap) -> FeatureParams:
    """Feature extraction for the calibration: the extractor's defaults with the
    launcher's cylinder radius (the map is the truth here, not the default)."""
    return FeatureParams(circles=CircleParams(radius_m=launcher.cylinder_radius_m))


@dataclass(frozen=True)
class DockedPose:
    """Where the vehicle stood while the scans were taken, and how well that is known.

    ``centre`` is the vehicle frame's origin in the launcher frame; ``pivot_forward_m``
    is where the troughs hold the vehicle (the front end's centre, on the vehicle's x
    axis): a heading error turns the vehicle about it. Tolerances are taken as one σ.
    """

    centre: Pose2D
    pivot_forward_m: float
    longitudinal_tolerance_m: float = 0.003  # the front end touches the board
    lateral_tolerance_m: float = 0.01  # a trough is 2 cm wider than its tooth
    heading_tolerance_rad: float = math.radians(0.3)

    def __post_init__(self) -> None:
        for name in ("longitudinal_tolerance_m", "lateral_tolerance_m", "heading_tolerance_rad"):
            value = getattr(self, name)
            if not (value >= 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if not all(math.isfinite(v) for v in (*self.centre, self.pivot_forward_m)):
            raise ValueError("the docked pose and pivot must be finite")

    @classmethod
    def at_front_end(
        cls,
        front_end: Pose2D,
        front_end_forward_m: float,
        longitudinal_tolerance_m: float = 0.003,
        lateral_tolerance_m: float = 0.01,
        heading_tolerance_rad: float = math.radians(0.3),
    ) -> DockedPose:
        """The docked pose from where the front end's centre stands (the docking target)."""
        return cls(
            front_end.compose(Pose2D(-front_end_forward_m, 0.0, 0.0)),
            front_end_forward_m,
            longitudinal_tolerance_m,
            lateral_tolerance_m,
            heading_tolerance_rad,
        )

    def displaced(self, longitudinal_m: float, lateral_m: float, heading_rad: float) -> Pose2D:
        """The vehicle's pose moved by (longitudinal, lateral) at the pivot, in the vehicle's
        axes, and turned by ``heading_rad`` about the pivot: how it may really stand."""
        pivot = Pose2D(self.pivot_forward_m, 0.0, 0.0)
        moved = Pose2D(longitudinal_m, lateral_m, heading_rad)
        return (
            self.centre.compose(pivot)
            .compose(moved)
            .compose(Pose2D(-self.pivot_forward_m, 0.0, 0.0))
        )


@dataclass(frozen=True)
class CalibrationParams:
    """Point selection, fit and acceptance thresholds; defaults for the LMS111 on the
    flat-bed at Qian et al.'s launcher."""

    features: FeatureParams | None = None  # None: `calibration_feature_params(launcher)`
    min_range_m: float = 0.5  # the LMS111's operating range starts at 0.5 m (data sheet)
    edge_beams: int = 2  # dropped at each end of a landmark's beams: mixed echoes sit there
    board_gate_rad: float = math.radians(3.0)  # a line's direction vs the predicted board's
    board_gate_m: float = 0.15  # a line's distance vs the predicted board's
    cylinder_gate_m: float = 0.2  # a circle's centre vs the predicted cylinder's
    point_gate_m: float = 0.1  # a kept point is this close to its landmark (configured mount)
    corner_margin_m: float = 0.05  # board points this close to the board's ends are dropped
    outlier_sigmas: float = 4.0
    outlier_rounds: int = 3
    # Acceptance.
    min_board_points: int = 30
    min_cylinder_points: int = 10
    max_residual_rms_m: float = 0.015
    max_range_offset_m: float = 0.1
    max_yaw_offset_rad: float = math.radians(2.0)
    max_statistical_range_sigma_m: float = 0.005  # the points must determine δr at least this well
    max_statistical_yaw_sigma_rad: float = math.radians(0.1)
    # A position offset is applied only if known to this fraction of the bracket tolerance.
    mount_position_tolerance_m: float = 0.005
    observable_fraction: float = 0.5

    def __post_init__(self) -> None:
        if self.edge_beams < 0 or self.outlier_rounds < 0:
            raise ValueError("edge_beams and outlier_rounds must be >= 0")
        if self.min_board_points < 3 or self.min_cylinder_points < 3:
            raise ValueError("min_board_points and min_cylinder_points must be >= 3")


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


@dataclass(frozen=True)
class _Points:
    """Every kept point: its beam, which landmark, and its noise along that landmark's
    normal. ``centres`` has one row per point (NaN for board points)."""

    ranges_m: FloatArray
    angles_rad: FloatArray
    is_board: npt.NDArray[np.bool_]
    centres: FloatArray  # (N, 2)
    radii_m: FloatArray
    sigmas_m: FloatArray
    landmark: npt.NDArray[np.int64]  # index into names
    names: tuple[str, ...]

    def subset(self, keep: npt.NDArray[np.bool_]) -> _Points:
        return _Points(
            self.ranges_m[keep],
            self.angles_rad[keep],
            self.is_board[keep],
            self.centres[keep],
            self.radii_m[keep],
            self.sigmas_m[keep],
            self.landmark[keep],
            self.names,
        )

    def counts(self) -> dict[str, int]:
        found = np.bincount(self.landmark, minlength=len(self.names))
        return {name: int(found[i]) for i, name in enumerate(self.names)}


def _refused(
    reasons: Sequence[str],
    counts: Mapping[str, int],
    scans_used: int,
    notes: Sequence[str] = (),
    estimate: ScannerEstimate | None = None,
) -> ScannerCalibrationResult:
    return ScannerCalibrationResult(
        False, tuple(reasons), tuple(notes), MappingProxyType(dict(counts)), scans_used, estimate
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
    names = (BOARD, *(c.name for c in launcher.cylinders))
    empty = dict.fromkeys(names, 0)
    if not scans:
        return _refused(["no scans"], empty, 0)
    collected: list[_Points] = []
    scans_used = 0
    rejections: dict[str, int] = {}
    for index, (ranges, angles) in enumerate(scans):
        ranges_m = np.asarray(ranges, dtype=np.float64)
        angles_rad = np.asarray(angles, dtype=np.float64)
        if ranges_m.ndim != 1 or angles_rad.shape != ranges_m.shape:
            return _refused(
                [f"scan {index}: ranges and angles are not 1-D arrays of one length"],
                empty,
                0,
            )
        found = _landmark_points(ranges_m, angles_rad, configured_mount, docked, launcher, p)
        for key, count in found[1].items():
            rejections[key] = rejections.get(key, 0) + count
        if found[0].ranges_m.size:
            scans_used += 1
            collected.append(found[0])
    points = _concatenate(collected, names)
    return _fit_and_judge(points, configured_mount, docked, launcher, p, scans_used, rejections)


def _landmark_points(
    ranges_m: FloatArray,
    angles_rad: FloatArray,
    mount: Pose2D,
    docked: DockedPose,
    launcher: LauncherMap,
    p: CalibrationParams,
) -> tuple[_Points, Mapping[str, int]]:
    """One scan's board and cylinder points, by feature association (see the module)."""
    names = (BOARD, *(c.name for c in launcher.cylinders))
    features_params = p.features or calibration_feature_params(launcher)
    features = extract_features(ranges_m, angles_rad, mount, features_params)
    to_launcher = docked.centre.compose(mount)
    points = scan_points(ranges_m, angles_rad, to_launcher)
    xy = points.xy_m
    keep_ranges = points.valid & (points.ranges_m >= p.min_range_m)
    cos_sin = points.directions  # unit beams in the launcher frame
    selected: list[tuple[npt.NDArray[np.intp], int]] = []
    for line in features.lines:
        if _is_board(line, docked.centre, p):
            selected.append((_trimmed(line.first_index, line.last_index, p.edge_beams), 0))
    for circle in features.circles:
        landmark = _cylinder_of(circle, docked.centre, launcher.cylinders, p)
        if landmark is not None:
            beams = _trimmed(circle.first_index, circle.last_index, p.edge_beams)
            selected.append((beams, 1 + landmark))
    found = {landmark for _, landmark in selected}
    missing = [c for i, c in enumerate(launcher.cylinders) if 1 + i not in found]
    rejections = _why_not_found(
        missing, features.segments, points, ranges_m, angles_rad, mount, features_params, p
    )
    beams_list: list[npt.NDArray[np.intp]] = []
    which: list[npt.NDArray[np.int64]] = []
    for beams, landmark in selected:
        beams = beams[keep_ranges[beams]]
        if landmark == 0:
            x, y = xy[beams, 0], xy[beams, 1]
            inside = np.abs(y) <= launcher.half_width_m - p.corner_margin_m
            beams = beams[inside & (np.abs(x) <= p.point_gate_m)]
        else:
            cylinder = launcher.cylinders[landmark - 1]
            off = np.hypot(xy[beams, 0] - cylinder.x_m, xy[beams, 1] - cylinder.y_m)
            beams = beams[np.abs(off - cylinder.radius_m) <= p.point_gate_m]
        beams_list.append(beams)
        which.append(np.full(beams.size, landmark, dtype=np.int64))
    beams_all = np.concatenate(beams_list) if beams_list else np.zeros(0, dtype=np.intp)
    landmark_all = np.concatenate(which) if which else np.zeros(0, dtype=np.int64)
    # A beam in two features (a board line and a circle overlapping) is nobody's.
    unique, counts = np.unique(beams_all, return_counts=True)
    once = np.isin(beams_all, unique[counts == 1])
    beams_all, landmark_all = beams_all[once], landmark_all[once]
    centres = np.full((beams_all.size, 2), np.nan)
    radii = np.zeros(beams_all.size)
    for i, cylinder in enumerate(launcher.cylinders):
        mine = landmark_all == i + 1
        centres[mine] = (cylinder.x_m, cylinder.y_m)
        radii[mine] = cylinder.radius_m
    is_board = landmark_all == 0
    # Noise along each landmark's normal: the board's is x, a cylinder's the radius.
    normals = np.zeros((beams_all.size, 2))
    normals[is_board] = (1.0, 0.0)
    radial = xy[beams_all] - np.where(is_board[:, None], 0.0, centres)
    norm = np.hypot(radial[:, 0], radial[:, 1])
    with np.errstate(invalid="ignore", divide="ignore"):
        normals[~is_board] = radial[~is_board] / np.maximum(norm[~is_board, None], 1e-9)
    cos_incidence = np.abs(np.sum(cos_sin[beams_all] * normals, axis=1))
    sigmas = np.sqrt(features_params.scanner.normal_variance(cos_incidence))
    return (
        _Points(
            ranges_m[beams_all],
            angles_rad[beams_all],
            is_board,
            centres,
            radii,
            sigmas,
            landmark_all,
            names,
        ),
        rejections,
    )


def _why_not_found(
    cylinders: Sequence[CylinderLandmark],
    segments: Sequence[tuple[int, int]],
    launcher_points: ScanPoints,
    ranges_m: FloatArray,
    angles_rad: FloatArray,
    mount: Pose2D,
    features_params: FeatureParams,
    p: CalibrationParams,
) -> dict[str, int]:
    """For each cylinder no circle was found for, what the extractor says of the cluster
    where it should be (``"<name>.<reason>"``, e.g. ``not_isolated``: something stands
    beside it), or ``"<name>.not_seen"``: a refusal says why, not only "not found"."""
    reasons: dict[str, int] = {}
    vehicle_points: ScanPoints | None = None
    for cylinder in cylinders:
        reach = cylinder.radius_m + p.cylinder_gate_m
        why = "not_seen"
        for start, stop in segments:
            xy = launcher_points.xy_m[start:stop]
            if not np.any(np.hypot(xy[:, 0] - cylinder.x_m, xy[:, 1] - cylinder.y_m) <= reach):
                continue
            if vehicle_points is None:
                vehicle_points = scan_points(ranges_m, angles_rad, mount)
            outcome = fit_cylinder(
                vehicle_points, (start, stop), features_params.circles, features_params.scanner
            )
            why = outcome.reason.value if isinstance(outcome, FitRejection) else "off_its_place"
            break
        reasons[f"{cylinder.name}.{why}"] = 1
    return reasons


def _trimmed(first: int, last: int, edge: int) -> npt.NDArray[np.intp]:
    return np.arange(first + edge, last - edge + 1, dtype=np.intp)


def _is_board(line: LineFeature, centre: Pose2D, p: CalibrationParams) -> bool:
    """Whether a vehicle-frame line is the front board (x = 0 in the launcher frame)."""
    # x_L = centre.x + (R(yaw) p)_x = 0: normal R(-yaw) e_x, at -centre.x from the origin.
    normal_angle = -centre.yaw_rad
    distance = -centre.x_m
    if distance < 0.0:  # Hessian form keeps r >= 0: flip the normal instead
        distance, normal_angle = -distance, normal_angle + math.pi
    turn = math.remainder(line.alpha_rad - normal_angle, math.tau)
    return abs(turn) <= p.board_gate_rad and abs(line.r_m - distance) <= p.board_gate_m


def _cylinder_of(
    circle: CircleFeature,
    centre: Pose2D,
    cylinders: Sequence[CylinderLandmark],
    p: CalibrationParams,
) -> int | None:
    """The index of the cylinder a vehicle-frame circle is, or None."""
    x, y = centre.apply(circle.cx_m, circle.cy_m)
    for i, cylinder in enumerate(cylinders):
        if math.hypot(x - cylinder.x_m, y - cylinder.y_m) <= p.cylinder_gate_m:
            return i
    return None


def _concatenate(parts: Sequence[_Points], names: tuple[str, ...]) -> _Points:
    if not parts:
        return _Points(
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, dtype=np.bool_),
            np.zeros((0, 2)),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, dtype=np.int64),
            names,
        )
    return _Points(
        np.concatenate([q.ranges_m for q in parts]),
        np.concatenate([q.angles_rad for q in parts]),
        np.concatenate([q.is_board for q in parts]),
        np.concatenate([q.centres for q in parts]),
        np.concatenate([q.radii_m for q in parts]),
        np.concatenate([q.sigmas_m for q in parts]),
        np.concatenate([q.landmark for q in parts]),
        names,
    )


def _point_residuals(
    theta: FloatArray, points: _Points, vehicle: Pose2D, mount: Pose2D
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
    jac[:, _RANGE] = -(gx * wx + gy * wy)
    jac[:, _YAW] = r * (gy * wx - gx * wy)  # g · perp(beam)
    jac[:, _LONG] = gx * c + gy * s  # g · R(vehicle yaw) e_x
    jac[:, _LAT] = -gx * s + gy * c  # g · R(vehicle yaw) e_y
    return residual, jac


@dataclass(frozen=True)
class _Fit:
    theta: FloatArray
    covariance: FloatArray  # statistical, scaled by the residuals' variance
    residuals_m: FloatArray
    scale: float  # rms of the whitened residuals


class _FitFailed(Exception):
    pass


def _solve(points: _Points, vehicle: Pose2D, mount: Pose2D) -> _Fit:
    weights = 1.0 / points.sigmas_m

    def fun(theta: FloatArray) -> FloatArray:
        residual, _ = _point_residuals(theta, points, vehicle, mount)
        whitened: FloatArray = residual * weights
        return whitened

    def jac(theta: FloatArray) -> FloatArray:
        _, jacobian = _point_residuals(theta, points, vehicle, mount)
        whitened: FloatArray = jacobian * weights[:, None]
        return whitened

    try:
        solution = least_squares(fun, np.zeros(4), jac=jac, method="trf", x_scale="jac")
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise _FitFailed(str(exc)) from None
    theta = np.asarray(solution.x, dtype=np.float64)
    residual, jacobian = _point_residuals(theta, points, vehicle, mount)
    whitened = jacobian * weights[:, None]
    normal = whitened.T @ whitened
    if not (np.all(np.isfinite(theta)) and np.all(np.isfinite(normal))):
        raise _FitFailed("the fit did not stay finite")
    degenerate = "the points do not determine the parameters (degenerate geometry)"
    try:
        if not np.linalg.cond(normal) <= MAX_CONDITION:
            raise _FitFailed(degenerate)
        inverse = np.asarray(np.linalg.inv(normal), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise _FitFailed(degenerate) from None
    dof = max(residual.size - theta.size, 1)
    scale = math.sqrt(float(np.sum((residual * weights) ** 2)) / dof)
    covariance: FloatArray = inverse * scale**2
    return _Fit(theta, covariance, residual, scale)


def _pose_covariance(mount: Pose2D, docked: DockedPose) -> FloatArray:
    """What the docked pose's tolerance does to (δr, δψ, δx, δy): a vehicle moved by
    (ex, ey) and turned by eψ about the pivot moves the fitted mount by the same, in the
    vehicle's axes (the scanners' pose on the launcher is what the points fix)."""
    jac = np.zeros((4, 3))  # rows δr, δψ, δx, δy; columns ex, ey, eψ
    jac[_LONG, 0] = 1.0
    jac[_LAT, 1] = 1.0
    jac[_YAW, 2] = 1.0
    jac[_LONG, 2] = -mount.y_m
    jac[_LAT, 2] = mount.x_m - docked.pivot_forward_m
    tolerances = np.array(
        [docked.longitudinal_tolerance_m, docked.lateral_tolerance_m, docked.heading_tolerance_rad]
    )
    result: FloatArray = jac @ np.diag(tolerances**2) @ jac.T
    return result


def _fit_and_judge(
    points: _Points,
    mount: Pose2D,
    docked: DockedPose,
    launcher: LauncherMap,
    p: CalibrationParams,
    scans_used: int,
    rejections: Mapping[str, int],
) -> ScannerCalibrationResult:
    counts = points.counts()
    cylinder_names = [c.name for c in launcher.cylinders]
    reasons = _point_shortfalls(counts, cylinder_names, p, rejections)
    if reasons:
        return _refused(reasons, counts, scans_used)
    try:
        fit = _solve(points, docked.centre, mount)
        for _ in range(p.outlier_rounds):
            limit = p.outlier_sigmas * max(fit.scale, 1.0) * points.sigmas_m
            keep = np.abs(fit.residuals_m) <= limit
            if bool(np.all(keep)):
                break
            points = points.subset(keep)
            counts = points.counts()
            reasons = _point_shortfalls(counts, cylinder_names, p, {})
            if reasons:
                return _refused([*reasons, "after dropping outliers"], counts, scans_used)
            fit = _solve(points, docked.centre, mount)
    except _FitFailed as exc:
        return _refused([f"the fit failed: {exc}"], counts, scans_used)
    estimate, notes = _estimate(fit, mount, docked, p)
    reasons = _verdict_reasons(fit, estimate, p)
    if reasons:
        return _refused(reasons, counts, scans_used, notes, estimate)
    return ScannerCalibrationResult(
        True, (), tuple(notes), MappingProxyType(counts), scans_used, estimate
    )


def _point_shortfalls(
    counts: Mapping[str, int],
    cylinder_names: Sequence[str],
    p: CalibrationParams,
    rejections: Mapping[str, int],
) -> list[str]:
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


def _estimate(
    fit: _Fit, mount: Pose2D, docked: DockedPose, p: CalibrationParams
) -> tuple[ScannerEstimate, list[str]]:
    pose_cov = _pose_covariance(mount, docked)
    total = fit.covariance + pose_cov
    stat = np.sqrt(np.maximum(np.diag(fit.covariance), 0.0))
    pose = np.sqrt(np.maximum(np.diag(pose_cov), 0.0))
    sigma = np.sqrt(np.maximum(np.diag(total), 0.0))
    limit = p.observable_fraction * p.mount_position_tolerance_m
    observable = [True, True, bool(sigma[_LONG] <= limit), bool(sigma[_LAT] <= limit)]
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
    for i, label in ((_LAT, "lateral"), (_LONG, "longitudinal")):
        if not observable[i]:
            notes.append(
                f"{label} mount offset not observable: σ {sigma[i] * 1e3:.1f} mm "
                f"(points {stat[i] * 1e3:.2f} mm, docked pose {pose[i] * 1e3:.1f} mm) > "
                f"{limit * 1e3:.1f} mm; fixed at 0, the {fit.theta[i] * 1e3:+.1f} mm the points "
                "show is taken as where the vehicle stood"
            )
    if pose[_YAW] > stat[_YAW]:
        notes.append(
            f"mount yaw σ {math.degrees(sigma[_YAW]):.3f}° is mostly the docked heading's "
            f"tolerance ({math.degrees(pose[_YAW]):.3f}°, common to both scanners); the "
            f"points alone give {math.degrees(stat[_YAW]):.4f}°"
        )
    rms = float(np.sqrt(np.mean(fit.residuals_m**2)))
    estimate = ScannerEstimate(
        range_offset_m=float(fit.theta[_RANGE]),
        range_offset_sigma_m=float(sigma[_RANGE]),
        mount_yaw_offset_rad=float(fit.theta[_YAW]),
        mount_yaw_offset_sigma_rad=float(sigma[_YAW]),
        mount_yaw_offset_statistical_sigma_rad=float(stat[_YAW]),
        lateral_offset_m=float(fit.theta[_LAT]) if observable[_LAT] else None,
        lateral_offset_sigma_m=float(sigma[_LAT]),
        residual_rms_m=rms,
        parameters=parameters,
    )
    return estimate, notes


def _verdict_reasons(fit: _Fit, estimate: ScannerEstimate, p: CalibrationParams) -> list[str]:
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
    stat_range = math.sqrt(max(float(fit.covariance[_RANGE, _RANGE]), 0.0))
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
