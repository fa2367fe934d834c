"""Consistency: does the steering follow its command, and is the PC104 link healthy?

Two ways a commanded actuator can silently stop doing what it is told. The steering
servo can lose torque or slip (Stanley et al. report servo torque problems), so the
wheels no longer follow the command although every message arrives: the tracking
monitor compares commanded with measured. A link can deliver damaged or out-of-sequence
frames now and then without ever going stale: the error budget, after panda's
``wrong_counters``, tolerates the odd bad frame but not a run of them.

Pure rules: time comes in as ``now_s`` (monotonic seconds), angles are tyre angles in
radians, converted from the vehicle file's degrees once, in ``appliance.config.parts``.
Each returns the condition (a level); latching it into a fault is the fault monitor's
and the mode machine's job.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass


@dataclass(frozen=True)
class SteeringTrackingParams:
    tolerance_rad: float
    fault_after_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.tolerance_rad) and self.tolerance_rad > 0.0):
            raise ValueError("tolerance_rad must be positive and finite")
        if not (math.isfinite(self.fault_after_s) and self.fault_after_s > 0.0):
            raise ValueError("fault_after_s must be positive and finite")


class SteeringTrackingMonitor:
    """True (a steering fault) while the servo is not steering the wheels.

    - Released (``commanded_rad`` None) or ``overriding`` (the operator has the wheel,
      so the deviation is theirs): never a fault, and the timer resets.
    - Otherwise the steering is off track when ``|measured - commanded| >
      tolerance_rad`` or when it cannot be seen (measured None or non-finite: a steering
      we cannot see is a steering we cannot trust). Off track continuously for at least
      ``fault_after_s`` is a fault; exactly at the tolerance is on track.
    - A non-finite ``commanded_rad`` or ``now_s`` is a broken producer or clock: a fault
      at once, whatever ``overriding`` says, and the timer is left as it was.

    Time going backwards restarts the timer from the new ``now_s``.
    """

    def __init__(self, params: SteeringTrackingParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self.off_track_since_s: float | None = None

    def update(
        self,
        commanded_rad: float | None,
        measured_rad: float | None,
        overriding: bool,
        now_s: float,
    ) -> bool:
        """Return True while the steering has been off track for ``fault_after_s``."""
        if commanded_rad is None:
            self.reset()
            return False
        if not (math.isfinite(commanded_rad) and math.isfinite(now_s)):
            return True
        if overriding:
            self.reset()
            return False
        off_track = (
            measured_rad is None
            or not math.isfinite(measured_rad)
            or abs(measured_rad - commanded_rad) > self.params.tolerance_rad
        )
        if not off_track:
            self.reset()
            return False
        if self.off_track_since_s is None or now_s < self.off_track_since_s:
            self.off_track_since_s = now_s
        return now_s - self.off_track_since_s >= self.params.fault_after_s


def _check_count(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{name} must be a non-negative int (got {value!r})")


class ErrorBudget:
    """A budget of link errors, after panda's ``wrong_counters``.

    Every error (CRC, rolling counter, length) adds one, capped at ``limit``; every good
    frame takes one away, floored at 0. The budget is exhausted once it reaches the
    limit and stays exhausted until it is back at 0 (hysteresis): a link that produced a
    burst of errors has to prove itself with as many good frames before it is trusted.

    Within one update the errors count before the good frames: the order of the frames
    inside a batch is unknown, so the pessimistic one is assumed. An update whose errors
    reach the limit reports exhausted even if its good frames bring the budget back to 0;
    the next update reports the recovery. Negative or non-integer counts are a caller's
    bug and raise ValueError, with the budget unchanged.
    """

    def __init__(self, limit: int) -> None:
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"limit must be a positive int (got {limit!r})")
        self.limit = limit
        self.reset()

    def reset(self) -> None:
        self.level = 0
        self.exhausted = False

    def update(self, errors: int, good: int) -> bool:
        """Add ``errors``, take away ``good``; return True while the budget is exhausted."""
        _check_count("errors", errors)
        _check_count("good", good)
        level = min(self.level + errors, self.limit)
        reached = level >= self.limit
        self.level = max(level - good, 0)
        self.exhausted = reached or (self.exhausted and self.level > 0)
        return self.exhausted


class CounterDeltas:
    """Turns a driver's ever-growing totals into what happened since the last update.

    ``update`` takes the totals by name (e.g. ``{"errors": crc + counter + malformed,
    "frames": frames_received}``) and returns the increase of each since the last
    update. The first time a name is seen is its baseline: delta 0. A total that goes
    down means the driver restarted and reset its counters; differences across two runs
    of a driver mean nothing, so then every total of that update re-baselines with delta
    0 and ``restarted`` is True for that update (the caller decides whether a restart is
    worth a log line or a fault). A name missing from an update keeps its baseline.
    Negative or non-integer totals raise ValueError, with the baselines unchanged.
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.totals: dict[str, int] = {}
        self.restarted = False

    def update(self, totals: Mapping[str, int]) -> dict[str, int]:
        """Return each total's increase since the previous update (0 on a baseline)."""
        for name, total in totals.items():
            _check_count(name, total)
        self.restarted = any(
            total < self.totals[name] for name, total in totals.items() if name in self.totals
        )
        deltas = {
            name: 0 if self.restarted else total - self.totals.get(name, total)
            for name, total in totals.items()
        }
        self.totals.update(totals)
        return deltas
