"""The look-ahead tuning on the simulated vehicle, faster than real time.

The same :class:`~appliance.core.route_tuning.RouteTuning` the daemon's route source
arms (the program laying the courses, the route chain tracking them with each run's
candidate), on the kinematic model of Stanley et al. (G_ss, the servo's lag and rate
limit) with the pedal speed controller, and an operator who engages when a run is laid
and disengages when it has stopped at its course's end. Each run starts where the last
one stopped (the plane is open; the technician's drive back to a start is left out).

Two cross-track errors per cycle: the one the daemon sees (its blended pose against the
course, what the step fits on the vehicle) and the truth (the true anchor against the
course): the benchmark judges the choice by the truth.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.config.models import VehicleConfig
from appliance.config.tuning_models import LookaheadTuningSettings
from appliance.core.route_autopilot import follow_params, tuning_params
from appliance.core.route_tuning import RouteTuning
from appliance.core.wish import Observation
from appliance.guidance.lookahead_samples import RunSample
from appliance.guidance.lookahead_tuning import TuningPhase
from appliance.guidance.pedal_speed import PedalSpeedController, PedalSpeedParams
from appliance.localization.gnss_pose import GnssPose
from appliance.sim.track_run import TrackRunParams, _Fixes, _Truth, husky_plant, pursuit_anchor
from appliance.sim.vehicle import VehicleCommand, VehicleState, step
from drivers.pc104.messages import MotionPattern


@dataclass(frozen=True)
class TuningSimParams:
    loc_noise_m: float = 0.02  # σ per axis of each fix (the figure)
    seed: int = 1
    control_hz: float = 50.0
    world_hz: float = 100.0
    run_timeout_s: float = 240.0


@dataclass
class TuningSimResult:
    samples: list[RunSample]  # the daemon's view: what the step fits
    truth: list[RunSample]  # the true anchor's cross-track, cycle for cycle
    run_durations_s: dict[int, float]
    distance_m: float
    duration_s: float
    wall_s: float
    aborted: int


def run_tuning(
    config: VehicleConfig,
    settings: LookaheadTuningSettings,
    sim: TuningSimParams = TuningSimParams(),
    first_run: int = 0,
    last_run: int | None = None,
) -> TuningSimResult:
    """Drive runs ``first_run``..``last_run`` (inclusive; None: to the end)."""
    started = time.perf_counter()
    follow = follow_params(config)
    params = tuning_params(config.model_copy(update={"lookahead_tuning": settings}))
    last = len(params.runs) - 1 if last_run is None else last_run
    tuning = RouteTuning(follow, params, first_run)
    plant = husky_plant(config, 0.3)
    pedals = PedalSpeedController(PedalSpeedParams.from_limits(config.limits))
    fixes = _Fixes(
        TrackRunParams(loc_noise_m=sim.loc_noise_m, seed=sim.seed),
        config.positioning.antenna_forward_m,
    )
    state = VehicleState()
    world_dt, control_dt = 1.0 / sim.world_hz, 1.0 / sim.control_hz
    t_s, next_control = 0.0, 0.0
    engaged, engaged_at = False, 0.0
    seq = 0
    gnss: GnssPose | None = None
    command = VehicleCommand(pattern=MotionPattern.COUNTER_STEER, brake_pct=30.0)
    samples: list[RunSample] = []
    truth_samples: list[RunSample] = []
    durations: dict[int, float] = {}
    truth: _Truth | None = None
    truth_for: object = None
    run_started = 0.0
    while True:
        run = tuning.program.run
        if run is None or run.index > last:
            break
        if t_s - run_started > sim.run_timeout_s:
            raise RuntimeError(f"run {run.index} did not finish in {sim.run_timeout_s} s")
        for fix in fixes.update(t_s, state):
            seq, gnss = seq + 1, fix
        if t_s + 1e-9 >= next_control:
            next_control += control_dt
            observation = Observation(
                t_s,
                state.speed_mps,
                state.front_steer_rad,
                engaged=engaged,
                gnss=gnss,
                gnss_seq=seq,
            )
            wish = tuning.update(observation, state.speed_mps, state.front_steer_rad)
            status = wish.status.get("tuning", {})
            phase = status.get("phase") if isinstance(status, dict) else None
            if not engaged and wish.ready and abs(state.speed_mps) < 0.01:
                engaged, engaged_at = True, t_s
                tuning.reset(state.speed_mps, state.front_steer_rad)
                pedals.reset(throttle_pct=0.0, brake_pct=0.0)
            elif engaged and (
                not wish.ready
                or (
                    phase == TuningPhase.FINISH
                    and abs(state.speed_mps) < 0.01
                    and t_s - engaged_at > 1.0
                )
            ):
                engaged = False
                durations[run.index] = t_s - run_started
                run_started = t_s
            if engaged and wish.ready:
                target = wish.max_speed_mps or 0.0
                pedal = pedals.update(target, state.speed_mps, None, t_s)
                command = VehicleCommand(
                    pattern=MotionPattern.COUNTER_STEER,
                    front_steer_rad=wish.steer_tyre_rad,
                    throttle_pct=pedal.throttle_pct,
                    brake_pct=pedal.brake_pct,
                )
            else:
                command = VehicleCommand(
                    pattern=MotionPattern.COUNTER_STEER,
                    front_steer_rad=state.front_steer_rad,
                    brake_pct=30.0,
                )
            if isinstance(status, dict):
                follower = tuning.follower
                if follower is not None and follower.route_m is not truth_for:
                    truth_for, truth = follower.route_m, _Truth(follower.route_m)
                anchor = pursuit_anchor(state, config.geometry.anchor_point_forward_m)
                true_error = None if truth is None else truth.update(anchor.x_m, anchor.y_m)[0]
                run_index = status.get("run")
                samples.append(
                    RunSample(t_s, run_index, phase, status.get("cross_track_m"), state.speed_mps)
                )
                truth_samples.append(RunSample(t_s, run_index, phase, true_error, state.speed_mps))
        state = step(state, command, world_dt, plant)
        t_s += world_dt
    return TuningSimResult(
        samples=samples,
        truth=truth_samples,
        run_durations_s=durations,
        distance_m=state.odometer_m,
        duration_s=t_s,
        wall_s=time.perf_counter() - started,
        aborted=tuning.program.aborted,
    )


def rms(values: Sequence[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if len(values) else math.nan
