"""Maneuvers driven on the simulated vehicle's own models, for the fits to recover.

Each generator runs the same pure models the twins use (``appliance.sim.vehicle.step``,
``drivers.actuators.steering_model.step_servo`` and ``PotMapping``) with a scripted
driver or servo, and samples what the daemon would record, with the sensors' noise.
The truth the fits must find is then known exactly: the pot mapping's parameters, the
servo's backlash, the vehicle's throttle and brake response.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from calibration.pot_map import PotMapResult, wheel_rad_at
from drivers.actuators.messages import SteeringMode
from drivers.actuators.steering_model import (
    PotMapping,
    ServoParams,
    ServoState,
    ServoTarget,
    step_servo,
)
from drivers.pc104.messages import MotionPattern

FloatArray = NDArray[np.float64]

HUSKY = VehicleParams(
    wheelbase_m=3.6,
    track_width_m=2.4,
    counter_steer_ratio_k=0.63,
    characteristic_speed_mps=10.0,
    max_steer_angle_rad=math.radians(32.0),
    max_steer_rate_rad_per_s=math.radians(25.0),
    brake_time_constant_s=0.3,
)
MAPPING = PotMapping()
SERVO = ServoParams()
COUNTS_PER_TYRE_DEG = MAPPING.gain_counts_per_rad * SERVO.steering_ratio * math.pi / 180.0


@dataclass(frozen=True)
class StraightDrive:
    t_s: FloatArray
    pot_counts: FloatArray
    yaw_rate_rad_per_s: FloatArray
    speed_mps: FloatArray
    steer_rate_rad_per_s: FloatArray


def straight_drive(
    seed: int,
    legs: int = 4,
    leg_s: float = 25.0,
    speed_mps: float = 3.0,
    sample_hz: float = 20.0,
    crowned_leg: int | None = None,
    crown_tyre_deg: float = 0.6,
) -> StraightDrive:
    """Straight legs along lines 3 m apart, a lane change between them.

    The driver steers back to the line from the lateral offset and the heading, with a
    slow random wander (a person never holds the wheel still); the vehicle runs on
    ``appliance.sim.vehicle.step`` (counter-steer, steering lag, sideslip). The pot reads
    the true steering-wheel angle through ``MAPPING`` with its noise, the INS's yaw rate
    and speed carry theirs. On ``crowned_leg`` the road's crown pulls the vehicle: the
    driver holds ``crown_tyre_deg`` more against it to go straight, so the pot reads off
    centre while the vehicle goes straight (the segment the fit must drop).
    """
    rng = np.random.default_rng(seed)
    dt_s = 0.02
    per_sample = round(1.0 / (sample_hz * dt_s))
    state = VehicleState(speed_mps=speed_mps)
    throttle_pct = 100.0 * HUSKY.drag_per_s * speed_mps / HUSKY.max_accel_mps2
    wander_rad, previous_wheel = 0.0, 0.0
    rows: list[tuple[float, float, float, float, float]] = []
    steps = round(legs * leg_s / dt_s)
    for i in range(steps):
        leg = int(i * dt_s // leg_s)
        crown = math.radians(crown_tyre_deg) if leg == crowned_leg else 0.0
        wander_rad += -wander_rad * dt_s / 2.0 + rng.normal(0.0, 0.0012) * math.sqrt(dt_s)
        line_y = 3.0 * leg
        steer = -0.15 * (state.y_m - line_y) / 3.0 - 1.0 * state.yaw_rad + wander_rad
        steer = max(-0.15, min(0.15, steer))
        command = VehicleCommand(
            MotionPattern.COUNTER_STEER,
            front_steer_rad=steer,
            throttle_pct=throttle_pct,
            brake_pct=0.0,
        )
        before = state
        state = step(state, command, dt_s, HUSKY)
        if i % per_sample:
            continue
        yaw_rate = math.remainder(state.yaw_rad - before.yaw_rad, math.tau) / dt_s
        # the crown turns the vehicle as much as the wheel held against it turns it back
        wheel_rad = (state.front_steer_rad + crown) * SERVO.steering_ratio
        rows.append(
            (
                state.t_s,
                MAPPING.ideal_counts(wheel_rad) + rng.normal(0.0, MAPPING.noise_counts),
                yaw_rate + rng.normal(0.0, 0.003),
                state.speed_mps + rng.normal(0.0, 0.02),
                (wheel_rad - previous_wheel) * sample_hz,
            )
        )
        previous_wheel = wheel_rad
    data = np.asarray(rows).T
    data[1] = np.round(data[1])  # the ADC gives whole counts
    return StraightDrive(data[0], data[1], data[2], data[3], data[4])


@dataclass(frozen=True)
class PotSweep:
    t_s: FloatArray
    encoder_wheel_rad: FloatArray
    pot_counts: FloatArray
    commanded_wheel_rad: FloatArray


def pot_sweep(
    seed: int,
    mapping: PotMapping = MAPPING,
    servo: ServoParams = SERVO,
    reach_rad: float = 11.0,
    step_rad: float = math.pi,
    pause_s: float = 2.0,
    encoder_zero_rad: float = 0.0,
    sample_hz: float = 50.0,
    glitches: int = 0,
) -> PotSweep:
    """Fig. 17's maneuver on the servo model: from full right to full left and back in
    half turns (``step_rad``), holding each command ``pause_s``; commanded ``reach_rad``
    is past the lock, so the ends are the servo pressing into the locks.

    The encoder reads the servo's shaft (``motor_rad``, half the backlash ahead of the
    wheel) from ``encoder_zero_rad``, in 0.001 rad ticks; the pot reads the wheel through
    ``mapping`` with its noise, in whole counts. ``glitches`` pot samples are replaced by
    a rail reading or a spike of a few hundred counts.
    """
    rng = np.random.default_rng(seed)
    dt_s = 0.005
    per_sample = round(1.0 / (sample_hz * dt_s))
    up = np.arange(-reach_rad, reach_rad + 1e-9, step_rad)
    commands = np.concatenate([up, up[-2::-1]])
    state = ServoState()
    rows: list[tuple[float, float, float, float]] = []
    t_s = 0.0
    steps_per_hold = round(pause_s / dt_s)
    for command in commands:
        target = ServoTarget(SteeringMode.POSITION, motor_setpoint_rad=float(command))
        for i in range(steps_per_hold):
            state = step_servo(state, target, dt_s, servo)
            t_s += dt_s
            if i % per_sample == 0:
                counts = mapping.ideal_counts(state.wheel_rad) + rng.normal(
                    0.0, mapping.noise_counts
                )
                encoder = round((state.motor_rad - encoder_zero_rad) * 1000.0) / 1000.0
                rows.append((t_s, encoder, counts, float(command) - encoder_zero_rad))
    data = np.asarray(rows).T
    data[2] = _pot_readings(data[2], glitches, rng)
    return PotSweep(data[0], data[1], data[2], data[3])


def hand_sweep(
    seed: int,
    mapping: PotMapping = MAPPING,
    servo: ServoParams = SERVO,
    step_rad: float = math.pi,
    pace_rad_per_s: tuple[float, float] = (1.0, 2.5),
    pause_s: tuple[float, float] = (1.5, 2.5),
    tremor_rad: float = 0.002,
    encoder_zero_rad: float = 0.0,
    sample_hz: float = 50.0,
    glitches: int = 0,
) -> PotSweep:
    """Fig. 17's maneuver by hand, as the daemon's pot-map step asks for it: from the
    centre to full right, then half turns (``step_rad``) with rests to full left and
    back the same way to full right; the ends pushed into the locks.

    A person turns the wheel: each stroke a smooth minimum-jerk move at a peak pace drawn
    from ``pace_rad_per_s``, each rest drawn from ``pause_s``, a hand's tremor
    (``tremor_rad`` rms, a tenth of a second's correlation) on top. The released servo's
    shaft follows the wheel within the backlash (``SteeringTwin._update``: clamped to the
    hands ± half the play), so the encoder trails the wheel by half the play. Nothing is
    commanded: the command column is the encoder, as the step feeds it. Encoder, pot and
    glitches as in :func:`pot_sweep`.
    """
    rng = np.random.default_rng(seed)
    dt_s = 0.01
    per_sample = round(1.0 / (sample_hz * dt_s))
    lock, half_play = servo.wheel_limit_rad, servo.backlash_rad / 2.0
    up = [-lock - 0.3, *np.arange(-lock + step_rad, lock - 1e-9, step_rad), lock + 0.3]
    stops = [0.0, *up, *up[-2::-1]]
    motor, tremor = 0.0, 0.0
    rows: list[tuple[float, float, float]] = []
    steps = 0

    def hold(target_rad: float) -> None:
        nonlocal motor, tremor, steps
        wheel = max(-lock, min(lock, target_rad + tremor))
        motor = min(max(motor, wheel - half_play), wheel + half_play)
        steps += 1
        if steps % per_sample == 0:
            counts = mapping.ideal_counts(wheel) + rng.normal(0.0, mapping.noise_counts)
            encoder = round((motor - encoder_zero_rad) * 1000.0) / 1000.0
            rows.append((steps * dt_s, encoder, counts))
        tremor += -tremor * dt_s / 0.1 + rng.normal(0.0, tremor_rad * math.sqrt(2 * dt_s / 0.1))

    for start, stop in itertools.pairwise(stops):
        duration_s = 1.875 * abs(stop - start) / rng.uniform(*pace_rad_per_s)
        for k in range(1, round(duration_s / dt_s) + 1):
            tau = min(1.0, k * dt_s / duration_s)
            hold(start + (stop - start) * tau**3 * (10.0 - 15.0 * tau + 6.0 * tau**2))
        for _ in range(round(rng.uniform(*pause_s) / dt_s)):
            hold(stop)
    data = np.asarray(rows).T
    data[2] = _pot_readings(data[2], glitches, rng)
    return PotSweep(data[0], data[1], data[2], data[1].copy())


def _pot_readings(counts: FloatArray, glitches: int, rng: np.random.Generator) -> FloatArray:
    """The ADC's whole counts, ``glitches`` of them a rail reading or a spike."""
    counts = np.clip(np.round(counts), 0, 4095)
    for index in rng.choice(counts.size, size=glitches, replace=False):
        counts[index] = rng.choice([0.0, 4095.0, counts[index] + rng.choice([-300.0, 300.0])])
    return counts


def true_wheel_rad(counts: FloatArray, mapping: PotMapping = MAPPING) -> FloatArray:
    """The wheel angle a reading means, inverting the mapping's cubic by Newton's method."""
    wheel = (counts - mapping.centre_counts) / mapping.gain_counts_per_rad
    for _ in range(30):
        error = mapping.centre_counts + mapping.gain_counts_per_rad * wheel
        error = error + mapping.cubic_counts_per_rad3 * wheel**3 - counts
        slope = mapping.gain_counts_per_rad + 3.0 * mapping.cubic_counts_per_rad3 * wheel**2
        wheel = wheel - error / slope
    return np.asarray(wheel, dtype=np.float64)


def map_error_tyre_deg(
    result: PotMapResult, mapping: PotMapping = MAPPING, relative: bool = False
) -> float:
    """Worst error of the fitted map over its usable range; ``relative``: measured from
    the fit's own centre (what the map adds to whatever error the centre has)."""
    assert result.pot_centre_counts is not None
    counts = np.linspace(result.usable_min_counts, result.usable_max_counts, 2001)
    fitted = wheel_rad_at(result.pot_to_wheel_coeffs, counts - result.pot_centre_counts)
    truth = true_wheel_rad(counts, mapping)
    if relative:
        truth = truth - true_wheel_rad(np.array([result.pot_centre_counts]), mapping)[0]
    return math.degrees(float(np.max(np.abs(fitted - truth))) / SERVO.steering_ratio)


PEDAL_VEHICLE = VehicleParams(**{**HUSKY.__dict__, "max_speed_mps": 10.0})


@dataclass(frozen=True)
class PedalSweep:
    t_s: FloatArray
    speed_mps: FloatArray
    throttle_pct: FloatArray
    brake_pct: FloatArray


def true_accel_mps2(
    throttle_pct: float, brake_pct: float, speed_mps: float, vehicle: VehicleParams = PEDAL_VEHICLE
) -> float:
    """The simulated vehicle's acceleration under steady pedals, moving
    (``appliance.sim.vehicle.step``): throttle × max accel less drag, less brake × max
    decel. The sim puts the drag inside the traction's lag, so while the speed changes
    the drag it applies is the one of ``tau`` seconds ago: solving
    ``a = target(v) + drag × tau × a`` gives the steady map over (1 - drag × tau),
    2 % more than the map itself."""
    drive = throttle_pct / 100.0 * vehicle.max_accel_mps2 - vehicle.drag_per_s * speed_mps
    steady = drive - brake_pct / 100.0 * vehicle.max_decel_mps2
    return steady / (1.0 - vehicle.drag_per_s * vehicle.traction_time_constant_s)


def pedal_sweep(
    seed: int,
    levels: tuple[float, ...] = tuple(float(x) for x in range(10, 101, 10)),
    sample_hz: float = 20.0,
    speed_noise_mps: float = 0.03,
    spikes: int = 0,
    vehicle: VehicleParams = PEDAL_VEHICLE,
) -> PedalSweep:
    """Throttle steps from standstill (each held until 6 m/s or 20 s, then a 6 s coast
    for the 0 % cells and a stop), then brake steps from 9 m/s (reached at 60 % throttle,
    then a 3 s coast, then the brake held to a stop: a hard brake needs the speed, its
    cells fill only below the speed left once it has settled), on
    ``appliance.sim.vehicle.step`` with its traction and brake lags. The speed is the
    GNSS/INS's: noise, and ``spikes`` jumps of 0.5 m/s."""
    rng = np.random.default_rng(seed)
    dt_s = 0.01
    per_sample = round(1.0 / (sample_hz * dt_s))
    state = VehicleState()
    rows: list[tuple[float, float, float, float]] = []
    step_count = 0

    def hold(throttle: float, brake: float, max_s: float, done: Callable[[float], bool]) -> None:
        nonlocal state, step_count
        command = VehicleCommand(MotionPattern.STRAIGHT, throttle_pct=throttle, brake_pct=brake)
        for _ in range(round(max_s / dt_s)):
            state = step(state, command, dt_s, vehicle)
            step_count += 1
            if step_count % per_sample == 0:
                rows.append((state.t_s, state.speed_mps, throttle, brake))
            if done(state.speed_mps):
                return

    never: Callable[[float], bool] = lambda _: False  # noqa: E731
    for level in levels:
        hold(level, 0.0, 20.0, lambda v: v >= 6.0)
        hold(0.0, 0.0, 6.0, never)
        hold(0.0, 60.0, 10.0, lambda v: v <= 0.0)
    for level in levels:
        hold(60.0, 0.0, 30.0, lambda v: v >= 9.0)
        hold(0.0, 0.0, 3.0, never)
        hold(0.0, level, 30.0, lambda v: v <= 0.0)
    data = np.asarray(rows).T
    data[1] += rng.normal(0.0, speed_noise_mps, data.shape[1])
    data[1, rng.choice(data.shape[1], size=spikes, replace=False)] += 0.5
    return PedalSweep(data[0], data[1], data[2], data[3])
