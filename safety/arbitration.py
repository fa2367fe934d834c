"""Arbitration: operator > safety > autopilot, and only allow-listed set-points pass.

The operator always wins: when a pedal or the steering wheel is overridden, automatic
control of that channel (speed or steering) lets go within the same cycle. Then
safety: when control is revoked (a fault, a stale critical input) the safe command goes
out. Only then the autopilot, and even then only what the operator engaged: steering
when steering is engaged, throttle and brake when speed is engaged. Everything else is
left at its released value (allow-list).

The function never returns None ("send nothing"), although the type allows it. Sending
nothing relies on the lower layers' own command timeouts, which act later than this
cycle and leave each board in whatever state it held; an explicit released or safe
command acts within one cycle and keeps the boards' command stream alive. None stays in
the return type so that a caller treating it as "send nothing" keeps working if a
future rule (e.g. a bus-off condition) ever finds silence safer.
"""

from __future__ import annotations

from dataclasses import dataclass

from safety.limits import ActuatorCommand

# Everything handed to the operator: no steering, throttle closed, our brake released.
RELEASED = ActuatorCommand(steer_angle_rad=None, throttle_pct=0.0, brake_pct=0.0)


@dataclass(frozen=True)
class OperatorInput:
    """The operator's override state, as decided by the override-detection rule."""

    steering_override: bool = False
    brake_pedal: bool = False
    throttle_pedal: bool = False

    @property
    def overriding(self) -> bool:
        return self.steering_override or self.brake_pedal or self.throttle_pedal


def safe_command(brake_pct: float = 100.0) -> ActuatorCommand:
    """Throttle closed, brake applied, steering released.

    The limiter clamps the brake to the configured maximum; ramping the brake to a
    configured deceleration is the safe-stop sequence's job, not arbitration's.
    """
    return ActuatorCommand(steer_angle_rad=None, throttle_pct=0.0, brake_pct=brake_pct)


def arbitrate(
    operator: OperatorInput,
    safety_revoked: bool,
    autopilot: ActuatorCommand | None,
    engaged_steering: bool,
    engaged_speed: bool,
    *,
    safe_brake_pct: float = 100.0,
) -> ActuatorCommand | None:
    """Decide what may be sent this cycle, channel by channel.

    Steering and speed are arbitrated separately: a foot on the brake in speed hold takes
    the speed channel back at once while steering stays automatic (the cruise-control
    behaviour of Stanley et al.), and hands on the wheel take steering back. When control
    is revoked, an operator override of any kind releases everything, brake included:
    braking against an operator who is steering or accelerating out of trouble would take
    control from them. A missing autopilot command releases too; whether that is a fault
    is the staleness rule's decision, not arbitration's.
    """
    if safety_revoked:
        return RELEASED if operator.overriding else safe_command(safe_brake_pct)
    if autopilot is None:
        return RELEASED
    steering_ours = engaged_steering and not operator.steering_override
    speed_ours = engaged_speed and not (operator.brake_pedal or operator.throttle_pedal)
    return ActuatorCommand(
        steer_angle_rad=autopilot.steer_angle_rad if steering_ours else None,
        throttle_pct=autopilot.throttle_pct if speed_ours else 0.0,
        brake_pct=autopilot.brake_pct if speed_ours else 0.0,
    )
