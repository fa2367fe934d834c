"""The pedal sweep: the one calibration maneuver the daemon drives itself.

A throttle or brake map (``calibration.pedal_map``) needs each pedal held steady at known
levels across the speed range, which no driver's foot does: Dataspeed's throttle and brake
sweeps and Autoware's accel/brake map calibrator drive the pedals by program. Here the
program is a small pure class, stepped by the core with explicit time, whose output is a
*wish* like any autopilot source's: it goes through the mode machine, arbitration and the
pedal limiter, and is honoured only in SPEED_HOLD on the ``pedals`` speed path, with the
operator's engagement (and hold-to-move where the vehicle file asks for it). A brake tap,
the throttle pedal, the wheel, the override button, the e-stop or any fault take the
pedals away within the cycle, as from the speed controller; the sweep then pauses, and
when the operator hands the pedals back the interrupted run starts over from standstill
(its samples so far are kept by the client; a run is only useful from a steady start).

A run: brake to a standstill and wait (``STOPPING``); hold the run's throttle level until
the top speed, or until the speed stops rising, or a time limit (``THROTTLE``); a level too
low to get there is followed by the sweep's highest level up to the top speed (``BOOST``),
then held again while the vehicle slows from the top to where it had stopped gaining
(``DESCEND``: a low throttle at high speed is what a speed hold at the top sits on, and
no acceleration from standstill gets there), then boosted to the top once more, so every
brake starts from the top: a brake step fills its cells only once its lag has settled,
and a light brake's cells at high speed are the ones the speed controller uses most.
Then both pedals released (``COAST``, the 0 % column of both maps), and the run's
brake level to a stop (``BRAKE``). A brake level of 0 is a coast-down: released until
``coast_down_end_mps``, then the hold brake. Runs pair the throttle and brake levels in
order, the shorter list repeating. Deny by default: an unknown speed, or a speed past the
top by ``overspeed_margin_mps``, brakes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum


class SweepPhase(StrEnum):
    STOPPING = "stopping"
    THROTTLE = "throttle"
    BOOST = "boost"
    DESCEND = "descend"
    COAST = "coast"
    BRAKE = "brake"
    DONE = "done"
    PAUSED = "paused"  # the pedals are not the sweep's this cycle
    NO_SPEED = "no_speed"


@dataclass(frozen=True)
class PedalSweepParams:
    throttle_levels_pct: tuple[float, ...]
    brake_levels_pct: tuple[float, ...]
    top_speed_mps: float
    coast_s: float = 4.0
    max_throttle_s: float = 30.0
    coast_down_end_mps: float = 0.5
    hold_brake_pct: float = 40.0
    # Standing: a GNSS/INS speed reads a few cm/s on a vehicle held by its brake.
    stopped_mps: float = 0.15
    stopped_s: float = 1.0  # standing this long before a run's throttle
    # The throttle phase ends when the speed gained less than this over plateau_s.
    plateau_gain_mps: float = 0.1
    plateau_s: float = 3.0
    overspeed_margin_mps: float = 0.3

    def __post_init__(self) -> None:
        if not self.throttle_levels_pct or not self.brake_levels_pct:
            raise ValueError("the sweep needs at least one throttle and one brake level")
        if not all(math.isfinite(x) and 0.0 < x <= 100.0 for x in self.throttle_levels_pct):
            raise ValueError(
                f"throttle levels must lie in (0, 100] (got {self.throttle_levels_pct})"
            )
        if not (math.isfinite(self.hold_brake_pct) and 0.0 < self.hold_brake_pct <= 100.0):
            raise ValueError(f"hold_brake_pct must lie in (0, 100] (got {self.hold_brake_pct})")
        if not all(math.isfinite(x) and 0.0 <= x <= 100.0 for x in self.brake_levels_pct):
            raise ValueError(f"brake levels must lie in [0, 100] (got {self.brake_levels_pct})")
        for name in ("top_speed_mps", "max_throttle_s", "stopped_mps", "plateau_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be positive and finite (got {value})")

    @property
    def runs(self) -> int:
        return max(len(self.throttle_levels_pct), len(self.brake_levels_pct))

    def levels(self, run: int) -> tuple[float, float]:
        """The run's throttle and brake levels."""
        throttle, brake = self.throttle_levels_pct, self.brake_levels_pct
        return throttle[run % len(throttle)], brake[run % len(brake)]


@dataclass(frozen=True)
class SweepCommand:
    """The sweep's pedals this cycle, and where it is (for the tap and `dbw status`)."""

    phase: SweepPhase
    run: int  # 0-based; == runs when done
    runs: int
    throttle_pct: float
    brake_pct: float

    def as_status(self) -> dict[str, object]:
        return {
            "phase": str(self.phase),
            "run": min(self.run + 1, self.runs),
            "runs": self.runs,
            "throttle_pct": self.throttle_pct,
            "brake_pct": self.brake_pct,
        }


class PedalSweep:
    """The program (see the module): ``reset()``, ``update(speed, now, in_control)``."""

    def __init__(self, params: PedalSweepParams) -> None:
        self.params = params
        self.reset()

    def reset(self, first_run: int = 0) -> None:
        """From the start, or from ``first_run`` (a resumed maneuver: the runs before it
        are in its samples already)."""
        if not 0 <= first_run < self.params.runs:
            raise ValueError(f"the sweep has runs 0..{self.params.runs - 1}, not {first_run}")
        self.run = first_run
        self.phase = SweepPhase.STOPPING
        self._since_s: float | None = None  # when the current phase began
        self._still_since_s: float | None = None
        self._plateau_from: tuple[float, float] | None = None  # (t, speed) of the window
        self._low_from_mps: float | None = None  # where the run's level stopped gaining
        self._descended = False

    @property
    def done(self) -> bool:
        return self.phase is SweepPhase.DONE

    def pause(self) -> None:
        """The pedals were taken away: the run starts over from a standstill."""
        if self.phase is not SweepPhase.DONE:
            self._enter(SweepPhase.STOPPING, None)

    def update(self, speed_mps: float | None, now_s: float, in_control: bool) -> SweepCommand:
        p = self.params
        if not in_control:
            self.pause()
            return self._command(SweepPhase.PAUSED, 0.0, 0.0)
        if speed_mps is None or not math.isfinite(speed_mps):
            self.pause()
            return self._command(SweepPhase.NO_SPEED, 0.0, p.hold_brake_pct)
        speed = abs(speed_mps)
        if self._since_s is None:
            self._since_s = now_s
        throttle_pct, brake_pct = p.levels(min(self.run, p.runs - 1))
        if self.phase is SweepPhase.STOPPING:
            self._still_since_s = (
                (self._still_since_s if self._still_since_s is not None else now_s)
                if speed < p.stopped_mps
                else None
            )
            if self._still_since_s is not None and now_s - self._still_since_s >= p.stopped_s:
                self._enter(SweepPhase.THROTTLE, now_s)
                self._plateau_from = (now_s, speed)
        elif self.phase is SweepPhase.THROTTLE:
            timed_out = now_s - self._since_s >= p.max_throttle_s
            if speed >= p.top_speed_mps:
                self._enter(SweepPhase.COAST, now_s)
            elif self._gained_less(speed, now_s, p.plateau_gain_mps) or timed_out:
                self._low_from_mps = speed
                self._enter(SweepPhase.BOOST, now_s)
        elif self.phase is SweepPhase.BOOST:
            if speed >= p.top_speed_mps or now_s - self._since_s >= p.max_throttle_s:
                descend = self._low_from_mps is not None and not self._descended
                self._enter(SweepPhase.DESCEND if descend else SweepPhase.COAST, now_s)
                self._plateau_from = (now_s, -speed)  # the descent watches the speed fall
        elif self.phase is SweepPhase.DESCEND:
            low = self._low_from_mps if self._low_from_mps is not None else 0.0
            timed_out = now_s - self._since_s >= p.max_throttle_s
            stopped_falling = self._gained_less(-speed, now_s, p.plateau_gain_mps)
            if speed <= low or stopped_falling or timed_out:
                self._descended = True
                self._enter(SweepPhase.BOOST, now_s)
        elif self.phase is SweepPhase.COAST:
            if now_s - self._since_s >= p.coast_s:
                self._enter(SweepPhase.BRAKE, now_s)
        elif self.phase is SweepPhase.BRAKE and speed < p.stopped_mps:
            self.run += 1
            self._enter(SweepPhase.DONE if self.run >= p.runs else SweepPhase.STOPPING, now_s)
        if speed > p.top_speed_mps + p.overspeed_margin_mps and self.phase in (
            SweepPhase.THROTTLE,
            SweepPhase.BOOST,
            SweepPhase.DESCEND,
            SweepPhase.COAST,
        ):
            self._enter(SweepPhase.BRAKE, now_s)  # deny by default: never faster than planned
        match self.phase:
            case SweepPhase.THROTTLE | SweepPhase.DESCEND:
                return self._command(self.phase, throttle_pct, 0.0)
            case SweepPhase.BOOST:
                return self._command(self.phase, max(p.throttle_levels_pct), 0.0)
            case SweepPhase.COAST:
                return self._command(self.phase, 0.0, 0.0)
            case SweepPhase.BRAKE:
                overspeed = speed > p.top_speed_mps + p.overspeed_margin_mps
                coasted = brake_pct == 0.0 and speed < p.coast_down_end_mps
                brake = p.hold_brake_pct if overspeed or coasted else brake_pct
                return self._command(self.phase, 0.0, brake)
            case _:
                return self._command(self.phase, 0.0, p.hold_brake_pct)

    def _gained_less(self, value: float, now_s: float, gain: float) -> bool:
        """Once per ``plateau_s`` window: did ``value`` (the speed rising, or its negative
        falling) gain less than ``gain`` over the window that just closed?"""
        start = self._plateau_from
        if start is None or now_s - start[0] < self.params.plateau_s:
            return False
        self._plateau_from = (now_s, value)
        return value - start[1] < gain

    def _enter(self, phase: SweepPhase, now_s: float | None) -> None:
        self.phase = phase
        self._since_s = now_s
        self._still_since_s = None
        if phase is SweepPhase.STOPPING:  # a run (again) from the start
            self._low_from_mps = None
            self._descended = False

    def _command(self, phase: SweepPhase, throttle_pct: float, brake_pct: float) -> SweepCommand:
        return SweepCommand(phase, self.run, self.params.runs, throttle_pct, brake_pct)
