"""The pedal sweep on the simulated vehicle, faster than real time, and the maps' truth.

What the sweep and its fit are worth is a question of physics and of the grid, not of the
daemon's plumbing (the runtime test drives the same program through the daemon), so it is
answered here at simulation speed: the vehicle file's ``[pedal_sweep]`` program
(:class:`~appliance.guidance.pedal_sweep.PedalSweep`) drives the kinematic model's pedals
through the same pedal limiter the core uses and through actuators with the board twins'
lag and rate, the speed is the GNSS/INS's (10 Hz epochs held between them, rounded as its
RMC sentence rounds it), and each control cycle becomes a sample as the daemon's tap
makes it. The fit is compared with :func:`appliance.sim.vehicle.pedal_accel_mps2`, the
simulated vehicle's own answer to held pedals.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance.config import parts
from appliance.config.models import VehicleConfig
from appliance.guidance.pedal_sweep import PedalSweep, SweepPhase
from appliance.sim.twins.boards import approach_pct
from appliance.sim.vehicle import (
    VehicleCommand,
    VehicleParams,
    VehicleState,
    pedal_accel_mps2,
    step,
)
from calibration.pedal_map_cells import PedalMap
from drivers.pc104.messages import MotionPattern
from safety.limits import ActuatorCommand, CommandLimiter

KNOT_MPS = 1852.0 / 3600.0


@dataclass(frozen=True)
class SweepRunParams:
    control_hz: float = 50.0
    world_hz: float = 100.0
    gnss_hz: float = 10.0
    actuator_tau_s: float = 0.08  # the pedal twins'
    actuator_rate_pct_per_s: float = 250.0
    timeout_s: float = 1800.0


@dataclass(frozen=True)
class SweepRun:
    samples: list[dict[str, Any]]  # as the daemon's tap makes them (the fit's fields)
    duration_s: float
    distance_m: float
    runs: int
    done: bool


def run_sweep(config: VehicleConfig, params: SweepRunParams = SweepRunParams()) -> SweepRun:
    """The whole sweep from a standstill in SPEED_HOLD, nobody interrupting it."""
    vehicle = VehicleParams.from_config(config)
    sweep = PedalSweep(parts.pedal_sweep_params(config))
    limiter = CommandLimiter(parts.limit_params(config.limits))
    state = VehicleState()
    throttle_act = brake_act = 0.0
    dt_control = 1.0 / params.control_hz
    substeps = max(1, round(params.world_hz / params.control_hz))
    dt_world = dt_control / substeps
    epoch_every = max(1, round(params.control_hz / params.gnss_hz))
    speed_reading = 0.0
    samples: list[dict[str, Any]] = []
    cycle = 0
    while cycle * dt_control < params.timeout_s and not sweep.done:
        now_s = cycle * dt_control
        if cycle % epoch_every == 0:  # a new epoch: RMC's knots to three decimals
            speed_reading = round(abs(state.speed_mps) / KNOT_MPS, 3) * KNOT_MPS
        command = sweep.update(speed_reading, now_s, in_control=True)
        limited, _ = limiter.update(
            ActuatorCommand(None, command.throttle_pct, command.brake_pct), speed_reading, now_s
        )
        throttle_cmd = 0.0 if limited.brake_pct > 0.0 else limited.throttle_pct
        for _ in range(substeps):
            throttle_act = approach_pct(
                throttle_act,
                throttle_cmd,
                dt_world,
                params.actuator_tau_s,
                params.actuator_rate_pct_per_s,
            )
            brake_act = approach_pct(
                brake_act,
                limited.brake_pct,
                dt_world,
                params.actuator_tau_s,
                params.actuator_rate_pct_per_s,
            )
            state = step(
                state,
                VehicleCommand(
                    pattern=MotionPattern.COUNTER_STEER,
                    throttle_pct=throttle_act,
                    brake_pct=brake_act,
                ),
                dt_world,
                vehicle,
            )
        samples.append(
            {
                "t_s": now_s,
                "mode": "speed_hold",
                "sweep_phase": str(command.phase),
                "sweep_run": command.run,
                "speed_mps": speed_reading,
                "throttle_actuator_pct": throttle_act,
                "brake_actuator_pct": brake_act,
            }
        )
        cycle += 1
    return SweepRun(
        samples=samples,
        duration_s=cycle * dt_control,
        distance_m=state.odometer_m,
        runs=sweep.params.runs,
        done=sweep.phase is SweepPhase.DONE,
    )


def map_errors_mps2(config: VehicleConfig, pedal_map: PedalMap, brake: bool) -> np.ndarray:
    """Fitted minus true acceleration at every cell (NaN where the map has none)."""
    vehicle = VehicleParams.from_config(config)
    errors = np.full(pedal_map.accel_mps2.shape, math.nan)
    for (i, j), value in np.ndenumerate(pedal_map.accel_mps2):
        if np.isfinite(value):
            level, speed = float(pedal_map.pedal_pct[i]), float(pedal_map.speed_mps[j])
            truth = pedal_accel_mps2(
                vehicle, 0.0 if brake else level, level if brake else 0.0, speed
            )
            errors[i, j] = value - truth
    return errors


def full_scale_mps2(config: VehicleConfig, pedal_map: PedalMap, brake: bool) -> float:
    """The map's span: from coasting to its top level, at the lowest band (what a 5 %
    error is counted against)."""
    vehicle = VehicleParams.from_config(config)
    top = float(pedal_map.pedal_pct[-1])
    speed = float(pedal_map.speed_mps[0])
    coast = pedal_accel_mps2(vehicle, 0.0, 0.0, speed)
    end = pedal_accel_mps2(vehicle, 0.0 if brake else top, top if brake else 0.0, speed)
    return abs(end - coast)
