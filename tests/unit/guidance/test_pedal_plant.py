"""The speed controller's pedal model: the linear one it always had, the sweep's maps.

The map's inversion is checked against its own forward reading (``accel_at_throttle``)
and against values worked out by hand; the controller on the maps is checked in closed
loop on the simulated vehicle with pedals the linear model does not describe, where the
maps the sweep measured must track a speed profile better than the linear gains.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.config import parts
from appliance.config.calibration import Calibration
from appliance.config.calibration_pedals import PedalsCalibration
from appliance.config.simulated_calibration import simulated_calibration
from appliance.guidance.pedal_plant import (
    LinearPlant,
    MapPlant,
    PedalPlant,
    PedalTable,
    table_from_bands,
)
from appliance.guidance.pedal_speed import PedalSpeedController
from appliance.maneuvers.pedals_step import PedalsStep, map_table
from appliance.maneuvers.steps import StepContext
from appliance.sim.sweep_run import run_sweep
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.pc104.messages import MotionPattern
from tests.unit.guidance.test_pedal_sweep import shaped_husky

NAN = math.nan
LINEAR = LinearPlant(0.01, 0.03, 0.05)
# Two bands (1 and 3 m/s); coasting measured at 3 m/s only, 40 % at 1 m/s only.
THROTTLE = PedalTable(
    pedal_pct=(0.0, 20.0, 40.0),
    speed_mps=(1.0, 3.0),
    accel_mps2=((NAN, -0.15), (0.2, 0.1), (0.5, NAN)),
)
BRAKE = PedalTable(
    pedal_pct=(0.0, 10.0, 30.0),
    speed_mps=(1.0, 3.0),
    accel_mps2=((NAN, -0.15), (-0.4, -0.5), (-1.2, -1.3)),
)
MAP = MapPlant(THROTTLE, BRAKE, LINEAR)


def test_the_map_read_by_hand() -> None:
    # At 3 m/s: coasting measured; 20 % gives 0.1, so an effort of 0.25 above coasting
    # (net 0.1) is 20 %, half of it is 10 %.
    assert MAP.coast_accel_mps2(3.0) == pytest.approx(-0.15)
    assert MAP.throttle_pct(0.25, 3.0) == pytest.approx(20.0)
    assert MAP.throttle_pct(0.125, 3.0) == pytest.approx(10.0)
    # Past the last level measured there: the linear gain from it (0.01 m/s² per %).
    assert MAP.throttle_pct(0.35, 3.0) == pytest.approx(30.0)
    # At 1 m/s no coasting was measured: the linear model's, -0.05.
    assert MAP.coast_accel_mps2(1.0) == pytest.approx(-0.05)
    assert MAP.throttle_pct(0.4, 1.0) == pytest.approx(30.0)  # net 0.35, between 20 and 40
    # Between the bands, levels both have: 20 % at 2 m/s gives 0.15.
    assert MAP.accel_at_throttle_mps2(20.0, 2.0) == pytest.approx(0.15)
    # Brake at 3 m/s: an effort of -0.35 (net -0.5) is 10 %; -1.15 (net -1.3) is 30 %.
    assert MAP.brake_pct(-0.35, 3.0) == pytest.approx(10.0)
    assert MAP.brake_pct(-1.15, 3.0) == pytest.approx(30.0)
    assert MAP.brake_pct(0.1, 3.0) == 0.0 and MAP.throttle_pct(-0.1, 3.0) == 0.0
    assert math.isnan(MAP.throttle_pct(NAN, 3.0))


@given(st.floats(0.0, 1.0), st.floats(0.0, 5.0))
def test_the_throttle_inverse_reads_back_and_rises(effort: float, speed: float) -> None:
    pct = MAP.throttle_pct(effort, speed)
    assert pct >= 0.0
    net = MAP.accel_at_throttle_mps2(pct, speed)
    assert net == pytest.approx(effort + MAP.coast_accel_mps2(speed), abs=1e-9)
    assert MAP.throttle_pct(effort + 0.01, speed) >= pct


@given(st.floats(-2.0, 0.0), st.floats(0.0, 5.0))
def test_more_braking_wanted_never_gives_less_brake(effort: float, speed: float) -> None:
    assert 0.0 <= MAP.brake_pct(effort, speed) <= MAP.brake_pct(effort - 0.01, speed)


def test_the_linear_plant_is_the_controllers_old_arithmetic() -> None:
    assert LINEAR.throttle_pct(0.25, 3.0) == 0.25 / 0.01
    assert LINEAR.brake_pct(-0.3, 3.0) == 0.3 / 0.03
    assert LINEAR.accel_at_throttle_mps2(45.0, 3.0) == 45.0 * 0.01 - 0.05 * 3.0


def test_the_files_bands_become_a_full_table() -> None:
    table = table_from_bands((0.0, 20.0, 40.0), (1.0, 3.0), (1, 0), ((0.2, 0.5), (-0.15, 0.1)))
    assert np.array_equal(
        np.asarray(table.accel_mps2), np.asarray(THROTTLE.accel_mps2), equal_nan=True
    )


def speed_profile_rms_mps(plant: PedalPlant | None) -> float:
    """The controller holding a profile of set speeds on the shaped Husky: the RMS of the
    speed about the controller's own reference (what it meant to do)."""
    config = shaped_husky()
    vehicle = VehicleParams.from_config(config)
    controller = PedalSpeedController(parts.pedal_speed_params(config), plant)
    state = VehicleState()
    profile = ((0.0, 2.0), (20.0, 3.5), (40.0, 1.0), (60.0, 4.0), (80.0, 0.0))
    errors = []
    for i in range(int(90.0 / 0.02)):
        now_s = i * 0.02
        target = [speed for start, speed in profile if start <= now_s][-1]
        command = controller.update(target, state.speed_mps, None, now_s)
        pedals = VehicleCommand(
            pattern=MotionPattern.COUNTER_STEER,
            throttle_pct=command.throttle_pct,
            brake_pct=command.brake_pct,
        )
        for _ in range(2):
            state = step(state, pedals, 0.01, vehicle)
        errors.append(state.speed_mps - command.reference_speed_mps)
    return float(np.sqrt(np.mean(np.square(errors))))


def test_the_swept_maps_track_speed_better_than_the_linear_gains() -> None:
    config = shaped_husky()
    sweep = PedalsStep(StepContext(config, None))
    assert sweep.fit(run_sweep(config).samples, None).accepted
    fitted = sweep.accumulator.fit()
    pedals = PedalsCalibration(throttle=map_table(fitted.throttle), brake=map_table(fitted.brake))
    calibration = Calibration.from_file(simulated_calibration(config.name))
    plant = parts.pedal_plant(config, dataclasses.replace(calibration, pedals=pedals))
    assert plant is not None
    assert parts.pedal_plant(config, calibration) is None  # no maps: the linear model
    linear, mapped = speed_profile_rms_mps(None), speed_profile_rms_mps(plant)
    assert mapped < 0.8 * linear, (mapped, linear)
