"""The forklift's pallet guidance built from the vehicle file: the vehicle's outline and
the planner's and controller's parameters (guidance reads no configuration: its callers,
the `pallet` source and `dbw sim pallet`, build its plain numbers here, once)."""

from __future__ import annotations

import math

from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.guidance.pallet_approach_params import PalletApproachParams
from appliance.guidance.pallet_geometry import ScannerField, VehicleShape
from appliance.guidance.pallet_plan import PalletPlanParams
from drivers.lms111.mounted import mount_pose


def max_steer_rad(config: VehicleConfig, calibration: Calibration | None = None) -> float:
    """The steering the guidance may plan with: the vehicle file's limit, and within the
    range the pot is calibrated over (the core clamps every command to it)."""
    limit = math.radians(config.limits.max_steer_angle_deg)
    if calibration is None:
        return limit
    low, high = calibration.valid_tyre_range_rad
    return min(limit, -low, high)


def vehicle_shape(config: VehicleConfig, calibration: Calibration | None = None) -> VehicleShape:
    """The outline the planner checks (the body to the forks' heel, the forks beyond)
    and the scanners' fields the view pose is checked against."""
    forks = config.forks
    return VehicleShape(
        length_m=config.geometry.length_m,
        width_m=config.geometry.width_m,
        front_m=forks.tips_forward_m,
        wheelbase_m=config.geometry.wheelbase_m,
        max_steer_rad=max_steer_rad(config, calibration),
        tips_forward_m=forks.tips_forward_m,
        forks_offset_y_m=forks.offset_y_m,
        scanners=(
            ScannerField(mount_pose(config.geometry.scanner_left_mount)),
            ScannerField(mount_pose(config.geometry.scanner_right_mount)),
        ),
        heel_forward_m=forks.heel_forward_m,
        forks_width_m=forks.spread_m + forks.width_m,
    )


def approach_params(
    config: VehicleConfig, calibration: Calibration | None = None
) -> PalletApproachParams:
    pallets = config.pallets
    return PalletApproachParams(
        wheelbase_m=config.geometry.wheelbase_m,
        max_steer_rad=max_steer_rad(config, calibration),
        max_steer_rate_rad_per_s=math.radians(
            min(config.limits.max_steer_rate_deg_per_s, pallets.steer_rate_deg_per_s)
        ),
        tips_forward_m=config.forks.tips_forward_m,
        forks_offset_y_m=config.forks.offset_y_m,
        final_gap_m=pallets.final_gap_m,
        cruise_speed_mps=pallets.cruise_speed_mps,
        final_speed_mps=pallets.final_speed_mps,
        redetect_gate_m=pallets.redetect_gate_m,
        max_lateral_error_m=pallets.max_lateral_error_m,
        max_heading_error_rad=math.radians(pallets.max_heading_error_deg),
    )


def plan_params(config: VehicleConfig) -> PalletPlanParams:
    return PalletPlanParams(approach_standoff_m=config.pallets.approach_standoff_m)
