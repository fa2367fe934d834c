"""The steps done by hand: what they share (HandStep), and the pot centre.

Each step is the glue between the daemon's tapped samples and a pure fit in
``calibration/``: which samples it needs fresh, what the technician is told, what breaks
the maneuver (moving during a stationary step), how complete the coverage is, and how the
fit's numbers become the calibration file's. The fits decide; the steps only translate.

The steps by hand watch and never command: the technician turns the wheel and drives, the daemon
stays out of automatic modes (engaging during a hand maneuver aborts it), so the safety
layer has nothing to refuse.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, ClassVar

import click

from appliance.config.calibration import CalibrationFile
from appliance.config.models import VehicleConfig
from appliance.maneuvers.merge import StepResult
from appliance.maneuvers.report import FitReport, item_record
from appliance.maneuvers.runner import Progress
from calibration.fit_checks import Verdict
from calibration.pot_centre import PotCentreAccumulator, PotCentreResult
from calibration.pot_map import wheel_rad_at

BAR_WIDTH = 20
# A stationary step: faster than this for longer than MOVING_S, the vehicle is moving.
# Not tighter: a GNSS/INS speed reads up to ~0.15 m/s on a vehicle standing still.
STILL_MPS = 0.3
MOVING_S = 1.0
MAX_FIX_AGE_S = 0.5


@dataclass(frozen=True)
class StepContext:
    config: VehicleConfig
    calibration: CalibrationFile | None  # what the step builds on (None: first install)
    options: Mapping[str, Any] = field(default_factory=dict)


def bar(fraction: float) -> str:
    filled = round(max(0.0, min(1.0, fraction)) * BAR_WIDTH)
    return "#" * filled + "." * (BAR_WIDTH - filled)


def counts_text(value: float | None) -> str:
    return "none" if value is None else f"{value:.1f} counts"


def with_unread(rejected: Mapping[str, int], taken: int, fitted: int) -> dict[str, int]:
    """The fit's rejections, plus the tapped samples that never reached it (no reading)."""
    missing = taken - fitted
    return {**rejected, **({"no reading": missing} if missing else {})}


def tail_lines(
    taken: int, used: int, rejected: Mapping[str, int], method: str, verdict: Verdict
) -> list[str]:
    """What every step's report ends with: the samples' fate, the method, the verdict."""
    refused = ", ".join(f"{k} {v}" for k, v in rejected.items() if v) or "none"
    outcome = "ACCEPTED" if verdict.accepted else "REFUSED: " + "; ".join(verdict.reasons)
    return [
        f"  samples {taken}: used {used}, rejected {refused}",
        f"  method: {method}",
        f"  verdict: {outcome}",
    ]


def sample_number(sample: Mapping[str, Any], key: str) -> float | None:
    value = sample.get(key)
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else None


def sample_speed(sample: Mapping[str, Any]) -> float | None:
    speed = sample_number(sample, "speed_mps")
    return speed if speed is not None else sample_number(sample, "gnss_speed_mps")


class HandStep(ABC):
    """What the steps done by hand share: they end if the operator engages."""

    name: ClassVar[str]
    summary: ClassVar[str]
    extra_options: ClassVar[tuple[Any, ...]] = ()
    instructions: tuple[str, ...] = ()
    moves_vehicle = False
    # How long a run may take before the command gives up (the vehicle left safe).
    default_timeout_s: float = 900.0
    needed_inputs: tuple[str, ...] = ("board.steering", "steering.pot")
    tolerated_faults: frozenset[str] = frozenset()

    def __init__(self, context: StepContext) -> None:
        self.context = context
        self.reset()

    @abstractmethod
    def reset(self) -> None:
        """Forget every sample taken (a fit starts from this too)."""

    def start_step(self) -> str:
        """The daemon is told the step's name: a step by hand resumes by itself (its
        samples so far are taken again before the run goes on)."""
        return self.name

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = []
        mode = str(status.get("mode"))
        if mode in ("error", "estop"):
            pass  # said by the runner's common checks (or tolerated: what this step measures)
        elif mode not in ("self_check", "ready"):
            problems.append(
                f"the daemon is in {mode.upper()}: a maneuver by hand needs it in READY or "
                "SELF_CHECK (disengage first)"
            )
        if status.get("vehicle") != self.context.config.name:
            problems.append(
                f"the daemon runs vehicle {status.get('vehicle')!r}, not "
                f"{self.context.config.name!r}: give the right --config"
            )
        return problems

    def update(self, sample: Mapping[str, Any]) -> str | None:
        if sample.get("engaged"):
            return "the operator engaged: a maneuver by hand runs with the autopilot off"
        return self.take(sample)

    @abstractmethod
    def take(self, sample: Mapping[str, Any]) -> str | None:
        """Take one sample as the step needs it (the engaged check done); a text ends
        the run."""

    @abstractmethod
    def progress(self) -> Progress:
        """The coverage so far, as the technician's progress line shows it."""

    @abstractmethod
    def complete(self) -> bool:
        """Enough taken for the fit: the run stops tapping and fits."""

    @abstractmethod
    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        """The fit over ``samples`` (a live run's, a samples file's or a recording's)."""

    def steering_ratio(self) -> float:
        ratio = self.context.options.get("x_steering_ratio")
        if isinstance(ratio, int | float) and ratio > 0:
            return float(ratio)
        if self.context.calibration is not None:
            return self.context.calibration.steering.steering_ratio
        raise click.UsageError(
            "no calibration to take the steering ratio from: give --steering-ratio (the "
            "steering gear's, from its data sheet; the palm tree measures it later)"
        )


class DrivenStep(HandStep):
    """A step the daemon drives (the pedal sweep, the look-ahead runs): it runs engaged,
    so an engagement does not end it, and it is armed from READY."""

    moves_vehicle = True

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = []
        config = self.context.config
        if status.get("vehicle") != config.name:
            problems.append(
                f"the daemon runs vehicle {status.get('vehicle')!r}, not {config.name!r}: "
                "give the right --config"
            )
        mode = str(status.get("mode"))
        if mode not in ("ready", "error", "estop"):  # the last two: the runner's checks
            problems.append(f"the daemon is in {mode.upper()}: {self.name} starts from READY")
        return problems

    def update(self, sample: Mapping[str, Any]) -> str | None:
        return self.take(sample)


class PotCentreStep(HandStep):
    name = "pot-center"
    summary = "Drive straight along a visual reference: the pot's straight-ahead reading."
    extra_options = (
        click.option(
            "--counts-per-tyre-deg",
            "x_counts_per_tyre_deg",
            type=float,
            help="The pot's slope, where no calibration gives it (first installation).",
        ),
    )
    needed_inputs: tuple[str, ...] = ("board.steering", "steering.pot")
    instructions: tuple[str, ...] = (
        "pot-center: drive straight along a visual reference (a kerb, a painted line),",
        "  at a steady speed above 1 m/s, for at least three stretches of 10 m or more",
        "  (100 m in all). Turn around between stretches as you like: turns are left out.",
    )

    def reset(self) -> None:
        self.accumulator = PotCentreAccumulator()
        self._checked = 0
        self._coverage_at = -1

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = super().preconditions(status)
        gnss = status.get("gnss")
        if not isinstance(gnss, dict) or not gnss.get("fix") or gnss.get("yaw_deg") is None:
            problems.append(
                "no GNSS/INS fix with a heading: the straight stretches are found from its "
                "heading rate (is the receiver connected and fixed?)"
            )
        return problems

    def take(self, sample: Mapping[str, Any]) -> str | None:
        pot = sample_number(sample, "pot_counts")
        speed = sample_speed(sample)
        yaw_rate = sample_number(sample, "yaw_rate_rad_per_s")
        t_s = sample_number(sample, "t_s")
        if pot is None or speed is None or yaw_rate is None or t_s is None:
            return None  # counted by the fit as missing, never a reason to stop
        gnss_t = sample_number(sample, "gnss_time_s")
        fix_ok = gnss_t is not None and t_s - gnss_t <= MAX_FIX_AGE_S
        self.accumulator.update(t_s, pot, yaw_rate, abs(speed), 0.0, fix_ok)
        return None

    def progress(self) -> Progress:
        coverage = self.accumulator.coverage()
        fraction = min(
            coverage.segments / coverage.segments_needed,
            coverage.distance_m / coverage.distance_needed_m,
        )
        return Progress(
            min(1.0, fraction),
            bar(fraction),
            f"{coverage.segments}/{coverage.segments_needed} straight stretches, "
            f"{coverage.distance_m:.0f}/{coverage.distance_needed_m:.0f} m",
        )

    def complete(self) -> bool:
        return self.accumulator.coverage().complete

    def counts_per_tyre_deg(self) -> float:
        given = self.context.options.get("x_counts_per_tyre_deg")
        if isinstance(given, int | float) and given != 0:
            return float(given)
        calibration = self.context.calibration
        if calibration is None:
            raise click.UsageError(
                "no calibration to take the pot's slope from: give --counts-per-tyre-deg"
            )
        steering = calibration.steering
        slope_rad_per_count = float(wheel_rad_at(steering.pot_to_wheel_coeffs, 1.0))
        return math.radians(1.0) * steering.steering_ratio / slope_rad_per_count

    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        self.reset()
        for sample in samples:
            self.take(sample)
        result = self.accumulator.fit(self.counts_per_tyre_deg())
        return pot_centre_report(result, len(samples), raw_data)


def pot_centre_report(result: PotCentreResult, taken: int, raw_data: str | None) -> FitReport:
    verdict = result.verdict
    rejected = with_unread(result.rejected, taken, result.samples)
    centre = result.centre_counts
    lines = [
        f"pot centre: {'none found' if centre is None else f'{centre:.1f} counts'} "
        f"from {result.segments_used} straight stretch(es), {result.distance_m:.0f} m",
        f"  spread between stretches {result.spread_tyre_deg:.3f} deg tyre "
        f"(std error {result.standard_error_tyre_deg:.3f} deg), within stretches "
        f"{result.within_segment_std_tyre_deg:.3f} deg",
        *tail_lines(taken, result.accepted, rejected, result.method, verdict),
    ]
    step_result = None
    if verdict.accepted and centre is not None:
        record = item_record(
            method=result.method,
            accepted=True,
            residual_rms=result.spread_tyre_deg,
            residual_max=max(
                (abs(s.centre_counts - centre) for s in result.segments if s.used), default=0.0
            )
            / abs(result.counts_per_tyre_deg),
            residual_unit="deg tyre",
            samples_used=result.accepted,
            rejected=rejected,
            summary=lines[0],
            raw_data=raw_data,
        )
        step_result = StepResult("pot_centre", {"steering.pot_centre_counts": centre}, record)
    return FitReport(
        step="pot-center",
        accepted=step_result is not None,
        lines=tuple(lines),
        reasons=verdict.reasons,
        result=step_result,
        draw=lambda plt: _draw_pot_centre(plt, result),
        figures={
            "pot_centre_counts": centre,
            "segments": result.segments_used,
            "distance_m": result.distance_m,
            "spread_tyre_deg": result.spread_tyre_deg,
        },
    )


def _draw_pot_centre(plt: Any, result: PotCentreResult) -> Any:
    figure, axes = plt.subplots(figsize=(7, 4))
    for segment in result.segments:
        axes.errorbar(
            [0.5 * (segment.start_t_s + segment.end_t_s)],
            [segment.centre_counts],
            yerr=[segment.std_counts],
            fmt="o" if segment.used else "x",
            color="tab:blue" if segment.used else "tab:red",
        )
    if result.centre_counts is not None:
        axes.axhline(result.centre_counts, color="k", lw=1, label="centre")
        axes.legend()
    axes.set_xlabel("time (s)")
    axes.set_ylabel("pot at zero curvature (counts)")
    axes.set_title("pot centre: one estimate per straight stretch")
    return figure
