"""Operator override: is a hand on the wheel or a foot on a pedal fighting automatic control?

The operator always wins (see ``safety.arbitration``), so this rule decides when the
operator is there. Steering: the measured tyre angle leaves the commanded one by more
than a threshold while the servo pushes hard (it is pushing against something: hands on
the wheel), continuously for a dwell time; the override ends, with hysteresis, only once
the wheel is back near the command. Pedals: a pedal pressed further than our actuator
pulls it is the operator's foot, at once (a foot on the brake must not wait for a dwell).

Everything is pure: no clock, no I/O; time comes in as ``now_s`` (monotonic seconds) and
angles are tyre angles in radians, converted from the vehicle file's degrees once, in
``appliance.config.parts``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from safety.arbitration import OperatorInput


@dataclass(frozen=True)
class SteeringOverrideParams:
    """Steering override thresholds, as tyre angles in radians.

    ``threshold_rad`` starts an override, ``release_rad`` (smaller) ends it. Within
    ``stop_margin_rad`` of either steering stop (``max_steer_angle_rad``) a deviation
    towards that stop does not start one; see :class:`SteeringOverrideDetector`.
    """

    threshold_rad: float
    release_rad: float
    dwell_s: float
    min_torque_nm: float
    stop_margin_rad: float
    max_steer_angle_rad: float

    def __post_init__(self) -> None:
        values = (
            self.threshold_rad,
            self.release_rad,
            self.dwell_s,
            self.min_torque_nm,
            self.stop_margin_rad,
            self.max_steer_angle_rad,
        )
        if not all(math.isfinite(x) for x in values):
            raise ValueError("steering override parameters must be finite")
        if not 0.0 < self.release_rad < self.threshold_rad:
            raise ValueError("release_rad must be positive and below threshold_rad")
        if self.dwell_s < 0.0 or self.min_torque_nm < 0.0 or self.stop_margin_rad < 0.0:
            raise ValueError("dwell_s, min_torque_nm and stop_margin_rad must not be negative")
        if not self.max_steer_angle_rad > 0.0:
            raise ValueError("max_steer_angle_rad must be positive")


class SteeringOverrideDetector:
    """True while the operator has the wheel.

    ``commanded_rad`` is the limited set-point the servo was asked to follow (None:
    steering released). Not the raw request: rate limiting would then count as
    deviation. A released set-point ends an override at once, so the hysteresis below
    only acts for a caller that holds the last set-point while the operator steers; a
    caller that leaves automatic steering on the first override just releases.

    - Released (``commanded_rad`` None): nothing to override, never an override; the
      dwell and the override state reset.
    - Start: ``|measured - commanded| > threshold_rad`` and ``|servo_torque_nm| >=
      min_torque_nm``, continuously for at least ``dwell_s`` (0: in the same update). The
      torque only gates the start: once the operator has the wheel the servo may let go.
    - End (hysteresis): only when ``|measured - commanded| < release_rad``.
    - Steering stops: when the measured angle is within ``stop_margin_rad`` of a stop
      (``|measured| >= max_steer_angle_rad - stop_margin_rad``, on that stop's side, a
      reading past the configured maximum included) and the command lies further out
      towards the same stop, the servo is pushing the wheels against the lock: that
      deviation is the stop, not the operator, and does not start an override. A
      deviation away from the stop, near the stop, still counts. The price is that an
      operator holding the wheel back within the margin band is not seen until the
      command leaves the band or the wheel is pulled inwards past it. With a set-point
      clamped to the maximum, a deviation towards a stop inside the band is at most
      ``stop_margin_rad``, so the exemption only matters where the margin reaches the
      threshold; a physical lock well inside ``max_steer_angle_rad`` is a calibration
      error this rule does not hide.
    - Unseen: a missing measured angle (no valid pot reading) or any non-finite input
      (angle, torque, ``now_s``) means the detector cannot tell. It returns False, never
      an override it cannot see, sets ``unknown`` for that update (the caller treats it
      as a steering fault) and resets, so a dwell only counts what was seen.
      ``unknown`` is set whether or not steering is commanded: a wheel nobody can see
      is a fault in READY as well, and blocks engagement.

    Time going backwards restarts the dwell from the new ``now_s``.
    """

    def __init__(self, params: SteeringOverrideParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self.overriding = False
        self.unknown = False
        self.deviating_since_s: float | None = None

    def _at_stop(self, commanded_rad: float, measured_rad: float) -> bool:
        """The wheels stand at a stop and the command lies further out towards it."""
        p = self.params
        inner_edge_rad = p.max_steer_angle_rad - p.stop_margin_rad
        at_positive_stop = measured_rad > 0.0 and measured_rad >= inner_edge_rad
        at_negative_stop = measured_rad < 0.0 and measured_rad <= -inner_edge_rad
        return (at_positive_stop and commanded_rad > measured_rad) or (
            at_negative_stop and commanded_rad < measured_rad
        )

    def update(
        self,
        commanded_rad: float | None,
        measured_rad: float | None,
        servo_torque_nm: float,
        now_s: float,
    ) -> bool:
        """Return True while the operator has the wheel (see the class docstring)."""
        p = self.params
        given = [servo_torque_nm, now_s]
        for optional in (commanded_rad, measured_rad):
            if optional is not None:
                given.append(optional)
        unseen = measured_rad is None or not all(math.isfinite(x) for x in given)
        if unseen or commanded_rad is None or measured_rad is None:
            self.reset()
            self.unknown = unseen
            return False
        self.unknown = False

        deviation_rad = abs(measured_rad - commanded_rad)
        if self.overriding:
            self.overriding = deviation_rad >= p.release_rad
            return self.overriding

        pushing = (
            deviation_rad > p.threshold_rad
            and abs(servo_torque_nm) >= p.min_torque_nm
            and not self._at_stop(commanded_rad, measured_rad)
        )
        if not pushing:
            self.deviating_since_s = None
            return False
        if self.deviating_since_s is None or now_s < self.deviating_since_s:
            self.deviating_since_s = now_s
        if now_s - self.deviating_since_s >= p.dwell_s:
            self.overriding = True
            self.deviating_since_s = None
        return self.overriding


@dataclass(frozen=True)
class PedalOverrideParams:
    """A pedal more than ``margin_pct`` above our actuator's position is the operator's."""

    margin_pct: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.margin_pct) and self.margin_pct > 0.0):
            raise ValueError("margin_pct must be positive and finite")


class PedalOverrideDetector:
    """True while the operator's foot is on the pedal (throttle or brake).

    One cycle, no dwell: a foot on the brake wins at once. ``pedal_pct`` None means the
    board has no pedal sensor: there is nothing to detect, False. A non-finite pedal or
    actuator position cannot be compared: the detector assumes the operator (True),
    which releases automatic control (deny by default). Exactly at the margin is not
    yet an override ("more than").
    """

    def __init__(self, params: PedalOverrideParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self.overriding = False

    def update(self, pedal_pct: float | None, actuator_pct: float) -> bool:
        """Return True when the pedal is pressed beyond what our actuator pulls."""
        if not math.isfinite(actuator_pct) or not (pedal_pct is None or math.isfinite(pedal_pct)):
            self.overriding = True
        elif pedal_pct is None:
            self.overriding = False
        else:
            self.overriding = pedal_pct > actuator_pct + self.params.margin_pct
        return self.overriding


class OperatorOverride:
    """One steering and two pedal detectors, combined into :class:`OperatorInput`.

    ``steering_unknown`` forwards the steering detector's ``unknown``: the caller must
    treat it as a fault, since an unseen wheel is reported as no override.
    """

    def __init__(self, steering: SteeringOverrideParams, pedal: PedalOverrideParams) -> None:
        self.steering = SteeringOverrideDetector(steering)
        self.brake = PedalOverrideDetector(pedal)
        self.throttle = PedalOverrideDetector(pedal)

    @property
    def steering_unknown(self) -> bool:
        return self.steering.unknown

    def reset(self) -> None:
        self.steering.reset()
        self.brake.reset()
        self.throttle.reset()

    def update(
        self,
        *,
        commanded_steer_rad: float | None,
        measured_steer_rad: float | None,
        servo_torque_nm: float,
        brake_pedal_pct: float | None,
        brake_actuator_pct: float,
        throttle_pedal_pct: float | None,
        throttle_actuator_pct: float,
        now_s: float,
    ) -> OperatorInput:
        """Run every detector once and return this cycle's operator input."""
        return OperatorInput(
            steering_override=self.steering.update(
                commanded_steer_rad, measured_steer_rad, servo_torque_nm, now_s
            ),
            brake_pedal=self.brake.update(brake_pedal_pct, brake_actuator_pct),
            throttle_pedal=self.throttle.update(throttle_pedal_pct, throttle_actuator_pct),
        )
