"""What the launcher localizer is given and what it reports: its scanners, its
parameters, and the estimate with its status and quality.

Apart from :mod:`.launcher_localizer` because more reads them than runs the filter: the
dock source, the docking simulation, the calibration's scanner setups and the CLIs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from appliance.localization.board_motion import BoardMotionParams
from appliance.localization.initial_pose import InitialPoseParams
from appliance.localization.launcher_ekf import EkfParams
from appliance.localization.launcher_map import LauncherMap
from appliance.perception.features import FeatureParams
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]


class LocalizationStatus(StrEnum):
    OK = "ok"
    DEGRADED = "degraded"  # usable with care: automatic motion may not start or go on
    LOST = "lost"  # no pose: automatic motion stops


@dataclass(frozen=True)
class ScannerSetup:
    """One scanner as the localizer uses it: its mount in the vehicle frame (calibrated
    where a calibration exists), its range offset, and what is left of its systematic
    error (the data sheet's ±30 mm and the mount's tenths of a degree uncalibrated, a few
    millimetres and hundredths after ``dbw calibrate scanners``)."""

    mount: Pose2D
    range_offset_m: float = 0.0
    # Uncalibrated: the data sheet's "typical" ±30 mm taken as 2σ, and a mount set to a
    # few tenths of a degree (±0.3° as 2σ).
    systematic_range_sigma_m: float = 0.015
    systematic_yaw_sigma_rad: float = math.radians(0.15)


@dataclass(frozen=True)
class LocalizerParams:
    launcher: LauncherMap = field(default_factory=LauncherMap)
    features: FeatureParams = field(default_factory=FeatureParams)
    ekf: EkfParams = field(default_factory=EkfParams)
    board_motion: BoardMotionParams = field(default_factory=BoardMotionParams)
    initial: InitialPoseParams = field(default_factory=InitialPoseParams)
    scan_max_age_s: float = 0.12
    # Two scanners' scans are taken together for the initial pose within this time.
    initial_pair_s: float = 0.1
    cylinder_roi_m: float = 0.6
    board_roi_m: float = 0.4
    board_match_heading_rad: float = math.radians(3.0)
    board_match_range_m: float = 0.25
    # Status: lost with no accepted measurement for this long, or beyond this σ.
    lost_after_s: float = 0.5
    lost_sigma_m: float = 0.15
    degraded_sigma_m: float = 0.05
    degraded_heading_sigma_rad: float = math.radians(0.5)
    # With no cylinder for this long, y rests on the board's ends alone.
    cylinder_degraded_after_s: float = 3.0
    # A scanner that has given no usable scan for this long: the pose rests on one side.
    scanner_silent_after_s: float = 0.3
    # A landmark whose sightings over this window are mostly rejected (at least this many
    # sightings, more than this fraction rejected) says the map is wrong.
    disagreement_window_s: float = 2.0
    disagreement_min_sightings: int = 10
    disagreement_fraction: float = 0.5
    disagreement_mean_nis: float = 6.0  # three times a 2-dimensional measurement's 2
    # A landmark counts as expected (a miss is a verdict against the map) only well
    # inside a scanner's field (±135°) and range.
    in_view_half_angle_rad: float = math.radians(110.0)
    in_view_min_range_m: float = 0.6
    in_view_max_range_m: float = 12.0


@dataclass(frozen=True)
class LocalizationEstimate:
    status: LocalizationStatus
    reason: str
    quality: int  # 0..100
    t_s: float | None  # the time of the last measurement the estimate includes
    pose: Pose2D | None  # O_f in the launcher frame
    covariance: FloatArray | None
    centre_pose: Pose2D | None  # the vehicle's geometric centre O_m, for the controller
    centre_covariance: FloatArray | None
    nis: Mapping[str, float]
    accepted: Mapping[str, int]
    rejected: Mapping[str, int]
