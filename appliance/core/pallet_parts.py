"""The forklift's pallet guidance built from the vehicle file: the vehicle's outline, the
planner's and controller's parameters, the site's posts and walls, the worker's map and
the merge's weights (guidance, mapping and localization read no configuration: their
caller, the `pallet` source, builds their plain values here, once)."""

from __future__ import annotations

import math
from dataclasses import replace
from importlib import resources

from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.guidance.pallet_approach_params import PalletApproachParams
from appliance.guidance.pallet_geometry import (
    Obstacle,
    ScannerField,
    VehicleShape,
    disc_obstacle,
    wall_obstacle,
)
from appliance.guidance.pallet_plan import PalletPlanParams
from appliance.localization.landmark_initial import LandmarkMap
from appliance.localization.launcher_map import CylinderLandmark
from appliance.mapping.association import RobustParams
from appliance.mapping.map_file import (
    MapFileError,
    MapRead,
    pallet_map_from_bytes,
    read_pallet_map,
)
from appliance.mapping.merge import MergeParams
from drivers.lms111.mounted import mount_pose

BUILTIN_WORKER_MAP = "builtin:pallets"  # the simulated terminal's survey of `pallets`


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


def landmark_map(config: VehicleConfig) -> LandmarkMap:
    return LandmarkMap(
        tuple(
            CylinderLandmark(lm.name, lm.x_m, lm.y_m, lm.radius_m)
            for lm in config.pallets.landmarks
        )
    )


def site_obstacles(config: VehicleConfig, clearance_m: float) -> tuple[Obstacle, ...]:
    """The walls, posts and columns, which the merged map (pallets only) does not hold."""
    walls = tuple(
        wall_obstacle(w.x0_m, w.y0_m, w.x1_m, w.y1_m, clearance_m, w.name)
        for w in config.pallets.walls
    )
    discs = [(c.x_m, c.y_m, c.radius_m, c.name) for c in config.pallets.landmarks]
    discs += [(c.x_m, c.y_m, c.radius_m, c.name) for c in config.pallets.columns]
    posts = tuple(disc_obstacle(x, y, r, clearance_m, name) for x, y, r, name in discs)
    return walls + posts


def load_worker_map(spec: str) -> MapRead:
    """The worker's map the vehicle file names, a cloud's alternative readings with it
    (raises `MapFileError` saying why not)."""
    if not spec:
        raise MapFileError("no worker map: set pallets.worker_map in the vehicle file")
    if spec == BUILTIN_WORKER_MAP:
        data = resources.files("appliance.config").joinpath("maps/pallets-worker.json")
        return pallet_map_from_bytes(data.read_bytes(), spec, "worker")
    return read_pallet_map(spec, "worker", with_alternatives=True)


def merge_params(config: VehicleConfig) -> MergeParams:
    w = config.pallets.merge_w_m2_per_rad2
    if w is None:
        return MergeParams()
    return MergeParams(robust=replace(RobustParams(), w_m2_per_rad2=w))
