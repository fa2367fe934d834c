"""What the scanner calibration is given: the docked pose and how well it is known, and
the thresholds that select points, fit them and accept the result.

The docked pose is the calibration's one reference: at it the vehicle's pose on the
launcher is known without any scanner, so its tolerances bound what the fit can say (see
:mod:`appliance.localization.scanner_calibration`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.localization.launcher_map import LauncherMap
from appliance.perception.cylinders import CircleParams
from appliance.perception.features import FeatureParams
from drivers.geometry import Pose2D


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
