"""Safe defaults as a function of time: the brake ramp and the speed set-point ramp.

On a fault the brake goes on at a configured deceleration, ramped in so a loaded nine-ton
vehicle at speed is not thrown onto its wheel locks by a sensor dropout; an e-stop
applies full brake at once. The speed set-point sent to the PC104 may rise only at the
configured acceleration; it may always fall, but a controlled stop (hold-to-move
released) falls at the deceleration that stops within the configured distance. Both are
small classes with ``reset()``/``update()`` and explicit time (STYLE rules 5 and 7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum


class SafeKind(StrEnum):
    NONE = "none"  # not in a safe state: the brake is released
    FAULT = "fault"  # ramp to the safe-stop deceleration
    ESTOP = "estop"  # full brake now


@dataclass(frozen=True)
class SafeBrakeParams:
    fault_brake_pct: float
    estop_brake_pct: float
    ramp_pct_per_s: float
    max_step_dt_s: float = 0.1


class SafeBrake:
    """The brake level of the safe state, ramped on faults, immediate on e-stop."""

    def __init__(self, params: SafeBrakeParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._pct = 0.0
        self._last_s: float | None = None

    def update(self, kind: SafeKind, now_s: float) -> float:
        p = self.params
        dt_s = 0.0 if self._last_s is None else min(max(now_s - self._last_s, 0.0), p.max_step_dt_s)
        self._last_s = now_s
        if kind is SafeKind.NONE:
            self._pct = 0.0
            return 0.0
        if kind is SafeKind.ESTOP or not math.isfinite(now_s):
            self._pct = p.estop_brake_pct
            return self._pct
        # Start the ramp from a real brake at once: the first cycle already brakes.
        start = max(self._pct, min(p.fault_brake_pct, p.ramp_pct_per_s * 0.02))
        self._pct = min(p.fault_brake_pct, start + p.ramp_pct_per_s * dt_s)
        return self._pct


@dataclass(frozen=True)
class SpeedRampParams:
    max_speed_mps: float
    max_accel_mps2: float
    stop_distance_m: float
    max_step_dt_s: float = 0.1


# The PC104's speed loop lags its set-point; aiming at a shorter distance than allowed
# leaves room for that lag.
STOP_DISTANCE_MARGIN = 0.7


class SpeedRamp:
    """The speed set-point: capped, rising at the acceleration limit, stopping in distance."""

    def __init__(self, params: SpeedRampParams) -> None:
        self.params = params
        self.reset()

    def reset(self, speed_mps: float = 0.0) -> None:
        self._setpoint_mps = max(0.0, speed_mps) if math.isfinite(speed_mps) else 0.0
        self._last_s: float | None = None
        self._stop_decel_mps2: float | None = None

    @property
    def setpoint_mps(self) -> float:
        return self._setpoint_mps

    def update(self, target_mps: float, now_s: float, *, controlled_stop: bool = False) -> float:
        """The next set-point toward ``target_mps`` (non-finite target: 0, deny by default).

        A non-finite ``now_s`` is a broken clock: the set-point may fall but not rise, and
        the last good time is kept so the next good cycle ramps from it.
        """
        p = self.params
        if not math.isfinite(now_s):
            self._setpoint_mps = (
                min(self._setpoint_mps, max(target_mps, 0.0)) if math.isfinite(target_mps) else 0.0
            )
            return self._setpoint_mps
        dt_s = 0.0 if self._last_s is None else min(max(now_s - self._last_s, 0.0), p.max_step_dt_s)
        self._last_s = now_s
        target = min(max(target_mps, 0.0), p.max_speed_mps) if math.isfinite(target_mps) else 0.0
        if controlled_stop:
            if self._stop_decel_mps2 is None:  # fixed at the release: v^2 / (2 d)
                v = self._setpoint_mps
                self._stop_decel_mps2 = max(
                    v * v / (2.0 * p.stop_distance_m * STOP_DISTANCE_MARGIN), 0.05
                )
            self._setpoint_mps = max(0.0, self._setpoint_mps - self._stop_decel_mps2 * dt_s)
            return self._setpoint_mps
        self._stop_decel_mps2 = None
        if target > self._setpoint_mps:
            self._setpoint_mps = min(target, self._setpoint_mps + p.max_accel_mps2 * dt_s)
        else:
            self._setpoint_mps = target
        return self._setpoint_mps
