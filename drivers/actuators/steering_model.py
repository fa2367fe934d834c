"""Physics of the steering servo and the steering potentiometer, as pure functions.

The servo sits on the steering column and turns the wheel through a coupling with free play
(backlash). It slews at a limited rate, ignores errors inside its deadband, and can only push
as hard as its torque limit, which falls with supply voltage (the paper's "torque of the
steering servo was lowered because of a voltage change"); the load is dry friction plus a
self-centring term that grows with the wheel angle. If the load exceeds what the servo can
give, the wheel stays where it is and the servo stalls against the play.

The pot reports the wheel angle as raw 12-bit counts through the kind of mapping a real
installation has: an off-centre straight-ahead reading, a gain, a small cubic term and a
count or two of noise. Calibration is expected to recover it; the true parameters live in
:class:`PotMapping` so tests can check the fit.

Angles here are *steering-wheel* angles in radians; the tyre angle is wheel / ratio.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from drivers.actuators.messages import POT_FULL_SCALE_COUNTS, SteeringMode


@dataclass(frozen=True)
class ServoParams:
    steering_ratio: float = 18.0  # wheel rad per tyre rad
    wheel_limit_rad: float = 9.42  # lock: 30 deg of tyre x 18
    max_rate_rad_per_s: float = 6.0  # servo slew, wheel side
    position_gain_per_s: float = 8.0  # position loop: rate = gain x error
    deadband_rad: float = 0.01
    backlash_rad: float = 0.04  # total free play between servo and wheel
    torque_limit_nm: float = 15.0
    # Servo torque is not symmetric in practice (Stanley et al.): the limit when turning
    # left (positive) is scaled by (1 - asymmetry), right by (1 + asymmetry).
    torque_asymmetry: float = 0.0
    friction_nm: float = 4.0
    centering_nm_per_rad: float = 0.6
    free_play_torque_nm: float = 0.3  # moving through the backlash
    torque_constant_nm_per_a: float = 1.5
    nominal_supply_v: float = 24.0


@dataclass(frozen=True)
class ServoState:
    motor_rad: float = 0.0  # servo output shaft, expressed as a wheel angle
    wheel_rad: float = 0.0
    torque_nm: float = 0.0  # what the servo applies (signed)


@dataclass(frozen=True)
class ServoTarget:
    mode: SteeringMode
    motor_setpoint_rad: float = 0.0
    torque_setpoint_nm: float = 0.0


def load_torque_nm(wheel_rad: float, params: ServoParams) -> float:
    """Torque needed to move the wheel at ``wheel_rad`` (magnitude)."""
    return params.friction_nm + params.centering_nm_per_rad * abs(wheel_rad)


def available_torque_nm(direction: float, params: ServoParams, torque_scale: float) -> float:
    """The servo's torque limit in ``direction`` (sign), scaled by supply health."""
    side = 1.0 - params.torque_asymmetry if direction > 0 else 1.0 + params.torque_asymmetry
    return max(0.0, params.torque_limit_nm * side * torque_scale)


def position_rate_rad_per_s(error_rad: float, params: ServoParams) -> float:
    """Deadband, then a proportional rate clipped to the slew limit."""
    if abs(error_rad) <= params.deadband_rad:
        return 0.0
    rate = params.position_gain_per_s * error_rad
    return max(-params.max_rate_rad_per_s, min(params.max_rate_rad_per_s, rate))


def _move(
    state: ServoState, rate: float, dt_s: float, push_nm: float, params: ServoParams
) -> ServoState:
    """Move the motor by ``rate`` x ``dt_s``, dragging the wheel through the backlash.

    ``push_nm`` is how hard the servo can push in the direction of motion. The wheel only
    moves once the play is taken up, and only if ``push_nm`` beats the load.
    """
    if rate == 0.0:
        return replace(state, torque_nm=0.0)
    half_play = params.backlash_rad / 2.0
    direction = 1.0 if rate > 0 else -1.0
    motor = state.motor_rad + rate * dt_s
    wheel = state.wheel_rad
    gap = (motor - wheel) * direction - half_play  # > 0: the coupling is pushing the wheel
    if gap <= 0.0:
        return ServoState(motor, wheel, direction * params.free_play_torque_nm)
    load = load_torque_nm(wheel, params)
    if push_nm < load:  # stall: the servo presses against the wheel and gets no further
        return ServoState(wheel + direction * half_play, wheel, direction * push_nm)
    wheel = motor - direction * half_play
    if abs(wheel) > params.wheel_limit_rad:  # at the steering lock
        wheel = math.copysign(params.wheel_limit_rad, wheel)
        motor = wheel + direction * half_play
    return ServoState(motor, wheel, direction * load)


def step_servo(
    state: ServoState,
    target: ServoTarget,
    dt_s: float,
    params: ServoParams,
    torque_scale: float = 1.0,
) -> ServoState:
    """Advance the servo by ``dt_s``. ``torque_scale`` < 1 models low voltage or torque loss."""
    if dt_s <= 0.0:
        return state
    match target.mode:
        case SteeringMode.RELEASE:
            return replace(state, torque_nm=0.0)  # clutch out: nothing moves the wheel
        case SteeringMode.POSITION:
            rate = position_rate_rad_per_s(target.motor_setpoint_rad - state.motor_rad, params)
            push = available_torque_nm(rate, params, torque_scale)
            return _move(state, rate, dt_s, push, params)
        case SteeringMode.TORQUE:
            return _torque_step(state, target.torque_setpoint_nm, dt_s, params, torque_scale)
    return state


def _torque_step(
    state: ServoState, setpoint_nm: float, dt_s: float, params: ServoParams, torque_scale: float
) -> ServoState:
    """Torque mode: apply the setpoint (clipped); speed grows with the torque left over."""
    if setpoint_nm == 0.0:
        return replace(state, torque_nm=0.0)
    direction = 1.0 if setpoint_nm > 0 else -1.0
    push = min(abs(setpoint_nm), available_torque_nm(direction, params, torque_scale))
    in_play = (state.motor_rad - state.wheel_rad) * direction < params.backlash_rad / 2.0
    resistance = params.free_play_torque_nm if in_play else load_torque_nm(state.wheel_rad, params)
    surplus = push - resistance
    if surplus <= 0.0:
        return replace(state, torque_nm=direction * push)
    fraction = min(1.0, surplus / max(params.torque_limit_nm, 1e-9))
    return _move(state, direction * params.max_rate_rad_per_s * fraction, dt_s, push, params)


@dataclass(frozen=True)
class PotMapping:
    """Raw pot counts as a function of the steering-wheel angle (truth, for the twin)."""

    centre_counts: float = 2131.0  # straight ahead: not 2048, it depends on the installation
    gain_counts_per_rad: float = 180.0
    cubic_counts_per_rad3: float = -0.35
    noise_counts: float = 0.8  # standard deviation

    def ideal_counts(self, wheel_rad: float) -> float:
        return (
            self.centre_counts
            + self.gain_counts_per_rad * wheel_rad
            + self.cubic_counts_per_rad3 * wheel_rad**3
        )


def pot_counts(wheel_rad: float, mapping: PotMapping, noise_counts: float = 0.0) -> int:
    """ADC reading: the ideal mapping plus the given noise sample, rounded and clipped."""
    raw = mapping.ideal_counts(wheel_rad) + noise_counts
    if not math.isfinite(raw):
        return 0
    return max(0, min(POT_FULL_SCALE_COUNTS, round(raw)))
