"""Kinematics of the simulated vehicle: four-wheel counter-steer and the flat-bed's patterns.

The model is the one Stanley et al. used to evaluate their tracker (after Kuwata et al.),
a bicycle with both axles steered and an empirical sideslip gain:

    yaw_rate = v / L * (tan(phi_f) + tan(phi_r)) * G_ss,   G_ss = 1 / (1 + (v / V_char)^2)

with ``phi_r`` positive when the rear wheels counter-steer (turn opposite to the front),
so proportional counter-steer is ``phi_r = k * phi_f`` and crab (oblique) motion is
``phi_r = -phi_f``: the yaw rate vanishes and the body translates at the steer angle.
The velocity direction at the geometric centre follows from the wheel angles
(``tan(beta) = (tan(phi_f) - tan(phi_r)) / 2`` for a centre midway between the axles).

Actuators are not ideal: steering follows its command with a first-order lag and a rate
limit, traction is a lagged acceleration from the throttle, and the brake's force builds
up with its own lag (zero unless the vehicle's plant says otherwise). The flat-bed's upper
platform (where the scanners are) lags the chassis in yaw when turning, as Qian et al.
report; its pose is what the simulated scanners see.

Everything here is pure: ``step(state, command, dt_s, params) -> state``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from appliance.config.models import VehicleConfig
from drivers.pc104.messages import MotionPattern


@dataclass(frozen=True)
class VehicleParams:
    wheelbase_m: float
    track_width_m: float
    counter_steer_ratio_k: float
    characteristic_speed_mps: float
    max_steer_angle_rad: float
    max_steer_rate_rad_per_s: float
    steer_time_constant_s: float = 0.15
    max_accel_mps2: float = 1.0
    max_decel_mps2: float = 3.0
    traction_time_constant_s: float = 0.4
    # Brake force builds up (and releases) with this lag; 0: at once. The Husky's
    # cable-pulled brake is not instantaneous (Stanley et al.); the flat-bed's PC104
    # drives its own brake and the sim keeps it immediate.
    brake_time_constant_s: float = 0.0
    drag_per_s: float = 0.05  # rolling resistance, as a fraction of speed per second
    max_speed_mps: float = 6.0
    # Upper platform vs chassis (flat-bed): yaw offset gained per rad of chassis rotation,
    # relaxing with its own time constant once the turn ends.
    platform_yaw_gain: float = 0.0
    platform_time_constant_s: float = 2.0
    # The pedals' shape (``pedal_fraction``): dead band (0..1 of travel) and exponent.
    throttle_deadband: float = 0.0
    throttle_exponent: float = 1.0
    brake_deadband: float = 0.0
    brake_exponent: float = 1.0

    @classmethod
    def from_config(cls, config: VehicleConfig) -> VehicleParams:
        flatbed = config.kind == "flatbed"
        pedals = config.simulation.pedals
        return cls(
            wheelbase_m=config.geometry.wheelbase_m,
            track_width_m=config.geometry.track_width_m,
            counter_steer_ratio_k=(
                config.geometry.counter_steer_ratio_k
                if config.simulation.steering.counter_steer_ratio_k is None
                else config.simulation.steering.counter_steer_ratio_k
            ),
            characteristic_speed_mps=config.geometry.characteristic_speed_mps,
            max_steer_angle_rad=math.radians(config.limits.max_steer_angle_deg),
            max_steer_rate_rad_per_s=math.radians(config.limits.max_steer_rate_deg_per_s),
            max_speed_mps=config.limits.max_speed_mps * 1.5,
            platform_yaw_gain=0.01 if flatbed else 0.0,
            throttle_deadband=pedals.throttle_deadband_pct / 100.0,
            throttle_exponent=pedals.throttle_exponent,
            brake_deadband=pedals.brake_deadband_pct / 100.0,
            brake_exponent=pedals.brake_exponent,
        )


@dataclass(frozen=True)
class VehicleCommand:
    """What the lower layers apply to the wheels (the twins translate into this)."""

    pattern: MotionPattern = MotionPattern.STOP
    front_steer_rad: float = 0.0  # also the crab angle in OBLIQUE
    rear_steer_rad: float = 0.0  # used in REAR_STEER; positive = counter-steer direction
    throttle_pct: float = 0.0
    brake_pct: float = 100.0
    reverse: bool = False


@dataclass(frozen=True)
class VehicleState:
    t_s: float = 0.0
    x_m: float = 0.0
    y_m: float = 0.0
    yaw_rad: float = 0.0
    speed_mps: float = 0.0  # signed: negative when reversing
    accel_mps2: float = 0.0
    front_steer_rad: float = 0.0
    rear_steer_rad: float = 0.0  # positive = counter-steer direction
    platform_yaw_offset_rad: float = 0.0
    odometer_m: float = 0.0
    brake_level: float = 0.0  # 0..1, what the brake applies now (lags its command)

    @property
    def platform_yaw_rad(self) -> float:
        return self.yaw_rad + self.platform_yaw_offset_rad


def sideslip_gain(speed_mps: float, characteristic_speed_mps: float) -> float:
    return 1.0 / (1.0 + (speed_mps / characteristic_speed_mps) ** 2)


def wheel_targets(command: VehicleCommand, params: VehicleParams) -> tuple[float, float]:
    """Front and rear wheel angle targets the pattern asks for."""
    limit = params.max_steer_angle_rad
    front = max(-limit, min(limit, command.front_steer_rad))
    match command.pattern:
        case MotionPattern.STOP | MotionPattern.STRAIGHT | MotionPattern.TURN_AROUND:
            return 0.0, 0.0
        case MotionPattern.OBLIQUE:
            return front, -front
        case MotionPattern.FRONT_STEER:
            return front, 0.0
        case MotionPattern.REAR_STEER:
            return 0.0, max(-limit, min(limit, command.rear_steer_rad))
        case MotionPattern.COUNTER_STEER:
            return front, params.counter_steer_ratio_k * front


def pedal_fraction(pedal: float, deadband: float, exponent: float) -> float:
    """The fraction of full traction (or braking) a pedal at ``pedal`` (0..1) gives:
    nothing in the dead band, then a power law to 1 at full travel."""
    if pedal <= deadband:
        return 0.0
    return float(min(1.0, (pedal - deadband) / (1.0 - deadband)) ** exponent)


def pedal_accel_mps2(
    params: VehicleParams, throttle_pct: float, brake_pct: float, speed_mps: float
) -> float:
    """The steady acceleration (forward, on the flat) at held pedals and ``speed_mps``:
    what a pedal map measures, the truth the pedal sweep's fit is compared with. The
    brake only slows a moving vehicle; at standstill it holds."""
    drive = params.max_accel_mps2 * pedal_fraction(
        throttle_pct / 100.0, params.throttle_deadband, params.throttle_exponent
    )
    braking = params.max_decel_mps2 * pedal_fraction(
        brake_pct / 100.0, params.brake_deadband, params.brake_exponent
    )
    return drive - params.drag_per_s * speed_mps - (braking if speed_mps > 0.0 else 0.0)


def _approach(value: float, target: float, dt_s: float, tau_s: float, rate_limit: float) -> float:
    """First-order lag toward target, with a rate limit."""
    alpha = 1.0 - math.exp(-dt_s / tau_s) if tau_s > 0 else 1.0
    delta = (target - value) * alpha
    max_delta = rate_limit * dt_s
    return value + max(-max_delta, min(max_delta, delta))


def step(
    state: VehicleState, command: VehicleCommand, dt_s: float, params: VehicleParams
) -> VehicleState:
    """Advance the vehicle by ``dt_s`` under ``command``."""
    if dt_s <= 0:
        return state
    front_target, rear_target = wheel_targets(command, params)
    front = _approach(
        state.front_steer_rad,
        front_target,
        dt_s,
        params.steer_time_constant_s,
        params.max_steer_rate_rad_per_s,
    )
    rear = _approach(
        state.rear_steer_rad,
        rear_target,
        dt_s,
        params.steer_time_constant_s,
        params.max_steer_rate_rad_per_s,
    )

    # Traction: throttle accelerates in the selected direction, brake opposes motion.
    throttle = 0.0 if command.pattern is MotionPattern.STOP else command.throttle_pct / 100.0
    brake = 1.0 if command.pattern is MotionPattern.STOP else command.brake_pct / 100.0
    direction = -1.0 if command.reverse else 1.0
    traction = pedal_fraction(
        max(0.0, min(1.0, throttle)), params.throttle_deadband, params.throttle_exponent
    )
    drive_mps2 = direction * traction * params.max_accel_mps2
    drive_mps2 -= params.drag_per_s * state.speed_mps
    accel = _approach(state.accel_mps2, drive_mps2, dt_s, params.traction_time_constant_s, 1e9)
    speed = state.speed_mps + accel * dt_s
    brake_target = pedal_fraction(
        max(0.0, min(1.0, brake)), params.brake_deadband, params.brake_exponent
    )
    brake_level = _approach(
        state.brake_level, brake_target, dt_s, params.brake_time_constant_s, 1e9
    )
    braking_mps = brake_level * params.max_decel_mps2 * dt_s
    speed = math.copysign(max(0.0, abs(speed) - braking_mps), speed)
    speed = max(-params.max_speed_mps, min(params.max_speed_mps, speed))

    if command.pattern is MotionPattern.TURN_AROUND:
        turn_radius_m = math.hypot(params.wheelbase_m / 2, params.track_width_m / 2)
        yaw_rate = speed / turn_radius_m
        vx_body = vy_body = 0.0
    else:
        tan_f, tan_r = math.tan(front), math.tan(rear)
        beta = math.atan((tan_f - tan_r) / 2.0)
        gain = sideslip_gain(speed, params.characteristic_speed_mps)
        yaw_rate = speed * math.cos(beta) / params.wheelbase_m * (tan_f + tan_r) * gain
        vx_body = speed * math.cos(beta)
        vy_body = speed * math.sin(beta)

    yaw_mid = state.yaw_rad + 0.5 * yaw_rate * dt_s  # midpoint rule: exact for straight lines
    cos_y, sin_y = math.cos(yaw_mid), math.sin(yaw_mid)
    x = state.x_m + (vx_body * cos_y - vy_body * sin_y) * dt_s
    y = state.y_m + (vx_body * sin_y + vy_body * cos_y) * dt_s
    yaw = math.remainder(state.yaw_rad + yaw_rate * dt_s, math.tau)

    relax = math.exp(-dt_s / params.platform_time_constant_s)
    platform_offset = (
        state.platform_yaw_offset_rad * relax - params.platform_yaw_gain * yaw_rate * dt_s
    )
    # Every field anew, by name: ``dataclasses.replace`` costs more than the step itself.
    return VehicleState(
        t_s=state.t_s + dt_s,
        x_m=x,
        y_m=y,
        yaw_rad=yaw,
        speed_mps=speed,
        accel_mps2=accel,
        front_steer_rad=front,
        rear_steer_rad=rear,
        platform_yaw_offset_rad=platform_offset,
        odometer_m=state.odometer_m + abs(speed) * dt_s,
        brake_level=brake_level,
    )
