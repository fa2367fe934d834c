"""Command limits: absolute and rate limits on steering, throttle and brake.

Whatever the autopilot asks, what leaves the process stays inside the vehicle's
configured envelope. The limiter clamps rather than rejects (a slightly too fast steering
request should still steer, just slower) and reports every clamp by name, so the fault
logic above can decide whether repeated clamping is itself a fault. A non-finite number
anywhere is not clamped: it means a broken producer, so the output is the safe command.
Time is an argument (``now_s``, monotonic), so the same rule runs on the vehicle, in
faster-than-real-time tests and in replay.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass


@dataclass(frozen=True)
class ActuatorCommand:
    """One cycle's actuator set-points. ``steer_angle_rad=None`` hands steering back."""

    steer_angle_rad: float | None
    throttle_pct: float
    brake_pct: float


@dataclass(frozen=True)
class LimitParams:
    """The limiter's parameters, in radians and SI, converted once from the vehicle file
    (``appliance.config.parts.limit_params``).

    ``steer_rate_fraction_at_max_speed`` makes the steering rate limit speed dependent:
    the allowed rate falls linearly from the full rate at standstill to this fraction of
    it at ``max_speed_mps`` (and stays there above). Lateral acceleration grows with the
    square of speed for a given curvature, so a steering step that is harmless while
    creeping can unsettle a loaded nine-ton vehicle at speed. The default 1.0 keeps the
    config's rate at every speed: no limit here is tighter than the config says unless
    the caller asks for it.

    ``max_step_dt_s`` caps the time a rate limit may integrate over: a late cycle or a
    gap in updates is not a licence for one large step.
    """

    max_steer_angle_rad: float
    max_steer_rate_rad_per_s: float
    throttle_min_pct: float
    throttle_max_pct: float
    max_throttle_rate_pct_per_s: float
    brake_min_pct: float
    brake_max_pct: float
    max_speed_mps: float
    steer_rate_fraction_at_max_speed: float = 1.0
    max_step_dt_s: float = 0.1

    def __post_init__(self) -> None:
        if not 0.0 < self.steer_rate_fraction_at_max_speed <= 1.0:
            raise ValueError("steer_rate_fraction_at_max_speed must be in (0, 1]")
        if not self.max_step_dt_s > 0.0:
            raise ValueError("max_step_dt_s must be positive")

    def steer_rate_limit_rad_per_s(self, speed_mps: float) -> float:
        """The steering rate allowed at this speed (direction of travel does not matter)."""
        share = min(abs(speed_mps) / self.max_speed_mps, 1.0)
        fraction = 1.0 - (1.0 - self.steer_rate_fraction_at_max_speed) * share
        return self.max_steer_rate_rad_per_s * fraction

    def safe_command(self) -> ActuatorCommand:
        """Throttle closed, brake at its configured maximum, steering released."""
        return ActuatorCommand(steer_angle_rad=None, throttle_pct=0.0, brake_pct=self.brake_max_pct)


def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


class CommandLimiter:
    """Clamps each command to the absolute and rate limits, against its previous output.

    Steering rate reference: when steering (re-)engages (after ``reset()`` or after a
    released/safe output) the first angle is rate-limited from the *measured* angle passed
    to ``update``, not from 0: starting from 0 would command the wheels back to centre
    with a jerk if they stand at 20 degrees. Without a measured angle there is no safe
    reference, so steering stays released (deny by default, violation
    ``steer_no_reference``). The first cycle has no dt, so it allows no change at all:
    the wheels are held where they are, and the next cycles ramp.

    Throttle: increases are rate-limited, decreases pass at once (closing is always
    safe). Anything at or below ``throttle_min_pct`` leaves as 0: below the minimum the
    throttle does not move the vehicle, so closing it costs nothing, and the limiter
    never opens the throttle on its own initiative. The ramp starts from the minimum.
    Brake: clamped to its range, no rate limit (braking must never be slowed down).
    """

    _TOLERANCE = 1e-9

    def __init__(self, params: LimitParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._last_now_s: float | None = None
        self._last_steer_rad: float | None = None
        self._last_throttle_pct = 0.0

    def update(
        self,
        command: ActuatorCommand,
        speed_mps: float,
        now_s: float,
        measured_steer_angle_rad: float | None = None,
    ) -> tuple[ActuatorCommand, tuple[str, ...]]:
        """Return the command to send and the names of the limits it violated."""
        p = self.params
        inputs = [command.throttle_pct, command.brake_pct, speed_mps, now_s]
        for optional in (command.steer_angle_rad, measured_steer_angle_rad):
            if optional is not None:
                inputs.append(optional)
        if not all(math.isfinite(x) for x in inputs):
            self.reset()
            return p.safe_command(), ("input_not_finite",)

        dt_s = (
            0.0
            if self._last_now_s is None
            else _clamp(now_s - self._last_now_s, 0.0, p.max_step_dt_s)
        )
        self._last_now_s = now_s
        violations: list[str] = []

        def note(name: str, requested: float, granted: float) -> None:
            if abs(requested - granted) > self._TOLERANCE:
                violations.append(name)

        steer = self._limit_steering(
            command.steer_angle_rad, measured_steer_angle_rad, speed_mps, dt_s, note
        )
        if command.steer_angle_rad is not None and steer is None:
            violations.append("steer_no_reference")

        throttle = _clamp(command.throttle_pct, 0.0, p.throttle_max_pct)
        note(
            "throttle_below_zero" if command.throttle_pct < 0 else "throttle_above_max",
            command.throttle_pct,
            throttle,
        )
        ramp_from = max(self._last_throttle_pct, p.throttle_min_pct)
        ramped = min(throttle, ramp_from + p.max_throttle_rate_pct_per_s * dt_s)
        note("throttle_rate_above_max", throttle, ramped)
        throttle = 0.0 if ramped <= p.throttle_min_pct else ramped
        self._last_throttle_pct = throttle

        brake = _clamp(command.brake_pct, p.brake_min_pct, p.brake_max_pct)
        note(
            "brake_below_min" if command.brake_pct < p.brake_min_pct else "brake_above_max",
            command.brake_pct,
            brake,
        )
        return ActuatorCommand(steer, throttle, brake), tuple(violations)

    def _limit_steering(
        self,
        requested_rad: float | None,
        measured_rad: float | None,
        speed_mps: float,
        dt_s: float,
        note: Callable[[str, float, float], None],
    ) -> float | None:
        p = self.params
        if requested_rad is None:
            self._last_steer_rad = None
            return None
        reference = self._last_steer_rad if self._last_steer_rad is not None else measured_rad
        if reference is None:
            return None
        reference = _clamp(reference, -p.max_steer_angle_rad, p.max_steer_angle_rad)
        angle = _clamp(requested_rad, -p.max_steer_angle_rad, p.max_steer_angle_rad)
        note("steer_angle_above_max", requested_rad, angle)
        step = p.steer_rate_limit_rad_per_s(speed_mps) * dt_s
        limited = _clamp(angle, reference - step, reference + step)
        note("steer_rate_above_max", angle, limited)
        self._last_steer_rad = limited
        return limited
