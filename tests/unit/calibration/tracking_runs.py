"""Tracking tests on the simulated vehicle: a plain pure pursuit on a line or an arc.

Independent of the runtime's tracker on purpose: the look-ahead fit is to choose well
for whatever loop it is given, and this one has the two behaviours the paper tuned
against: with too short a look-ahead the loop weaves (worse at speed and with a slower
servo), with too long a one it cuts the arc. Pure pursuit from the geometric centre,
counter-steer curvature (1 + k) tan φf / L, ``appliance.sim.vehicle.step`` at 20 Hz with
the servo's lag and rate limit, the cross-track error measured with 2 cm of noise.
"""

from __future__ import annotations

import math

import numpy as np

from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from calibration.lookahead import LookaheadCandidate, TrackingRun
from drivers.pc104.messages import MotionPattern

ARC_RADIUS_M = 20.0
DT_S = 0.05
MPH = 0.44704
SPEEDS_MPS = (5 * MPH, 10 * MPH)
CONDITIONS = (("line", 0.0), ("line", 3.0), ("line", -3.0), ("arc", 0.0), ("arc", -3.0))


def vehicle(rate_deg_per_s: float = 25.0, lag_s: float = 0.15) -> VehicleParams:
    return VehicleParams(
        wheelbase_m=3.6,
        track_width_m=2.3,
        counter_steer_ratio_k=0.63,
        characteristic_speed_mps=10.0,
        max_steer_angle_rad=math.radians(32.0),
        max_steer_rate_rad_per_s=math.radians(rate_deg_per_s),
        steer_time_constant_s=lag_s,
    )


def tracking_run(
    candidate: LookaheadCandidate,
    course: str,
    offset_m: float,
    speed_mps: float,
    params: VehicleParams,
    seconds: float = 25.0,
    seed: int = 0,
) -> TrackingRun:
    """Start ``offset_m`` to the left of the course, heading along it, at speed."""
    lookahead = candidate.lookahead_m(speed_mps)
    y0 = offset_m if course == "line" else -ARC_RADIUS_M + offset_m
    state = VehicleState(y_m=y0, speed_mps=speed_mps)
    rng = np.random.default_rng(seed)
    times, errors = [], []
    for _ in range(round(seconds / DT_S)):
        if course == "line":
            error = state.y_m
            goal_x, goal_y = state.x_m + lookahead, 0.0
        else:  # counter-clockwise about the origin; left of it is inside
            error = ARC_RADIUS_M - math.hypot(state.x_m, state.y_m)
            angle = math.atan2(state.y_m, state.x_m) + lookahead / ARC_RADIUS_M
            goal_x, goal_y = ARC_RADIUS_M * math.cos(angle), ARC_RADIUS_M * math.sin(angle)
        times.append(state.t_s)
        errors.append(error + rng.normal(0.0, 0.02))
        dx, dy = goal_x - state.x_m, goal_y - state.y_m
        eta = math.atan2(dy, dx) - state.yaw_rad
        curvature = 2.0 * math.sin(eta) / math.hypot(dx, dy)
        front = math.atan(curvature * params.wheelbase_m / (1.0 + params.counter_steer_ratio_k))
        throttle = 100.0 * min(
            1.0, max(0.0, 0.05 * speed_mps + 2.0 * (speed_mps - state.speed_mps))
        )
        command = VehicleCommand(MotionPattern.COUNTER_STEER, front, 0.0, throttle, 0.0, False)
        state = step(state, command, DT_S, params)
    return TrackingRun(candidate, course, offset_m, speed_mps, np.array(times), np.array(errors))


def tuning_runs(
    candidates: tuple[LookaheadCandidate, ...], params: VehicleParams
) -> list[TrackingRun]:
    """Every candidate on every condition at 5 and 10 mph, as the paper's tuning tests."""
    return [
        tracking_run(candidate, course, offset, speed, params, seed=i)
        for candidate in candidates
        for i, (course, offset) in enumerate(CONDITIONS)
        for speed in SPEEDS_MPS
    ]
