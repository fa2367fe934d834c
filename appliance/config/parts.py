"""The vehicle file, turned into each part's own parameters: the one place that reads it.

Safety rules and drivers take small frozen parameters in radians and SI units and know
nothing of the vehicle file; this module is where a degree becomes a radian, a rate
becomes a period and a topic name meets its age limit, each conversion once. A reviewer
who wants to know what ``limits.max_steer_angle_deg`` does to the vehicle reads this file
and the rule it feeds, and nothing else.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import replace

from appliance.config.calibration import Calibration
from appliance.config.models import Engagement, Limits, SafetyTimeouts, Staleness, VehicleConfig
from appliance.guidance.dock_source import DockSourceParams, DockZone
from appliance.guidance.docking import DockingParams
from appliance.guidance.pedal_plant import LinearPlant, MapPlant, table_from_bands
from appliance.guidance.pedal_speed import PedalSpeedParams
from appliance.guidance.pedal_sweep import PedalSweepParams
from appliance.localization.launcher_localizer import LocalizerParams, ScannerSetup
from appliance.localization.launcher_map import LauncherMap
from appliance.perception.features import FeatureParams
from drivers.geometry import Pose2D
from drivers.lms111.mounted import mount_pose
from drivers.pc104.client_core import ClientParams
from safety.consistency import ErrorBudget, SteeringTrackingParams
from safety.limits import LimitParams
from safety.override import OperatorOverride, PedalOverrideParams, SteeringOverrideParams
from safety.safe_state import STOP_DISTANCE_MARGIN, SafeBrakeParams, SpeedRampParams
from safety.staleness import DEFAULT_CRITICAL_INPUTS, StalenessGuard
from safety.system_health import SystemHealthParams

# What is left of a calibrated scanner's systematic error: the fit's own σ is about a
# millimetre and a hundredth of a degree (docs/calibration.md), the range scale error
# (±0.05 %) is not calibrated, and a mount may settle between calibrations.
CALIBRATED_RANGE_FLOOR_M = 0.003
CALIBRATED_YAW_FLOOR_RAD = math.radians(0.03)


def limit_params(
    limits: Limits, *, steer_rate_fraction_at_max_speed: float = 1.0, max_step_dt_s: float = 0.1
) -> LimitParams:
    return LimitParams(
        max_steer_angle_rad=math.radians(limits.max_steer_angle_deg),
        max_steer_rate_rad_per_s=math.radians(limits.max_steer_rate_deg_per_s),
        throttle_min_pct=limits.throttle_min_pct,
        throttle_max_pct=limits.throttle_max_pct,
        max_throttle_rate_pct_per_s=limits.max_throttle_rate_pct_per_s,
        brake_min_pct=limits.brake_min_pct,
        brake_max_pct=limits.brake_max_pct,
        max_speed_mps=limits.max_speed_mps,
        steer_rate_fraction_at_max_speed=steer_rate_fraction_at_max_speed,
        max_step_dt_s=max_step_dt_s,
    )


def steering_override_params(safety: SafetyTimeouts, limits: Limits) -> SteeringOverrideParams:
    return SteeringOverrideParams(
        threshold_rad=math.radians(safety.steer_override_threshold_deg),
        release_rad=math.radians(safety.steer_override_release_deg),
        dwell_s=safety.steer_override_dwell_s,
        min_torque_nm=safety.steer_override_min_torque_nm,
        stop_margin_rad=math.radians(safety.steer_stop_margin_deg),
        max_steer_angle_rad=math.radians(limits.max_steer_angle_deg),
    )


def pedal_override_params(safety: SafetyTimeouts) -> PedalOverrideParams:
    return PedalOverrideParams(margin_pct=safety.pedal_override_margin_pct)


def operator_override(safety: SafetyTimeouts, limits: Limits) -> OperatorOverride:
    return OperatorOverride(steering_override_params(safety, limits), pedal_override_params(safety))


def steering_tracking_params(safety: SafetyTimeouts) -> SteeringTrackingParams:
    return SteeringTrackingParams(
        tolerance_rad=math.radians(safety.steer_tracking_tolerance_deg),
        fault_after_s=safety.steer_tracking_fault_after_s,
    )


def error_budget(safety: SafetyTimeouts) -> ErrorBudget:
    return ErrorBudget(safety.pc104_error_budget_limit)


def safe_brake_params(safety: SafetyTimeouts, limits: Limits) -> SafeBrakeParams:
    """The safe-stop deceleration as a brake level: its share of what full brake gives."""
    share = safety.safe_stop_decel_mps2 / safety.full_brake_decel_mps2
    fault_pct = min(max(100.0 * share, limits.brake_min_pct), limits.brake_max_pct)
    return SafeBrakeParams(
        fault_brake_pct=max(fault_pct, 1.0),  # never a "safe" state without brake
        estop_brake_pct=limits.brake_max_pct,
        ramp_pct_per_s=safety.safe_stop_brake_ramp_pct_per_s,
    )


def speed_ramp_params(engagement: Engagement, limits: Limits) -> SpeedRampParams:
    return SpeedRampParams(
        max_speed_mps=min(engagement.max_set_speed_mps, limits.max_speed_mps),
        max_accel_mps2=engagement.max_accel_mps2,
        stop_distance_m=engagement.hold_to_move_stop_distance_m,
    )


def age_limits(staleness: Staleness) -> dict[str, float]:
    """The per-input age limits, by the topic names the control loop uses."""
    board_s = staleness.actuator_board_max_age_s
    return {
        "scan.left": staleness.scan_max_age_s,
        "scan.right": staleness.scan_max_age_s,
        "pose": staleness.pose_max_age_s,
        "pc104.status": staleness.pc104_status_max_age_s,
        "steering.pot": staleness.steering_pot_max_age_s,
        "board.steering": board_s,
        "board.throttle": board_s,
        "board.brake": board_s,
        "board.panel": staleness.panel_max_age_s,
    }


def staleness_guard(
    staleness: Staleness, critical: Iterable[str] = DEFAULT_CRITICAL_INPUTS
) -> StalenessGuard:
    return StalenessGuard(age_limits(staleness), critical)


def critical_inputs(config: VehicleConfig) -> tuple[str, ...]:
    """The inputs whose staleness revokes control. A vehicle on the ``pedals`` speed path
    has no PC104: its status is no input, so its absence can be neither stale nor a
    reason to hold the self-check."""
    if config.speed_path == "pedals":
        return tuple(name for name in DEFAULT_CRITICAL_INPUTS if name != "pc104.status")
    return DEFAULT_CRITICAL_INPUTS


def pedal_speed_params(config: VehicleConfig) -> PedalSpeedParams:
    """The throttle/brake speed controller inside the vehicle's throttle and brake limits,
    so the safety limiter, which enforces the same numbers, never has to clamp it (a
    clamp the controller does not know of would be windup it cannot see).

    Under hold-to-move a released button is the controller's stop request: its stop brake
    is raised to the deceleration that stops from the top set speed within
    ``hold_to_move_stop_distance_m`` (aiming at 70 % of it, as the PC104 path's ramp does,
    for the brake's rise), by the controller's own brake gain."""
    params = PedalSpeedParams.from_limits(config.limits)
    engagement = config.engagement
    if not engagement.hold_to_move:
        return params
    needed_mps2 = engagement.max_set_speed_mps**2 / (
        2.0 * engagement.hold_to_move_stop_distance_m * STOP_DISTANCE_MARGIN
    )
    stop_pct = min(needed_mps2 / params.decel_per_brake_pct_mps2, params.brake_max_pct)
    return replace(params, stop_brake_pct=max(params.stop_brake_pct, stop_pct))


def pedal_plant(config: VehicleConfig, calibration: Calibration | None) -> MapPlant | None:
    """The pedal sweep's maps for the speed controller (None: the calibration has none,
    and the controller keeps its linear model, which also continues the maps beyond
    what they measured)."""
    if calibration is None or calibration.pedals is None:
        return None
    params = pedal_speed_params(config)
    tables = []
    for table in (calibration.pedals.throttle, calibration.pedals.brake):
        tables.append(
            table_from_bands(
                table.pedal_pct,
                table.speed_mps,
                table.first_level_by_band,
                table.accel_mps2_by_band,
            )
        )
    linear = LinearPlant(
        params.accel_per_throttle_pct_mps2, params.decel_per_brake_pct_mps2, params.drag_per_s
    )
    return MapPlant(tables[0], tables[1], linear)


def pedal_sweep_params(config: VehicleConfig) -> PedalSweepParams:
    sweep = config.pedal_sweep
    return PedalSweepParams(
        throttle_levels_pct=sweep.throttle_levels_pct,
        brake_levels_pct=sweep.brake_levels_pct,
        top_speed_mps=sweep.top_speed_mps,
        coast_s=sweep.coast_s,
        max_throttle_s=sweep.max_throttle_s,
        hold_brake_pct=sweep.hold_brake_pct,
        coast_down_end_mps=sweep.speed_band_edges_mps[0],
    )


# A simulated device is the simulator's child process coming up beside the daemon: trying
# it every 0.2 s costs nothing, where the real devices' 1 s cap left the daemon waiting up
# to a second after the simulator was ready (READY 0.5 s later in every runtime test).
SIM_RECONNECT_CAP_S = 0.2
DEVICE_RECONNECT_CAP_S = 1.0


def reconnect_cap_s(config: VehicleConfig) -> float:
    """The longest wait between a device client's attempts to reach its device."""
    return SIM_RECONNECT_CAP_S if config.simulation.enabled else DEVICE_RECONNECT_CAP_S


def pc104_client_params(config: VehicleConfig) -> ClientParams:
    return ClientParams(
        command_period_s=1.0 / config.rates.pc104_command_hz,
        status_max_age_s=config.staleness.pc104_status_max_age_s,
        command_timeout_s=config.safety.lower_layer_command_timeout_s,
        reopen_backoff_cap_s=reconnect_cap_s(config),
    )


def scanner_setups(
    config: VehicleConfig, calibration: Calibration | None
) -> dict[str, ScannerSetup]:
    """Each front scanner as the launcher localizer uses it: the configured mount, made
    the calibrated one where ``dbw calibrate scanners`` has measured it.

    Uncalibrated, the localizer carries the data sheet's systematic error; calibrated,
    what is left of it. The yaw's σ is taken from the points, not the docked heading's
    tolerance: that part is common to both scanners and defines the launcher's heading as
    the one the vehicle docked at during calibration, which is the heading docking needs.
    """
    mounts = {
        "left": config.geometry.scanner_left_mount,
        "right": config.geometry.scanner_right_mount,
    }
    setups: dict[str, ScannerSetup] = {}
    for name, mount in mounts.items():
        configured = mount_pose(mount)
        entry = calibration.scanner(name) if calibration is not None else None
        if entry is None:
            setups[name] = ScannerSetup(configured)
            continue
        lateral_m = entry.lateral_offset_m or 0.0
        setups[name] = ScannerSetup(
            Pose2D(
                configured.x_m,
                configured.y_m + lateral_m,
                configured.yaw_rad + entry.mount_yaw_offset_rad,
            ),
            range_offset_m=entry.range_offset_m,
            systematic_range_sigma_m=max(entry.range_offset_sigma_m, CALIBRATED_RANGE_FLOOR_M),
            systematic_yaw_sigma_rad=CALIBRATED_YAW_FLOOR_RAD,
        )
    return setups


def dock_source_params(config: VehicleConfig) -> DockSourceParams:
    """The vehicle file's docking section as the dock source's parameters."""
    d = config.docking
    geometry = config.geometry
    launcher = LauncherMap(
        front_board_width_m=d.front_board_width_m,
        side_board_length_m=d.side_board_length_m,
        side_board_sweep_deg=d.side_board_sweep_deg,
        cylinder_radius_m=d.cylinder_radius_m,
        cylinder_lateral_m=d.cylinder_lateral_m,
        cylinder_ahead_m=d.cylinder_ahead_m,
    )
    features = FeatureParams(circles=replace(FeatureParams().circles, radius_m=d.cylinder_radius_m))
    docking = DockingParams(
        front_end_forward_m=d.front_end_forward_m or geometry.length_m / 2.0,
        teeth_lateral_m=d.teeth_lateral_m,
        tooth_insertion_m=d.tooth_insertion_m,
        trough_clearance_m=d.trough_clearance_m,
        standoff_m=d.standoff_m,
        max_speed_mps=min(d.max_speed_mps, config.limits.max_speed_mps),
        max_rear_steer_rad=math.radians(config.limits.max_steer_angle_deg),
        max_crab_rad=math.radians(min(15.0, config.limits.max_steer_angle_deg)),
        wheelbase_m=geometry.wheelbase_m,
    )
    localizer = LocalizerParams(
        launcher=launcher, features=features, scan_max_age_s=config.staleness.scan_max_age_s
    )
    zone = DockZone(
        max_gap_m=d.zone_max_gap_m,
        max_lateral_m=d.zone_max_lateral_m,
        max_heading_rad=math.radians(d.zone_max_heading_deg),
    )
    return DockSourceParams(docking=docking, localizer=localizer, zone=zone)


def system_health_params(config: VehicleConfig) -> SystemHealthParams | None:
    """The PC-health rule's thresholds; None where the vehicle file turns the monitor off."""
    monitor = config.system_monitor
    if not monitor.enabled:
        return None
    return SystemHealthParams(
        max_age_s=monitor.max_age_s,
        disk_stop_free_mb=monitor.disk_stop_free_mb,
        temperature_max_c=monitor.temperature_max_c,
        memory_min_available_mb=monitor.memory_min_available_mb,
    )
