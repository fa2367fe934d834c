"""Speed by throttle and brake: the Husky's speed path (it has no PC104 to hand speed to).

Stanley et al. used the Husky's engine throttle as the primary speed control in autopilot,
with the brake for slowing and stopping. This controller turns a target speed into the two
pedal positions, and is built around what a nine-ton truck on cable-pulled pedals needs:

* **One effort, two pedals.** Feed-forward and feedback are summed as an acceleration
  ``u`` (m/s²): the reference's own acceleration, plus the drag at the reference speed
  (so holding speed needs no integral), plus PI on the speed error. ``u`` above a small
  threshold opens the throttle, well below zero applies the brake; in between the vehicle
  coasts on its drag. Switching has hysteresis, and a pedal only moves once the other is
  fully released, so the two are never pressed together and small errors do not chatter
  between them. Working in m/s² keeps the gains physical: kp is 1/s, ki is 1/s².
* **A reference, not a step.** The target is followed by an internal reference speed:
  at the target's own rate when it moves (a ramping target is followed without lag),
  closing any gap exponentially, its acceleration jerk limited, rising no faster than the
  engine can deliver at that speed (with headroom for the feedback) and falling at a
  comfortable deceleration. Its acceleration is the feed-forward, so it fades out near
  the target instead of dropping to zero. The reference never runs more than
  ``ref_lead_max_mps`` ahead of the vehicle: a target the vehicle cannot reach does not
  pile up as a reference the vehicle is late for.
* **Anti-windup.** The integral only runs while the throttle is in charge and free to
  move in the direction the error asks: not while the throttle is held back (by its limit,
  its rate limit, or the brake still releasing), not while the brake is applied, and not
  at standstill. It is cleared whenever the vehicle is held or stopped, so a minute at
  rest cannot be stored up and released as a lurch.
* **Jerk limits.** Each pedal's rate of change is bounded, separately for throttle and
  brake and for pressing and releasing. The one exception is safety: with
  ``stop_requested`` the throttle closes at once (closing is always safe; the safety
  limiter passes throttle decreases unlimited too) and the brake rises at the separate,
  much faster ``stop_brake_rise_pct_per_s`` to ``stop_brake_pct``. A non-finite input, or
  a speed beyond 100 m/s, is treated the same way (state ``FAULT``).
* **Smooth stop and hold.** A target of (about) zero makes the reference fall at the
  comfortable deceleration, softening towards the end (deceleration proportional to the
  remaining speed, floored so the stop ends in finite time) to avoid the final pitch.
  At standstill the brake goes to ``hold_brake_pct`` and stays: a parked nine-ton truck
  must not creep. Leaving the hold releases the brake first, then the throttle rises.

Default parameters are for the Husky (nine tons, up to 4.47 m/s = 10 mph) against the
simulated plant (``appliance.sim.vehicle``: 1.0 m/s² at full throttle, 3.0 m/s² at full
brake, drag 0.05 /s, 0.4 s traction lag). On the vehicle the plant is measured: `dbw
calibrate pedals` sweeps the pedals into maps of acceleration per pedal and speed, and the
controller then turns its effort into pedal positions through them
(:class:`~appliance.guidance.pedal_plant.MapPlant`); the three linear numbers remain its
model where the maps end, and its whole model without them.

* Gains: with the 0.4 s traction lag, a P loop on speed has the characteristic equation
  ``0.4 s² + s + kp = 0``; kp = 0.5 /s gives damping ζ ≈ 1.1 (no ringing), ki = 0.05 /s²
  an integral time of 10 s, slow enough to stay out of the lag's way and only there to
  trim model error (feed-forward holds the speed on the flat).
* Pedal rates: throttle 25 %/s ≈ 0.25 m/s³ (the safety limiter's default allows 50 %/s),
  brake 15 %/s ≈ 0.45 m/s³: below the ≈ 0.5-0.9 m/s³ comfort limit used for buses, as a
  tall vehicle carrying an array should be driven gently. Releasing may be faster.
* Reference: 0.35 m/s² up (the engine gives at most 0.45 m/s² at the 45 % throttle
  limit), 0.8 m/s² down (a comfortable service brake), 1.5 s exponential approach, jerk
  0.4 m/s³ (what the pedal rates can follow, so the tracking error stays small).
* Deadband: throttle above 0.03 m/s², brake below -0.15 m/s² (off again above -0.05):
  at 10 mph drag alone decelerates 0.22 m/s², so slowing a little is left to drag.
* Stop: 0.8 m/s² then softening below 0.8 m/s, at least 0.3 m/s²; hold with 40 % brake
  (1.2 m/s² of braking capacity: holds the truck on about a 12 % grade); a stop request
  brakes to 70 % (2.1 m/s²) at 200 %/s (0.35 s to full stop braking, as fast as a foot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from enum import StrEnum
from typing import Protocol

from appliance.guidance.pedal_plant import LinearPlant, PedalPlant

# A speed beyond this comes from a broken producer, not from a truck: treated as non-finite.
_PLAUSIBLE_MPS = 100.0
# Parameters that may be zero (to switch a term off); every other one must be positive.
_MAY_BE_ZERO = {"drag_per_s", "kp_per_s", "ki_per_s2", "integral_limit_mps2"}
_MAY_BE_ZERO |= {"accel_feedback_gain", "throttle_on_mps2", "brake_off_mps2"}


class PedalState(StrEnum):
    DRIVE = "drive"  # throttle in charge
    COAST = "coast"  # neither pedal: inside the deadband, drag does the work
    BRAKE = "brake"  # brake in charge (slowing, stopping, or moving the wrong way)
    HOLD = "hold"  # at standstill with the brake held
    RELEASE = "release"  # leaving the hold: the brake comes off before any throttle
    STOP_REQUEST = "stop_request"  # safety stop: throttle closed, brake applied fast
    FAULT = "fault"  # a non-finite or implausible input: braked as for a stop request


@dataclass(frozen=True)
class PedalCommand:
    throttle_pct: float
    brake_pct: float
    state: PedalState
    reason: str
    reference_speed_mps: float  # the shaped speed being tracked (for status and logs)


class _PedalLimits(Protocol):
    """The part of the vehicle's ``Limits`` this controller needs (guidance may not
    import the config package, which sits above it)."""

    @property
    def throttle_max_pct(self) -> float: ...
    @property
    def brake_max_pct(self) -> float: ...
    @property
    def max_throttle_rate_pct_per_s(self) -> float: ...


@dataclass(frozen=True)
class PedalSpeedParams:
    # Plant model for the feed-forward (the simulated plant; measure on the vehicle).
    accel_per_throttle_pct_mps2: float = 0.01
    decel_per_brake_pct_mps2: float = 0.03
    drag_per_s: float = 0.05
    # PI on speed error, output in m/s²; optional damping on measured acceleration.
    kp_per_s: float = 0.5
    ki_per_s2: float = 0.05
    integral_limit_mps2: float = 0.2
    accel_feedback_gain: float = 0.0  # times (reference accel - measured accel)
    # Reference shaping.
    ref_accel_mps2: float = 0.35
    ref_decel_mps2: float = 0.8
    ref_time_constant_s: float = 1.5
    ref_jerk_mps3: float = 0.4
    ref_accel_headroom: float = 0.8  # share of the engine's spare acceleration planned on
    ref_lead_max_mps: float = 0.5
    # The pedal split, in m/s² of effort.
    throttle_on_mps2: float = 0.03
    brake_on_mps2: float = 0.15
    brake_off_mps2: float = 0.05
    # Pedal ranges and rates (jerk limits).
    throttle_max_pct: float = 45.0
    brake_max_pct: float = 100.0
    throttle_rise_pct_per_s: float = 25.0
    throttle_fall_pct_per_s: float = 50.0
    brake_rise_pct_per_s: float = 15.0
    brake_fall_pct_per_s: float = 25.0
    hold_release_pct_per_s: float = 80.0  # at standstill releasing moves nothing
    # Stopping, holding and the safety stop.
    standstill_mps: float = 0.05
    stop_final_decel_mps2: float = 0.3
    stop_soft_time_s: float = 1.0
    hold_brake_pct: float = 40.0
    stop_brake_pct: float = 70.0
    stop_brake_rise_pct_per_s: float = 200.0
    max_step_dt_s: float = 0.1

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            low_ok = value >= 0.0 if f.name in _MAY_BE_ZERO else value > 0.0
            if not (math.isfinite(value) and low_ok):
                raise ValueError(f"{f.name} must be finite and positive (got {value})")
        if self.throttle_max_pct > 100.0 or self.brake_max_pct > 100.0:
            raise ValueError("throttle_max_pct and brake_max_pct must be at most 100")
        if not self.hold_brake_pct <= self.stop_brake_pct <= self.brake_max_pct:
            raise ValueError("need hold_brake_pct <= stop_brake_pct <= brake_max_pct")
        if not self.brake_off_mps2 < self.brake_on_mps2:
            raise ValueError("brake_off_mps2 must be below brake_on_mps2 (hysteresis)")

    @classmethod
    def from_limits(
        cls, limits: _PedalLimits, base: PedalSpeedParams | None = None
    ) -> PedalSpeedParams:
        """These parameters inside the vehicle's configured limits, so the safety layer's
        limiter (which enforces the same numbers) never has to clamp what we send."""
        b = base if base is not None else cls()
        brake_max = min(b.brake_max_pct, limits.brake_max_pct)
        return replace(
            b,
            throttle_max_pct=min(b.throttle_max_pct, limits.throttle_max_pct),
            throttle_rise_pct_per_s=min(
                b.throttle_rise_pct_per_s, limits.max_throttle_rate_pct_per_s
            ),
            brake_max_pct=brake_max,
            stop_brake_pct=min(b.stop_brake_pct, brake_max),
            hold_brake_pct=min(b.hold_brake_pct, brake_max),
        )


def _toward(value: float, target: float, rise: float, fall: float, dt_s: float) -> float:
    """``value`` moved toward ``target`` by at most ``rise*dt`` up or ``fall*dt`` down."""
    step = max(-fall * dt_s, min(rise * dt_s, target - value))
    moved = value + step
    return 0.0 if abs(moved) < 1e-9 else moved


class PedalSpeedController:
    """Target speed in, throttle and brake out. Pure apart from its own state."""

    def __init__(
        self, params: PedalSpeedParams | None = None, plant: PedalPlant | None = None
    ) -> None:
        self.params = params if params is not None else PedalSpeedParams()
        p = self.params
        # The pedal sweep's maps where the calibration has them, else the linear model.
        self.plant: PedalPlant = (
            plant
            if plant is not None
            else LinearPlant(
                p.accel_per_throttle_pct_mps2, p.decel_per_brake_pct_mps2, p.drag_per_s
            )
        )
        self.reset()

    def reset(self, throttle_pct: float = 0.0, brake_pct: float = 0.0) -> None:
        """Forget everything. The pedals' current positions may be given so the first
        commands continue from them (the operator's foot at engagement) rather than jump."""
        p = self.params
        self._throttle_pct = min(max(throttle_pct, 0.0), p.throttle_max_pct)
        self._brake_pct = min(max(brake_pct, 0.0), p.brake_max_pct)
        if self._brake_pct > 0.0:
            self._throttle_pct = 0.0
        self._last_now_s: float | None = None
        self._integral_mps2 = 0.0
        self._reference_mps: float | None = None
        self._ref_accel_mps2 = 0.0
        self._last_target_mps: float | None = None
        self._state = PedalState.COAST

    @property
    def integral_mps2(self) -> float:
        return self._integral_mps2

    def update(
        self,
        target_speed_mps: float,
        measured_speed_mps: float,
        accel_mps2: float | None,
        now_s: float,
        *,
        stop_requested: bool = False,
    ) -> PedalCommand:
        """One control cycle. ``accel_mps2`` is the measured longitudinal acceleration
        (None if there is none); ``stop_requested`` is the safety stop (see the module)."""
        p = self.params
        inputs = [target_speed_mps, measured_speed_mps, now_s]
        if accel_mps2 is not None:
            inputs.append(accel_mps2)
        if not all(math.isfinite(x) for x in inputs) or not all(
            abs(x) <= _PLAUSIBLE_MPS for x in inputs[:2]
        ):
            # Time and speed cannot be trusted: brake as if moving and a full cycle had passed.
            return self._safety_stop(p.max_step_dt_s, math.inf, PedalState.FAULT, "bad input")
        dt_s = self._dt(now_s)
        speed = measured_speed_mps
        stopped = abs(speed) < p.standstill_mps
        if stop_requested:
            return self._safety_stop(dt_s, speed, PedalState.STOP_REQUEST, "stop requested")
        if speed <= -p.standstill_mps:
            # Rolling backwards is never what a forward autopilot asks for: stop it.
            return self._hold(dt_s, PedalState.BRAKE, "rolling backwards")
        target = max(target_speed_mps, 0.0)
        wants_stop = target < p.standstill_mps
        reference = self._reference_mps
        if wants_stop and stopped and (reference is None or reference < p.standstill_mps):
            return self._hold(dt_s, PedalState.HOLD, "holding at standstill")
        if wants_stop and reference is not None and reference <= 0.0:
            # The reference has stopped and the vehicle nearly: finish on the holding brake.
            return self._hold(dt_s, PedalState.BRAKE, "stopping")
        held = self._state in (PedalState.HOLD, PedalState.RELEASE)
        if held and stopped and self._brake_pct > 0.0:
            if wants_stop:  # the stop is not finished: back to holding while still
                return self._hold(dt_s, PedalState.HOLD, "holding at standstill")
            self._state = PedalState.RELEASE
            return self._release(dt_s, speed)
        return self._track(dt_s, target, speed, accel_mps2, wants_stop, stopped)

    # -- the cases ---------------------------------------------------------------------

    def _track(
        self,
        dt_s: float,
        target: float,
        speed: float,
        accel_mps2: float | None,
        wants_stop: bool,
        stopped: bool,
    ) -> PedalCommand:
        p = self.params
        reference, ref_accel = self._shape_reference(dt_s, target, speed, wants_stop)
        error = reference - speed
        plant = self.plant
        coast = plant.coast_accel_mps2(reference)
        effort = ref_accel - coast + p.kp_per_s * error + self._integral_mps2
        if accel_mps2 is not None:
            effort += p.accel_feedback_gain * (ref_accel - accel_mps2)

        if wants_stop:
            effort = min(effort, 0.0)  # a stop never opens the throttle
        state = self._split(effort)
        throttle_wish = plant.throttle_pct(effort, reference) if state is PedalState.DRIVE else 0.0
        brake_wish = plant.brake_pct(effort, reference) if state is PedalState.BRAKE else 0.0
        throttle_wish = min(max(throttle_wish, 0.0), p.throttle_max_pct)
        brake_wish = min(max(brake_wish, 0.0), p.brake_max_pct)
        if self._throttle_pct > 0.0:
            brake_wish = 0.0  # the throttle closes before the brake moves
        brake = _toward(
            self._brake_pct, brake_wish, p.brake_rise_pct_per_s, p.brake_fall_pct_per_s, dt_s
        )
        if brake > 0.0:
            throttle_wish = 0.0  # and the brake releases before the throttle opens
        throttle = _toward(
            self._throttle_pct,
            throttle_wish,
            p.throttle_rise_pct_per_s,
            p.throttle_fall_pct_per_s,
            dt_s,
        )

        # Anti-windup: integrate only while the throttle is in charge and can follow.
        wanted_throttle = plant.throttle_pct(effort, reference)
        held_back = error > 0.0 and throttle < wanted_throttle - 1e-6
        held_up = error < 0.0 and throttle > max(wanted_throttle, 0.0) + 1e-6
        closed = error < 0.0 and throttle <= 0.0
        if wants_stop:
            reason = "stopping"
        elif state is PedalState.BRAKE or brake > 0.0:
            reason = "braking"
        elif stopped:
            reason = "starting"
        elif held_back:
            reason = "throttle at limit" if throttle >= p.throttle_max_pct else "throttle ramping"
        elif closed or held_up:
            reason = "coasting" if closed else "throttle closing"
        else:
            reason = "tracking"
            self._integral_mps2 += p.ki_per_s2 * error * dt_s
            limit = p.integral_limit_mps2
            self._integral_mps2 = min(max(self._integral_mps2, -limit), limit)
        if stopped or wants_stop:
            self._integral_mps2 = 0.0
        self._state = state
        return self._emit(throttle, brake, state, reason)

    def _shape_reference(
        self, dt_s: float, target: float, speed: float, wants_stop: bool
    ) -> tuple[float, float]:
        """Advance the reference speed; return it and its acceleration."""
        p = self.params
        reference = self._reference_mps if self._reference_mps is not None else max(speed, 0.0)
        if wants_stop:
            soft_mps2 = reference / p.stop_soft_time_s
            wish = -max(p.stop_final_decel_mps2, min(p.ref_decel_mps2, soft_mps2))
        else:
            spare_mps2 = self.plant.accel_at_throttle_mps2(p.throttle_max_pct, reference)
            accel_cap = max(min(p.ref_accel_mps2, p.ref_accel_headroom * spare_mps2), 0.0)
            # Follow a moving target without lag (its rate), close the gap exponentially.
            last = self._last_target_mps
            rate_mps2 = 0.0 if last is None or dt_s <= 0.0 else (target - last) / dt_s
            rate_mps2 = min(max(rate_mps2, -p.ref_decel_mps2), p.ref_accel_mps2)
            gap_mps2 = (target - reference) / p.ref_time_constant_s
            wish = min(max(rate_mps2 + gap_mps2, -p.ref_decel_mps2), accel_cap)
        jerk = p.ref_jerk_mps3
        ref_accel = _toward(self._ref_accel_mps2, wish, jerk, jerk, dt_s)
        before_mps = reference - target
        reference += ref_accel * dt_s
        if wants_stop and reference <= 0.0:
            reference, ref_accel = 0.0, 0.0
        elif not wants_stop and before_mps * (reference - target) <= 0.0:
            # Reached the target (only the jerk limit's lag can carry it past): stay on it.
            reference, ref_accel = target, 0.0
        # Never far ahead of a vehicle that cannot follow (the reference's own windup).
        reference = min(reference, max(speed, 0.0) + p.ref_lead_max_mps)
        self._ref_accel_mps2 = ref_accel
        self._reference_mps = reference
        self._last_target_mps = target
        return reference, ref_accel

    def _split(self, effort: float) -> PedalState:
        """Which pedal, with hysteresis between them and a coasting band in the middle."""
        p = self.params
        previous = self._state
        if previous is PedalState.BRAKE and effort < -p.brake_off_mps2:
            return PedalState.BRAKE
        if previous is PedalState.DRIVE and effort > 0.0:
            return PedalState.DRIVE
        if effort > p.throttle_on_mps2:
            return PedalState.DRIVE
        if effort < -p.brake_on_mps2:
            return PedalState.BRAKE
        return PedalState.COAST

    def _hold(self, dt_s: float, state: PedalState, reason: str) -> PedalCommand:
        """Throttle closed, brake to at least the holding value at the normal rate."""
        p = self.params
        throttle = _toward(self._throttle_pct, 0.0, 0.0, p.throttle_fall_pct_per_s, dt_s)
        brake = self._brake_pct
        if throttle <= 0.0:
            brake = _toward(brake, max(brake, p.hold_brake_pct), p.brake_rise_pct_per_s, 0.0, dt_s)
        self._integral_mps2 = 0.0
        self._reference_mps, self._ref_accel_mps2 = 0.0, 0.0
        self._state = state
        return self._emit(throttle, brake, state, reason)

    def _release(self, dt_s: float, speed: float) -> PedalCommand:
        p = self.params
        brake = _toward(self._brake_pct, 0.0, 0.0, p.hold_release_pct_per_s, dt_s)
        self._integral_mps2 = 0.0
        self._reference_mps, self._ref_accel_mps2 = max(speed, 0.0), 0.0
        return self._emit(0.0, brake, PedalState.RELEASE, "releasing the holding brake")

    def _safety_stop(
        self, dt_s: float, speed: float, state: PedalState, reason: str
    ) -> PedalCommand:
        """Throttle closed at once, brake up fast to the stop value (or the holding value
        if already still): the one case the normal brake rate does not apply."""
        p = self.params
        goal = p.hold_brake_pct if abs(speed) < p.standstill_mps else p.stop_brake_pct
        brake = _toward(
            self._brake_pct, max(self._brake_pct, goal), p.stop_brake_rise_pct_per_s, 0.0, dt_s
        )
        self._integral_mps2 = 0.0
        # After the stop, start again from the measured speed.
        self._reference_mps, self._ref_accel_mps2 = None, 0.0
        still = abs(speed) < p.standstill_mps and state is PedalState.STOP_REQUEST
        self._state = PedalState.HOLD if still else PedalState.BRAKE
        return self._emit(0.0, brake, state, reason)

    # -- plumbing ----------------------------------------------------------------------

    def _dt(self, now_s: float) -> float:
        last, self._last_now_s = self._last_now_s, now_s
        if last is None:
            return 0.0
        return min(max(now_s - last, 0.0), self.params.max_step_dt_s)

    def _emit(self, throttle: float, brake: float, state: PedalState, reason: str) -> PedalCommand:
        p = self.params
        self._throttle_pct = min(max(throttle, 0.0), p.throttle_max_pct)
        self._brake_pct = min(max(brake, 0.0), p.brake_max_pct)
        reference = self._reference_mps if self._reference_mps is not None else 0.0
        return PedalCommand(self._throttle_pct, self._brake_pct, state, reason, reference)
