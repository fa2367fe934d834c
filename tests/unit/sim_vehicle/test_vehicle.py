"""Simulated vehicle kinematics against closed-form expectations."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.sim.vehicle import (
    VehicleCommand,
    VehicleParams,
    VehicleState,
    sideslip_gain,
)
from appliance.sim.world import SimWorld
from drivers.pc104.messages import MotionPattern

PARAMS = VehicleParams(
    wheelbase_m=3.0,
    track_width_m=2.0,
    counter_steer_ratio_k=1.0,
    characteristic_speed_mps=1e9,  # no sideslip unless a test asks for it
    max_steer_angle_rad=math.radians(30),
    max_steer_rate_rad_per_s=math.radians(1000),
    steer_time_constant_s=0.0,
    drag_per_s=0.0,
    traction_time_constant_s=0.0,
)


def drive(
    command: VehicleCommand,
    seconds: float,
    params: VehicleParams = PARAMS,
    state: VehicleState | None = None,
) -> VehicleState:
    world = SimWorld(params, initial=state, step_hz=200)
    world.command = command
    return world.advance_to(seconds)


def cruising(speed_mps: float) -> VehicleState:
    return VehicleState(speed_mps=speed_mps)


def test_straight_line_at_constant_speed() -> None:
    command = VehicleCommand(MotionPattern.STRAIGHT, throttle_pct=0.0, brake_pct=0.0)
    end = drive(command, 2.0, state=cruising(2.0))
    assert end.x_m == pytest.approx(4.0, abs=1e-9)
    assert end.y_m == pytest.approx(0.0, abs=1e-12)
    assert end.yaw_rad == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("k", [0.0, 0.63, 1.0])
def test_counter_steer_yaw_rate_matches_stanley(k: float) -> None:
    params = VehicleParams(**{**PARAMS.__dict__, "counter_steer_ratio_k": k})
    phi = math.radians(10)
    command = VehicleCommand(MotionPattern.COUNTER_STEER, front_steer_rad=phi, brake_pct=0.0)
    start = VehicleState(speed_mps=1.0, front_steer_rad=phi, rear_steer_rad=k * phi)
    end = drive(command, 1.0, params, start)
    beta = math.atan((math.tan(phi) - math.tan(k * phi)) / 2)
    expected = 1.0 * math.cos(beta) / 3.0 * (math.tan(phi) + math.tan(k * phi))
    assert end.yaw_rad == pytest.approx(expected, rel=1e-9)


def test_sideslip_gain_reduces_turning_at_speed() -> None:
    assert sideslip_gain(0.0, 5.0) == 1.0
    assert sideslip_gain(5.0, 5.0) == pytest.approx(0.5)
    slow = VehicleParams(**{**PARAMS.__dict__, "characteristic_speed_mps": 2.0})
    phi = math.radians(10)
    command = VehicleCommand(MotionPattern.FRONT_STEER, front_steer_rad=phi, brake_pct=0.0)
    start = VehicleState(speed_mps=2.0, front_steer_rad=phi)
    no_slip = drive(command, 0.5, PARAMS, start)
    with_slip = drive(command, 0.5, slow, start)
    assert with_slip.yaw_rad == pytest.approx(no_slip.yaw_rad / 2, rel=1e-6)


def test_oblique_translates_without_turning() -> None:
    crab = math.radians(20)
    command = VehicleCommand(MotionPattern.OBLIQUE, front_steer_rad=crab, brake_pct=0.0)
    start = VehicleState(speed_mps=1.0, front_steer_rad=crab, rear_steer_rad=-crab)
    end = drive(command, 1.0, state=start)
    assert end.yaw_rad == pytest.approx(0.0, abs=1e-12)
    assert math.atan2(end.y_m, end.x_m) == pytest.approx(crab, rel=1e-9)
    assert math.hypot(end.x_m, end.y_m) == pytest.approx(1.0, rel=1e-9)


def test_turn_around_rotates_in_place() -> None:
    command = VehicleCommand(MotionPattern.TURN_AROUND, brake_pct=0.0)
    end = drive(command, 1.0, state=cruising(0.5))
    assert (end.x_m, end.y_m) == (0.0, 0.0)
    assert end.yaw_rad == pytest.approx(0.5 / math.hypot(1.5, 1.0))


def test_brake_stops_without_reversing_and_stop_pattern_brakes() -> None:
    braking = VehicleCommand(MotionPattern.STRAIGHT, throttle_pct=0.0, brake_pct=100.0)
    end = drive(braking, 3.0, state=cruising(3.0))
    assert end.speed_mps == 0.0
    assert end.x_m == pytest.approx(1.5, abs=0.02)  # v^2 / (2 * 3 m/s^2)
    stopped = drive(VehicleCommand(MotionPattern.STOP, throttle_pct=100.0, brake_pct=0.0), 3.0)
    assert stopped.speed_mps == 0.0


def test_steering_follows_with_rate_limit() -> None:
    params = VehicleParams(**{**PARAMS.__dict__, "max_steer_rate_rad_per_s": math.radians(10)})
    command = VehicleCommand(MotionPattern.FRONT_STEER, front_steer_rad=math.radians(30))
    end = drive(command, 1.0, params)
    assert math.degrees(end.front_steer_rad) == pytest.approx(10.0, abs=0.06)


def test_flatbed_platform_lags_the_chassis_when_turning() -> None:
    params = VehicleParams.from_config(load_config("flatbed"))
    start = VehicleState(speed_mps=0.5)
    turned = drive(VehicleCommand(MotionPattern.TURN_AROUND, brake_pct=0.0), 2.0, params, start)
    assert turned.platform_yaw_offset_rad != 0.0
    assert abs(turned.platform_yaw_offset_rad) < 0.05 * abs(turned.yaw_rad)
    settled = drive(VehicleCommand(MotionPattern.STOP), 30.0, params, turned)
    assert abs(settled.platform_yaw_offset_rad) < abs(turned.platform_yaw_offset_rad) / 100


@settings(max_examples=100, deadline=None)
@given(
    pattern=st.sampled_from(list(MotionPattern)),
    steer=st.floats(-1.0, 1.0),
    throttle=st.floats(0.0, 100.0),
    brake=st.floats(0.0, 100.0),
    reverse=st.booleans(),
)
def test_state_stays_finite_and_within_limits(
    pattern: MotionPattern, steer: float, throttle: float, brake: float, reverse: bool
) -> None:
    params = VehicleParams.from_config(load_config("husky"))
    command = VehicleCommand(pattern, steer, steer, throttle, brake, reverse)
    end = drive(command, 5.0, params)
    for value in (end.x_m, end.y_m, end.yaw_rad, end.speed_mps):
        assert math.isfinite(value)
    assert abs(end.front_steer_rad) <= params.max_steer_angle_rad + 1e-12
    assert abs(end.speed_mps) <= params.max_speed_mps
    assert -math.pi <= end.yaw_rad <= math.pi


def test_world_merges_inputs_like_the_vehicle() -> None:
    world = SimWorld(PARAMS)
    assert world.command == VehicleCommand()  # parked: stopped and braked
    world.set_inputs("throttle_board", throttle_pct=5.0)
    assert world.command.pattern is MotionPattern.COUNTER_STEER  # no PC104: natural pattern
    world.set_inputs("pc104", pattern=MotionPattern.OBLIQUE, front_steer_rad=0.1, throttle_pct=20)
    world.set_inputs("brake_board", brake_pct=10.0)
    assert world.command.pattern is MotionPattern.OBLIQUE
    assert (world.command.throttle_pct, world.command.brake_pct) == (20, 10.0)
    world.set_inputs("steering_servo", front_steer_rad=0.2)
    assert world.command.front_steer_rad == 0.2
    world.set_inputs("operator", front_steer_rad=-0.3, brake_pct=60.0)
    assert (world.command.front_steer_rad, world.command.brake_pct) == (-0.3, 60.0)
    world.clear_inputs("operator")
    assert (world.command.front_steer_rad, world.command.brake_pct) == (0.2, 10.0)
    with pytest.raises(ValueError, match="unknown"):
        world.set_inputs("pc104", warp_drive=1)


def test_operator_hands_win_whatever_the_order() -> None:
    world = SimWorld(PARAMS)
    world.set_inputs("operator", front_steer_rad=-0.3)
    world.set_inputs("steering_servo", front_steer_rad=0.2)
    assert world.command.front_steer_rad == -0.3
