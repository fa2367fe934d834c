"""Step 1 of the scanner calibration: which beams of a scan lie on the front board and on
which cylinder, and how noisy each is along its landmark's normal.

The scan's features are extracted at the configured mount and associated with the board
and the cylinders predicted from the docked pose; their beams are kept less the mixed
echoes at each end, the ranges below the LMS111's operating range, the points off their
landmark and the board's corners. Where a cylinder is not found, the extractor's reason
for the cluster where it should be is kept, so that a refusal says why (the method as a
whole: :mod:`appliance.localization.scanner_calibration`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
import numpy.typing as npt

from appliance.localization.launcher_map import CylinderLandmark, LauncherMap
from appliance.localization.scanner_calibration_params import (
    CalibrationParams,
    DockedPose,
    calibration_feature_params,
)
from appliance.perception.cylinders import fit_cylinder
from appliance.perception.features import FeatureParams, extract_features
from appliance.perception.points import ScanPoints, scan_points
from appliance.perception.types import CircleFeature, FitRejection, LineFeature
from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]

BOARD: Final = "front_board"


def landmark_names(launcher: LauncherMap) -> tuple[str, ...]:
    """The landmarks points are counted by: the front board, then each cylinder."""
    return (BOARD, *(c.name for c in launcher.cylinders))


@dataclass(frozen=True)
class LandmarkPoints:
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

    def subset(self, keep: npt.NDArray[np.bool_]) -> LandmarkPoints:
        return LandmarkPoints(
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


def concatenate_points(parts: Sequence[LandmarkPoints], names: tuple[str, ...]) -> LandmarkPoints:
    if not parts:
        return LandmarkPoints(
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, dtype=np.bool_),
            np.zeros((0, 2)),
            np.zeros(0),
            np.zeros(0),
            np.zeros(0, dtype=np.int64),
            names,
        )
    return LandmarkPoints(
        np.concatenate([q.ranges_m for q in parts]),
        np.concatenate([q.angles_rad for q in parts]),
        np.concatenate([q.is_board for q in parts]),
        np.concatenate([q.centres for q in parts]),
        np.concatenate([q.radii_m for q in parts]),
        np.concatenate([q.sigmas_m for q in parts]),
        np.concatenate([q.landmark for q in parts]),
        names,
    )


def landmark_points(
    ranges_m: FloatArray,
    angles_rad: FloatArray,
    mount: Pose2D,
    docked: DockedPose,
    launcher: LauncherMap,
    p: CalibrationParams,
) -> tuple[LandmarkPoints, Mapping[str, int]]:
    """One scan's board and cylinder points, by feature association (see the module)."""
    names = landmark_names(launcher)
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
        LandmarkPoints(
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
