"""The palm tree driven by the daemon (`dbw calibrate palm-tree --auto`), at walking pace.

Stanley et al. drove the palm tree (Fig. 18) by hand: the wheel held at full left, an arc
forward, half a turn right at a standstill, and again to full right. The fit needs only
that each arc is driven at one held wheel angle and is long enough; a program holds the
wheel steadier than a hand and stops exactly, so where the vehicle file allows it
(``[palm_tree_drive] allowed``, and only with hold-to-move: the operator walks beside the
vehicle holding the engage button, and letting go stops it) the daemon drives the arcs.

A small pure class stepped with explicit time, like the pedal sweep: its output is a
*wish* (a wheel angle and a speed target) that the mode machine and the safety layer
judge as any source's. It has the vehicle only in SPEED_HOLD with hold-to-move held;
otherwise it pauses, keeping how far the arc got, and when the operator hands back it
stands, checks the wheel again, and drives the rest of the arc.

An arc: the wheel turned to its target with the vehicle standing, at a hand's pace
(``steer_rate_rad_per_s``: a step of three turns at once is more than a servo follows
within the steering-tracking rule's tolerance, and more than a dry-steered linkage should
take), held within ``wheel_tolerance_rad`` for ``settle_s`` (``STEER``); the walking
pace until the arc's length is driven (``DRIVE``, the distance from the measured speed);
a stop, standing for ``stopped_s`` (``STOP``). After the last arc the wheel goes back to
the centre, standing (``CENTRE``), then ``DONE`` (standing, held by the speed
controller). Forward only: the pedals path cannot reverse, so the arcs go on across the
ground (a circle of the arcs' length at most around where it started) instead of backing
over themselves as in the paper. Deny by default: an unknown speed or wheel angle stands
still (``NO_READING``); a wheel that does not reach its target within ``steer_timeout_s``
of its turn is reported (``stuck``), and the source then refuses, which disengages. The
wheel is only ever turned by the program while it has the vehicle: engaged without it,
the wheel is held where it was when the operator engaged (or let go), so an engagement
never swings it to a lock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

# The distance integration's longest step: a late cycle is not a jump in the arc.
MAX_STEP_S = 0.2


class DrivePhase(StrEnum):
    STEER = "steer"
    DRIVE = "drive"
    STOP = "stop"
    CENTRE = "centre"
    DONE = "done"
    PAUSED = "paused"  # the vehicle is not the program's this cycle
    NO_READING = "no_reading"


@dataclass(frozen=True)
class PalmTreeDriveParams:
    wheel_targets_rad: tuple[float, ...]  # in the order driven (left positive)
    arc_m: float
    speed_mps: float
    wheel_tolerance_rad: float = 0.05
    steer_rate_rad_per_s: float = 2.0  # the wheel's, turned standing
    settle_s: float = 1.0
    steer_timeout_s: float = 20.0
    # A GNSS/INS speed reads a few cm/s on a vehicle held by its brake.
    stopped_mps: float = 0.15
    stopped_s: float = 1.0

    def __post_init__(self) -> None:
        if not self.wheel_targets_rad:
            raise ValueError("the palm tree needs at least one wheel angle")
        if not all(math.isfinite(w) for w in self.wheel_targets_rad):
            raise ValueError(f"wheel targets must be finite (got {self.wheel_targets_rad})")
        for name in (
            "arc_m",
            "speed_mps",
            "wheel_tolerance_rad",
            "steer_rate_rad_per_s",
            "steer_timeout_s",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite (got {value})")
        for name in ("settle_s", "stopped_mps", "stopped_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be non-negative and finite (got {value})")

    @property
    def arcs(self) -> int:
        return len(self.wheel_targets_rad)


@dataclass(frozen=True)
class DriveCommand:
    """The program's wheel angle and speed this cycle, and where it is."""

    phase: DrivePhase
    arc: int  # 0-based; == arcs once every arc is driven
    arcs: int
    wheel_target_rad: float  # the arc's
    wheel_aim_rad: float  # what the wheel is steered to now, on its way to the target
    speed_mps: float  # the speed target: 0 stands (the controller stops and holds)
    driven_m: float  # along the current arc
    stuck: str | None = None  # the wheel did not get to its target: the source refuses

    def as_status(self) -> dict[str, object]:
        return {
            "phase": str(self.phase),
            "arc": min(self.arc + 1, self.arcs),
            "arcs": self.arcs,
            "wheel_target_rad": round(self.wheel_target_rad, 4),
            "wheel_aim_rad": round(self.wheel_aim_rad, 4),
            "speed_mps": self.speed_mps,
            "driven_m": round(self.driven_m, 2),
            "stuck": self.stuck,
        }


class PalmTreeDrive:
    """The program (see the module): ``reset()``, then ``update()`` once per cycle."""

    def __init__(self, params: PalmTreeDriveParams) -> None:
        self.params = params
        self.reset()

    def reset(self, first_arc: int = 0) -> None:
        """From the first arc, or from ``first_arc`` (a resumed maneuver: the arcs before
        it are in its samples already)."""
        if not 0 <= first_arc < self.params.arcs:
            raise ValueError(f"the palm tree has arcs 0..{self.params.arcs - 1}, not {first_arc}")
        self.arc = first_arc
        self.phase = DrivePhase.STEER
        self.driven_m = 0.0
        self._since_s: float | None = None  # when the current phase began
        self._ok_since_s: float | None = None  # standing (and on target) since
        self._last_s: float | None = None
        self._aim_rad: float | None = None  # None: not known yet (no wheel reading)
        self._budget_s = self.params.steer_timeout_s  # for the phase's steering

    @property
    def done(self) -> bool:
        return self.phase is DrivePhase.DONE

    @property
    def wheel_target_rad(self) -> float:
        if self.arc >= self.params.arcs:
            return 0.0
        return self.params.wheel_targets_rad[self.arc]

    def pause(self) -> None:
        """The vehicle was taken away: stand, and check the wheel again, before the rest
        of the arc (a stop already under way just finishes)."""
        if self.phase in (DrivePhase.DRIVE, DrivePhase.STEER):
            self._enter(DrivePhase.STEER)
        self._last_s = None

    def update(
        self,
        wheel_rad: float | None,
        speed_mps: float | None,
        now_s: float,
        in_control: bool,
        steering: bool = True,
    ) -> DriveCommand:
        """One cycle: ``in_control`` when the program has the vehicle (speed hold, the
        button held); ``steering`` when the steering is automatic at all (engaged)."""
        p = self.params
        wheel_known = wheel_rad is not None and math.isfinite(wheel_rad)
        if not in_control:
            self.pause()
            if wheel_known and (not steering or self._aim_rad is None):
                self._aim_rad = wheel_rad  # the operator's wheel, held where they left it
            return self._command(DrivePhase.PAUSED, 0.0)
        if (
            wheel_rad is None
            or speed_mps is None
            or not wheel_known
            or not math.isfinite(speed_mps)
        ):
            self.pause()
            return self._command(DrivePhase.NO_READING, 0.0)
        speed = abs(speed_mps)
        aim = wheel_rad if self._aim_rad is None else self._aim_rad
        if self._since_s is None:
            self._since_s = now_s
            travel_rad = abs(self.wheel_target_rad - aim)
            self._budget_s = p.steer_timeout_s + travel_rad / p.steer_rate_rad_per_s
        step_s = 0.0 if self._last_s is None else min(MAX_STEP_S, max(0.0, now_s - self._last_s))
        self._last_s = now_s
        standing = speed < p.stopped_mps
        stuck = None
        if self.phase in (DrivePhase.STEER, DrivePhase.CENTRE):
            if standing:  # turned only standing: every arc at one held angle
                reach = p.steer_rate_rad_per_s * step_s
                aim += max(-reach, min(reach, self.wheel_target_rad - aim))
            on_target = abs(wheel_rad - self.wheel_target_rad) <= p.wheel_tolerance_rad
            if self._held(standing and on_target, now_s, p.settle_s):
                self._enter(DrivePhase.DRIVE if self.phase is DrivePhase.STEER else DrivePhase.DONE)
            elif now_s - self._since_s > self._budget_s:
                stuck = (
                    f"the wheel is at {wheel_rad:+.2f} rad, not {self.wheel_target_rad:+.2f} "
                    f"(± {p.wheel_tolerance_rad:.2f}) after {self._budget_s:.0f} s"
                    + ("" if standing else f", the vehicle moving at {speed:.2f} m/s")
                )
        elif self.phase is DrivePhase.DRIVE:
            self.driven_m += speed * step_s
            if self.driven_m >= p.arc_m:
                self._enter(DrivePhase.STOP)
        elif self.phase is DrivePhase.STOP and self._held(standing, now_s, p.stopped_s):
            self.arc += 1
            self.driven_m = 0.0
            self._enter(DrivePhase.CENTRE if self.arc >= p.arcs else DrivePhase.STEER)
        self._aim_rad = aim
        speed_target = p.speed_mps if self.phase is DrivePhase.DRIVE else 0.0
        return self._command(self.phase, speed_target, stuck)

    def _held(self, condition: bool, now_s: float, for_s: float) -> bool:
        """Has ``condition`` held for ``for_s`` (counted from the first cycle it held)?"""
        if not condition:
            self._ok_since_s = None
            return False
        if self._ok_since_s is None:
            self._ok_since_s = now_s
        return now_s - self._ok_since_s >= for_s

    def _enter(self, phase: DrivePhase) -> None:
        self.phase = phase
        self._since_s = None
        self._ok_since_s = None

    def _command(
        self, phase: DrivePhase, speed_mps: float, stuck: str | None = None
    ) -> DriveCommand:
        target = self.wheel_target_rad
        return DriveCommand(
            phase,
            self.arc,
            self.params.arcs,
            target,
            target if self._aim_rad is None else self._aim_rad,
            speed_mps,
            self.driven_m,
            stuck,
        )


def half_turn_targets(low_rad: float, high_rad: float, half_turn_rad: float) -> tuple[float, ...]:
    """Full left (``high_rad``) to full right (``low_rad``): both ends of the usable range
    (the map is measured out to them, as a technician drives to each lock), and between
    them every half turn, on the centres of the bins the fit's coverage counts (a target
    on a bin's edge would split its arc between two), but for the ends' own bins, which
    their arcs cover (binned as the fit bins: ``round``)."""
    if not (math.isfinite(low_rad) and math.isfinite(high_rad) and low_rad < high_rad):
        raise ValueError(f"the wheel's range must be increasing (got {low_rad}..{high_rad})")
    if not (math.isfinite(half_turn_rad) and half_turn_rad > 0.0):
        raise ValueError(f"half_turn_rad must be positive (got {half_turn_rad})")
    ends = {round(low_rad / half_turn_rad), round(high_rad / half_turn_rad)}
    first, last = math.floor(high_rad / half_turn_rad), math.ceil(low_rad / half_turn_rad)
    centres = [
        k * half_turn_rad
        for k in range(first, last - 1, -1)
        if k not in ends and low_rad < k * half_turn_rad < high_rad
    ]
    return (high_rad, *centres, low_rad)
