"""Qian et al.'s docking (4.2): from about 10 m out, into the launcher's troughs within 1 cm.

The paper's steps, as motion patterns of the flat-bed's PC104:
(a) rear-wheel steering to bring the heading to zero (it barely moves the front end);
(b) oblique (crab) movement until the front end's centre is on the launcher's axis;
(c) closing in straight, with oblique or rear steering when needed;
(d) stop when the longitudinal gap reaches zero.

And what the paper says fell short, done better here: it saw the estimate jump and the
patterns switch back and forth, and had to widen its thresholds. So every threshold has
an entry and a smaller exit value (hysteresis), every pattern a minimum dwell time, the
thresholds narrow with the gap (loose 10 m out, tight at the troughs), and switches are
counted. A correction's wheels turn back in time (the braking-distance rule of
`_settling_angle`) and it ends only with them straight, so it does not overshoot into
the next one; and the lateral corrections null where the front end will meet the board,
not where it is, so a heading left inside its band does not drift it off on the way in.
Before the teeth reach the troughs there is a gate: the vehicle goes on only
aligned, otherwise it backs off and approaches again, so it never touches the launcher
misaligned. And speed falls with the gap and with the estimate's uncertainty.

Pure: ``update(centre_pose, covariance, now_s)`` returns a ``DockingCommand`` (pattern,
signed speed, crab or rear angle): a wish, which the mode machine and the safety layer
may refuse, and which the PC104's own pattern controllers carry out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from drivers.geometry import Pose2D
from drivers.pc104.messages import MotionPattern

FloatArray = NDArray[np.float64]


class DockingPhase(StrEnum):
    HEADING = "heading"  # (a)
    LATERAL = "lateral"  # (b)
    APPROACH = "approach"  # (c)
    BACK_OFF = "back_off"  # misaligned at the gate: reverse, then (c) again
    DOCKED = "docked"  # (d)


@dataclass(frozen=True)
class DockingParams:
    # Geometry, in the vehicle frame (origin at the geometric centre O_m).
    front_end_forward_m: float = 6.0
    teeth_lateral_m: float = 1.0  # the two teeth at ±this on the front end
    tooth_insertion_m: float = 0.15  # how deep a tooth goes into its trough
    trough_clearance_m: float = 0.01  # a trough is 2 cm wider than its tooth: ±1 cm
    standoff_m: float = 0.0  # the gap is zero when the front end is this far from the board
    # Speed: proportional to the gap, between these limits.
    max_speed_mps: float = 0.3
    min_speed_mps: float = 0.02
    speed_per_gap_per_s: float = 0.08
    # Thresholds: far (at ``far_gap_m`` and beyond) and near (at the gate), interpolated
    # in between. A correction is entered at that value and left only at
    # ``exit_fraction`` of the NEAR value: corrected once, all the way, rather than to a
    # fraction of a threshold that then narrows under it (a staircase of switches).
    far_gap_m: float = 8.0
    heading_far_rad: float = math.radians(1.0)
    # Near: what the teeth can take with the troughs' ±1 cm, less the estimate's error.
    # A residual heading of 0.1° drifts the front end 1.7 mm per metre driven straight,
    # and a lateral error left at the exit of a correction stays to the troughs: tighter
    # than this (measured: 0.15° and 5 mm left p95 5.9 mm at the teeth) costs switches.
    heading_near_rad: float = math.radians(0.1)
    lateral_far_m: float = 0.08
    lateral_near_m: float = 0.003
    exit_fraction: float = 0.4
    min_dwell_s: float = 2.0
    # A correction starts only when its error has stood for this long: one jumpy
    # estimate near the launcher must not cost two switches.
    enter_persist_s: float = 0.5
    # Gains: yaw rate per radian of heading error; lateral speed per metre by which the
    # front end would meet the board off the axis. The settling limit (below) lets them
    # be this high: measured with an exact pose, 0.4 for both took (a) 15 s from 4.8°
    # and (b) ended 0.8 m before the board from 0.9 m off.
    heading_gain_per_s: float = 1.0
    lateral_gain_per_s: float = 0.8
    max_rear_steer_rad: float = math.radians(20.0)
    max_crab_rad: float = math.radians(15.0)
    # How fast a crab or rear angle may change: a heavy vehicle's wheels turn slowly, and
    # a steering servo asked for more than it can follow reports a position error.
    max_steer_rate_rad_per_s: float = math.radians(3.0)
    # How far the wheels lag their command (the steering servo's time constant): while
    # they straighten, the error goes on changing for this long as well.
    steer_lag_s: float = 0.2
    # A correction ends only with its wheels back within this of straight (the crab
    # angle, the rear wheels' angle): from here straightening moves the heading by
    # under 0.02° and the front end by under 1 mm at docking speeds.
    settled_steer_rad: float = math.radians(0.5)
    # The straightening planned at this fraction of the rate limit: the margin for the
    # wheels' lag, a changing speed and a noisy error.
    settle_rate_fraction: float = 0.7
    wheelbase_m: float = 6.0
    # The gate, before the teeth reach the troughs: go on only aligned this well, with
    # an estimate this certain; otherwise back off by ``back_off_m`` and try again.
    gate_gap_m: float = 0.3
    gate_lateral_m: float = 0.007
    gate_heading_rad: float = math.radians(0.2)
    gate_sigma_m: float = 0.006
    # ... for this long: one jumpy estimate is not a reason to back off.
    gate_persist_s: float = 0.5
    back_off_m: float = 1.0
    max_attempts: int = 3


@dataclass(frozen=True)
class DockingCommand:
    phase: DockingPhase
    pattern: MotionPattern
    speed_mps: float  # signed: negative backs off
    front_steer_rad: float = 0.0  # the crab angle in OBLIQUE
    rear_steer_rad: float = 0.0  # REAR_STEER: physical angle, positive = left
    gap_m: float = math.nan
    lateral_m: float = math.nan  # the front end's centre off the axis (+ left)
    heading_rad: float = math.nan
    teeth_lateral_m: tuple[float, float] = (math.nan, math.nan)
    refused: str = ""  # non-empty: the docking cannot go on (given up after attempts)


def docking_errors(
    centre: Pose2D, params: DockingParams
) -> tuple[float, float, float, tuple[float, float]]:
    """Gap, front-end lateral offset, heading, and each tooth's lateral offset from its
    trough's centre line, all in the launcher frame."""
    front = centre.compose(Pose2D(params.front_end_forward_m, 0.0, 0.0))
    gap = -params.standoff_m - front.x_m
    teeth = tuple(
        centre.apply(params.front_end_forward_m, side * params.teeth_lateral_m)[1]
        - side * params.teeth_lateral_m
        for side in (1.0, -1.0)
    )
    return gap, front.y_m, math.remainder(centre.yaw_rad, math.tau), (teeth[0], teeth[1])


def teeth_inside(centre: Pose2D, params: DockingParams) -> bool:
    """Both teeth inside their troughs over their whole length: the teeth stick out
    ``tooth_insertion_m`` ahead of the front end, so tip and root are checked."""
    for depth in (params.tooth_insertion_m, 0.0):
        shifted = centre.compose(Pose2D(depth, 0.0, 0.0))
        _, _, _, teeth = docking_errors(shifted, params)
        if max(abs(t) for t in teeth) > params.trough_clearance_m:
            return False
    return True


def lateral_sigma_m(centre: Pose2D, covariance: FloatArray | None, forward_m: float) -> float:
    """σ of the front end's lateral position: what decides whether the teeth go in
    (the longitudinal σ only moves the stop by as much)."""
    if covariance is None:
        return math.inf
    # jᵀ C j with j = (0, 1, k), in floats (numpy's products of 3-vectors cost more).
    k = forward_m * math.cos(centre.yaw_rad)
    (_, c11, c12), (_, c21, c22) = np.asarray(covariance)[1:3].tolist()
    return math.sqrt(max((c11 + k * c21) + (c12 + k * c22) * k, 0.0))


class DockingController:
    def __init__(self, params: DockingParams | None = None) -> None:
        self.params = params or DockingParams()
        self.reset()

    def reset(self) -> None:
        self.phase = DockingPhase.HEADING
        self.pattern = MotionPattern.STOP
        self._since_s: float | None = None
        self.switches = 0
        self.attempts = 1
        self._back_off_until_gap_m = 0.0
        self._misaligned_since_s: float | None = None
        self._since_bad: dict[str, float] = {}
        self._front_rad = 0.0
        self._rear_rad = 0.0
        self._steer_s: float | None = None

    def _threshold(self, gap_m: float, far: float, near: float) -> float:
        p = self.params
        span = max(p.far_gap_m - p.gate_gap_m, 1e-6)
        w = min(1.0, max(0.0, (gap_m - p.gate_gap_m) / span))
        return near + w * (far - near)

    def _steer(self, front_rad: float, rear_rad: float, now_s: float) -> tuple[float, float]:
        """The angles moved toward the wanted ones no faster than the rate limit."""
        dt_s = 0.0 if self._steer_s is None else max(0.0, now_s - self._steer_s)
        self._steer_s = now_s
        step = self.params.max_steer_rate_rad_per_s * dt_s
        self._front_rad += max(-step, min(step, front_rad - self._front_rad))
        self._rear_rad += max(-step, min(step, rear_rad - self._rear_rad))
        return self._front_rad, self._rear_rad

    def _settling_angle(self, error: float, scale_m: float, speed_mps: float) -> float:
        """The largest wheel angle from which the wheels can be straightened, at the rate
        limit and with their lag, before a correction overshoots an ``error`` that
        changes at ``speed × angle / scale_m`` (heading: ``scale_m`` the wheelbase;
        lateral: 1).

        A proportional law alone leaves the wheels deflected when the error reaches
        zero (they turn back at only a few degrees a second), and the error goes on:
        measured, a 4.7° heading corrected that way ended 0.27° the other side, which
        the approach then had to correct again near the launcher with two more
        switches. Straightening from ``δ`` at rate ``ρ`` after a lag ``τ`` moves the
        error by ``(v / scale)(δ² / 2ρ + τ δ)``; this is the ``δ`` where that equals
        the error (the braking-distance rule).
        """
        rate = self.params.max_steer_rate_rad_per_s * self.params.settle_rate_fraction
        lag = self.params.steer_lag_s
        reach = 2.0 * abs(error) * scale_m / (max(speed_mps, 1e-3) * rate)
        return rate * (math.sqrt(lag * lag + reach) - lag)

    def _persists(self, what: str, condition: bool, now_s: float) -> bool:
        """``condition`` has held without a break for ``enter_persist_s``."""
        if not condition:
            self._since_bad.pop(what, None)
            return False
        since = self._since_bad.setdefault(what, now_s)
        return now_s - since >= self.params.enter_persist_s

    def _switch(self, pattern: MotionPattern, now_s: float) -> MotionPattern:
        """The pattern to use: a change only after the current one's dwell time."""
        if pattern is self.pattern:
            return pattern
        if self._since_s is not None and now_s - self._since_s < self.params.min_dwell_s:
            return self.pattern
        if self.pattern is not MotionPattern.STOP:
            self.switches += 1
        self.pattern = pattern
        self._since_s = now_s
        return pattern

    def update(self, centre: Pose2D, covariance: FloatArray | None, now_s: float) -> DockingCommand:
        p = self.params
        gap, lateral, heading, teeth = docking_errors(centre, p)
        sigma_m = lateral_sigma_m(centre, covariance, p.front_end_forward_m)

        def command(
            pattern: MotionPattern, speed: float, front: float = 0.0, rear: float = 0.0
        ) -> DockingCommand:
            return DockingCommand(
                self.phase, pattern, speed, front, rear, gap, lateral, heading, teeth
            )

        if self.phase is DockingPhase.DOCKED or gap <= 0.0:
            self.phase = DockingPhase.DOCKED
            self.pattern = MotionPattern.STOP
            return command(MotionPattern.STOP, 0.0)

        if self.phase is DockingPhase.BACK_OFF:
            if gap < self._back_off_until_gap_m:
                self._switch(MotionPattern.STRAIGHT, now_s)
                return command(
                    self.pattern,
                    -p.max_speed_mps / 2 if self.pattern is MotionPattern.STRAIGHT else 0.0,
                )
            self.phase = DockingPhase.APPROACH

        speed = min(p.max_speed_mps, max(p.min_speed_mps, p.speed_per_gap_per_s * gap))
        heading_enter = self._threshold(gap, p.heading_far_rad, p.heading_near_rad)
        lateral_enter = self._threshold(gap, p.lateral_far_m, p.lateral_near_m)

        # The gate: the teeth are about to meet the troughs.
        if gap <= p.gate_gap_m:
            aligned = (
                max(abs(t) for t in teeth) <= p.gate_lateral_m
                and abs(heading) <= p.gate_heading_rad
                and sigma_m <= p.gate_sigma_m
            )
            if aligned:
                self._misaligned_since_s = None
            elif self._misaligned_since_s is None:
                self._misaligned_since_s = now_s
            persistent = (
                self._misaligned_since_s is not None
                and now_s - self._misaligned_since_s >= p.gate_persist_s
            )
            if persistent and gap > p.tooth_insertion_m:  # before the tips reach the troughs
                if self.attempts >= p.max_attempts:
                    self._switch(MotionPattern.STOP, now_s)
                    refused = command(MotionPattern.STOP, 0.0)
                    return DockingCommand(
                        **{
                            **refused.__dict__,
                            "refused": "not aligned at the gate after every attempt",
                        }
                    )
                self.attempts += 1
                self._misaligned_since_s = None
                self.phase = DockingPhase.BACK_OFF
                self._back_off_until_gap_m = gap + p.back_off_m
                self._switch(MotionPattern.STRAIGHT, now_s)
                return command(self.pattern, 0.0)
            speed = min(speed, p.min_speed_mps * 2)

        heading_bad = self._persists("heading", abs(heading) > heading_enter, now_s)
        # Fine, and the wheels back near straight: otherwise the error goes on changing
        # after the switch and the next correction is already on its way.
        heading_fine = (
            abs(heading) <= p.heading_near_rad * p.exit_fraction
            and abs(self._rear_rad) <= p.settled_steer_rad
        )
        # Where the front end will meet the board if it goes straight on: what the
        # lateral corrections null, so a heading left inside its band does not drift
        # the front end off the axis on the way in and call for another correction.
        # Crabbing moves it at ``v × crab`` whatever the heading; driving straight
        # leaves it where it is.
        lateral_ahead = lateral + gap * math.tan(heading)
        lateral_bad = self._persists("lateral", abs(lateral_ahead) > lateral_enter, now_s)
        lateral_fine = (
            abs(lateral_ahead) <= p.lateral_near_m * p.exit_fraction
            and abs(self._front_rad) <= p.settled_steer_rad
        )

        if self.phase is DockingPhase.HEADING and heading_fine:
            self.phase = DockingPhase.LATERAL
        if self.phase is DockingPhase.LATERAL and lateral_fine:
            self.phase = DockingPhase.APPROACH

        wanted: MotionPattern
        if self.phase is DockingPhase.HEADING:
            wanted = MotionPattern.REAR_STEER
        elif self.phase is DockingPhase.LATERAL:
            wanted = MotionPattern.OBLIQUE
        else:  # (c): keep the current correction until it is fine, start one when bad
            current = self.pattern
            correcting = (current is MotionPattern.REAR_STEER and not heading_fine) or (
                current is MotionPattern.OBLIQUE and not lateral_fine
            )
            if correcting:
                wanted = current
            elif heading_bad:
                wanted = MotionPattern.REAR_STEER
            elif lateral_bad:
                wanted = MotionPattern.OBLIQUE
            else:
                wanted = MotionPattern.STRAIGHT
        pattern = self._switch(wanted, now_s)

        if pattern is MotionPattern.REAR_STEER:
            # yaw rate = -v tan(δ_r) / L for a physical rear angle δ_r (left positive).
            yaw_rate = -p.heading_gain_per_s * heading
            rear = -math.atan(yaw_rate * p.wheelbase_m / max(speed, 1e-3))
            limit = min(p.max_rear_steer_rad, self._settling_angle(heading, p.wheelbase_m, speed))
            rear = max(-limit, min(limit, rear))
            return command(pattern, speed, *self._steer(0.0, rear, now_s))
        if pattern is MotionPattern.OBLIQUE:
            wanted_lateral_mps = -p.lateral_gain_per_s * lateral_ahead
            ratio = max(-0.99, min(0.99, wanted_lateral_mps / max(speed, 1e-3)))
            limit = self._settling_angle(lateral_ahead, 1.0, speed)
            crab = max(-limit, min(limit, math.asin(ratio)))
            crab = max(-p.max_crab_rad, min(p.max_crab_rad, crab))
            return command(pattern, speed, *self._steer(crab, 0.0, now_s))
        return command(pattern, speed, *self._steer(0.0, 0.0, now_s))
