"""The forklift profile: its rear axle steers, in the simulated world as in the core."""

from __future__ import annotations

import math
from typing import Literal

import pytest
from pydantic import ValidationError

from appliance.config.forklift_models import PalletGuidanceSettings
from appliance.config.loader import load_config
from appliance.config.models import VehicleConfig, VehicleKind
from appliance.core.autopilot import default_pattern
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.pc104.messages import MotionPattern


@pytest.mark.parametrize("name", ["forklift", "forklift-sim"])
def test_the_forklift_profiles_load_as_a_rear_steered_vehicle(name: str) -> None:
    config = load_config(name)
    assert config.kind is VehicleKind.FORKLIFT
    assert default_pattern(config.kind) is MotionPattern.REAR_STEER
    assert config.forks.tips_forward_m == pytest.approx(
        config.forks.heel_forward_m + config.forks.length_m
    )
    assert config.engagement.hold_to_move


def _turn(steered_axle: Literal["front", "rear"], wheel_rad: float) -> tuple[float, float, float]:
    config = load_config("forklift-sim")
    world = SimWorld(VehicleParams.from_config(config), steered_axle=steered_axle)
    world.set_inputs("steering_servo", front_steer_rad=wheel_rad)
    world.set_inputs("throttle_board", throttle_pct=30.0, brake_pct=0.0)
    state = world.advance_to(4.0)
    return state.yaw_rad, state.front_steer_rad, state.rear_steer_rad


def test_the_steering_wheel_turns_the_rear_axle_and_the_forklift_turns_its_way() -> None:
    yaw, front, rear = _turn("rear", math.radians(20.0))
    assert front == 0.0
    assert rear == pytest.approx(math.radians(20.0), abs=1e-6)
    assert yaw > math.radians(5.0)  # a wheel turned left turns the forklift left
    yaw_right, _, _ = _turn("rear", math.radians(-20.0))
    assert yaw_right == pytest.approx(-yaw, abs=1e-9)


def test_a_front_steered_world_keeps_the_wheel_on_the_front_axle() -> None:
    _, front, rear = _turn("front", math.radians(20.0))
    assert front == pytest.approx(math.radians(20.0), abs=1e-6)
    assert rear == pytest.approx(0.0, abs=1e-12)  # k = 0 on the forklift's geometry


def test_pallet_guidance_refuses_a_final_speed_above_the_cruise() -> None:
    with pytest.raises(ValidationError, match="final_speed_mps"):
        PalletGuidanceSettings(cruise_speed_mps=0.3, final_speed_mps=0.5)
    with pytest.raises(ValidationError, match="at least one"):
        PalletGuidanceSettings(kinds=())


def test_the_tablet_page_needs_hold_to_move() -> None:
    data = load_config("forklift-sim").model_dump()
    data["tablet_page"] = {"enabled": True, "host": "127.0.0.1", "port": 0}
    VehicleConfig.model_validate(data)
    data["engagement"]["hold_to_move"] = False
    with pytest.raises(ValidationError, match="hold_to_move"):
        VehicleConfig.model_validate(data)
