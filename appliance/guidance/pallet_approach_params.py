"""The pallet approach's phases, parameters and wish (``pallet_approach``), and the
speed it drives its path at.

``PalletApproachParams`` holds plain numbers: the caller builds it from the vehicle
file (guidance does not read the configuration), e.g.::

    PalletApproachParams(
        wheelbase_m=config.geometry.wheelbase_m,
        max_steer_rad=math.radians(config.limits.max_steer_angle_deg),
        max_steer_rate_rad_per_s=math.radians(config.limits.max_steer_rate_deg_per_s),
        tips_forward_m=config.forks.tips_forward_m,
        forks_offset_y_m=config.forks.offset_y_m,
        final_gap_m=config.pallets.final_gap_m,
        cruise_speed_mps=config.pallets.cruise_speed_mps,
        final_speed_mps=config.pallets.final_speed_mps,
        redetect_gate_m=config.pallets.redetect_gate_m,
        max_lateral_error_m=config.pallets.max_lateral_error_m,
        max_heading_error_rad=math.radians(config.pallets.max_heading_error_deg),
    )
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from appliance.guidance.pallet_geometry import position_sigma_m
from appliance.guidance.pallet_plan import PalletPlan

FloatArray = NDArray[np.float64]


class PalletPhase(StrEnum):
    TO_VIEW = "to_view"
    REDETECT = "redetect"
    FINAL = "final"
    DONE = "done"
    REFUSED = "refused"


@dataclass(frozen=True)
class PalletApproachParams:
    """The vehicle (geometry, forks, limits) and the approach (the vehicle file's
    ``[pallets]``), and this controller's own tuning."""

    wheelbase_m: float = 1.6
    max_steer_rad: float = math.radians(60.0)
    max_steer_rate_rad_per_s: float = math.radians(40.0)
    tips_forward_m: float = 2.02
    forks_offset_y_m: float = 0.0
    final_gap_m: float = 0.0
    cruise_speed_mps: float = 0.8
    final_speed_mps: float = 0.2
    redetect_gate_m: float = 0.5
    max_lateral_error_m: float = 0.01
    max_heading_error_rad: float = math.radians(0.3)
    # TO_VIEW. Where the path turns (or will within the preview), this speed: at 40°/s
    # the wheels take over a second from straight to the plan's curvature.
    turn_speed_mps: float = 0.3
    turn_curvature_per_m: float = 0.15
    turn_preview_m: float = 1.5
    decel_mps2: float = 0.3
    lookahead_min_m: float = 0.5
    lookahead_per_mps_s: float = 0.6
    lookahead_max_m: float = 1.5
    view_tolerance_m: float = 0.02  # the view pose is reached this near its end
    # Off the path by more: refused (below the plan's clearance, which it spends).
    max_path_deviation_m: float = 0.15
    # REDETECT
    redetect_timeout_s: float = 10.0
    redetect_samples: int = 5  # detections averaged before the final approach starts
    # FINAL
    # ℓ of the curvature law (pallet_final). Shorter corrects faster on paper, but with
    # the servo's and the wheels' lag (~0.3 s) and wheels turned at a few degrees a
    # second it overshoots at a creep, and longer leaves the heading unsettled at the
    # stop; 0.35 m holds on the simulated forklift's whole chain (bench_pallet.py).
    convergence_length_m: float = 0.35
    settle_m: float = 0.5  # the reference reaches the axis this far before the stop
    # The wheels reach a wish this much later (the servo's position loop, 0.125 s, and
    # the wheels' own lag): the reference's curvature is wished for where the vehicle
    # will be by then.
    steer_lag_s: float = 0.3
    min_correction_m: float = 0.3  # the reference needs at least this much room
    reference_curvature_fraction: float = 0.7  # of the vehicle's, at most
    final_decel_mps2: float = 0.1
    # In the final approach the speed lets the wheels follow the reference's changing
    # curvature at this fraction of their rate limit (the rest: their lag, the law).
    steer_rate_fraction: float = 0.6
    steer_rate_preview_m: float = 0.2
    # Well above the speed loop's standstill threshold: slower, a PID speed loop sticks
    # and lurches, and the wheels turn on the spot meanwhile.
    creep_speed_mps: float = 0.05
    stop_tolerance_m: float = 0.002
    track_gate_m: float = 0.05  # a later detection farther from the mean is not the target
    track_gate_rad: float = math.radians(3.0)
    detection_memory: float = 0.995  # per detection (pallet_final.DetectionFilter)
    detection_slope_prior_m: float = 0.1
    # The pose
    max_position_sigma_m: float = 0.2
    lost_pose_timeout_s: float = 0.5
    standstill_mps: float = 0.02

    @property
    def max_curvature_per_m(self) -> float:
        return math.tan(self.max_steer_rad) / self.wheelbase_m


@dataclass(frozen=True)
class PalletOrder:
    """The controller's wish and what it is based on (for the status)."""

    phase: PalletPhase
    speed_mps: float  # ≥ 0: forward only
    steer_rad: float  # effective steering angle, positive left
    refused: str = ""
    waiting: str = ""  # why it is standing still for now (a lost pose, a detection)
    # TO_VIEW: the guide point off the path; FINAL: the fork tips off the pallet's axis.
    lateral_error_m: float = math.nan
    heading_error_rad: float = math.nan
    # TO_VIEW: path left to the view pose; FINAL: the tips to their stop.
    distance_m: float = math.nan
    detections: int = 0  # of the target, accepted so far
    rejected: str = ""  # why the last detection was not taken as the target


def pose_sigma_m(covariance: object) -> float:
    """σ of a pose estimate's position along its worst axis; inf for anything that is
    not a finite 3x3 covariance (so that it reads as lost)."""
    try:
        matrix = np.asarray(covariance, dtype=np.float64)
    except (TypeError, ValueError):
        return math.inf
    if matrix.shape != (3, 3) or not np.isfinite(matrix).all():
        return math.inf
    if matrix[0, 0] < 0.0 or matrix[1, 1] < 0.0:
        return math.inf
    return position_sigma_m(matrix)


def speed_profile_mps(plan: PalletPlan, params: PalletApproachParams) -> FloatArray:
    """The speed allowed at each point of the plan: the cruise speed, the turn speed
    where the path turns within the preview, braking to a stop at the end."""
    arc = plan.arc_m
    turning = np.abs(plan.curvature_per_m) > params.turn_curvature_per_m
    limit = np.full(arc.shape, params.cruise_speed_mps)
    ends = np.searchsorted(arc, arc + params.turn_preview_m, side="right")
    starts = np.searchsorted(arc, arc - 0.5, side="left")
    cumulative = np.concatenate([[0], np.cumsum(turning)])
    near_turn = cumulative[ends] - cumulative[starts] > 0
    limit[near_turn] = min(params.turn_speed_mps, params.cruise_speed_mps)
    speed = limit.copy()
    speed[-1] = 0.0
    for i in range(len(arc) - 2, -1, -1):
        reach = math.sqrt(speed[i + 1] ** 2 + 2.0 * params.decel_mps2 * (arc[i + 1] - arc[i]))
        speed[i] = min(limit[i], reach)
    return speed
