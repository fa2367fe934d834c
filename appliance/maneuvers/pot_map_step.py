"""The pot-map step done by hand (Stanley et al., Fig. 17): pot counts to wheel angle.

The technician turns the wheel lock to lock in half turns with rests, the vehicle
standing; the servo's encoder, released, measures the wheel. The fit
(``calibration.pot_map``) decides; this module translates the tapped samples into it and
its result into the calibration file.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import click
import numpy as np

from appliance.maneuvers.merge import StepResult
from appliance.maneuvers.report import FitReport, item_record
from appliance.maneuvers.runner import Progress
from appliance.maneuvers.steps import (
    MOVING_S,
    STILL_MPS,
    HandStep,
    bar,
    counts_text,
    sample_number,
    sample_speed,
    tail_lines,
    with_unread,
)
from calibration.pot_map import PotMapAccumulator, PotMapCoverage, PotMapResult, wheel_rad_at

STILL_WHEEL_RAD = 0.01  # the wheel resting: the encoder moves less than this
LOCK_TOLERANCE_RAD = 0.3  # back at the lock the sweep started from
FINAL_REST_S = 1.0


class PotMapStep(HandStep):
    name = "pot-map"
    summary = "Stationary: turn the wheel lock to lock in half turns (Fig. 17): the pot map."
    extra_options = (
        click.option(
            "--steering-ratio",
            "x_steering_ratio",
            type=click.FloatRange(min=1.0, max=60.0),
            help="Steering-wheel rad per tyre rad, where no calibration gives it.",
        ),
    )
    # A remounted pot reads outside the old calibration's range near the locks: the
    # daemon calls the steering unknown and holds its safe state (brake on, standing
    # still is what this step wants anyway); the map being measured is the cure.
    tolerated_faults = frozenset({"steering_unknown"})
    instructions: tuple[str, ...] = (
        "pot-map: with the vehicle standing still, engine running, servo released:",
        "  turn the steering wheel to full RIGHT lock and let it rest 2 s;",
        "  then turn it LEFT half a turn at a time, resting 2 s after each, to full left;",
        "  then back RIGHT the same way, half turns with rests, to full right.",
    )

    def reset(self) -> None:
        self.accumulator = PotMapAccumulator()
        self._coverage_rows = -1
        self._coverage = self.accumulator.coverage()
        self._rows = 0
        self._encoder_rad: float | None = None
        self._still_since_s = math.inf
        self._moving_since_s = math.inf
        self._last_s = -math.inf

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = super().preconditions(status)
        speed = status.get("measured_speed_mps")
        if not isinstance(speed, int | float):
            problems.append("the vehicle's speed is unknown: the pot map is measured standing")
        elif abs(speed) > STILL_MPS:
            problems.append(f"the vehicle is moving ({speed:.2f} m/s): stop it first")
        return problems

    def take(self, sample: Mapping[str, Any]) -> str | None:
        speed = sample_speed(sample)
        pot = sample_number(sample, "pot_counts")
        encoder = sample_number(sample, "servo_position_rad")
        t_s = sample_number(sample, "t_s")
        if t_s is None:
            return None
        if speed is None or abs(speed) <= STILL_MPS:
            self._moving_since_s = math.inf
        else:
            self._moving_since_s = min(self._moving_since_s, t_s)
            if t_s - self._moving_since_s >= MOVING_S:
                return f"the vehicle moved ({speed:.2f} m/s): the pot map is measured standing"
        if pot is None or encoder is None:
            return None
        # By hand nothing is commanded: the wheel is where the hands hold it.
        command = sample_number(sample, "steer_setpoint_rad")
        self.accumulator.update(t_s, encoder, pot, encoder if command is None else command)
        self._rows += 1
        if self._encoder_rad is None or abs(encoder - self._encoder_rad) > STILL_WHEEL_RAD:
            self._encoder_rad, self._still_since_s = encoder, t_s
        self._last_s = t_s
        return None

    def coverage(self) -> PotMapCoverage:
        if self._coverage_rows != self._rows:
            self._coverage = self.accumulator.coverage()
            self._coverage_rows = self._rows
        return self._coverage

    def progress(self) -> Progress:
        c = self.coverage()
        need = self.accumulator.params.min_pauses_per_direction
        fraction = (min(c.pauses_up, need) + min(c.pauses_down, max(need, c.pauses_up))) / (
            need + max(need, c.pauses_up)
        )
        span = (
            f", encoder {c.encoder_min_rad:+.1f}..{c.encoder_max_rad:+.1f} rad"
            if c.encoder_min_rad is not None
            else ""
        )
        return Progress(
            fraction, bar(fraction), f"rests: {c.pauses_up} going left, {c.pauses_down} back{span}"
        )

    def complete(self) -> bool:
        """Back at full right and resting there, with as many rests on the way back as
        on the way out (the rest at full right before the sweep counts as one back)."""
        c = self.coverage()
        need = self.accumulator.params.min_pauses_per_direction
        at_right_lock = (
            c.encoder_min_rad is not None
            and self._encoder_rad is not None
            and abs(self._encoder_rad - c.encoder_min_rad) < LOCK_TOLERANCE_RAD
            and self._last_s - self._still_since_s >= FINAL_REST_S
        )
        return c.pauses_up >= need and c.pauses_down >= c.pauses_up and at_right_lock

    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        self.reset()
        for sample in samples:
            self.take(sample)
        calibration = self.context.calibration
        centre = None if calibration is None else calibration.steering.pot_centre_counts
        centre = self.context.options.get("x_pot_centre_counts", centre)
        result = self.accumulator.fit(self.steering_ratio(), centre)
        calibration = self.context.calibration
        had_tyre_map = (
            calibration is not None and calibration.steering.wheel_to_tyre_coeffs is not None
        )
        return pot_map_report(result, len(samples), raw_data, self.steering_ratio(), had_tyre_map)


def pot_map_report(
    result: PotMapResult,
    taken: int,
    raw_data: str | None,
    steering_ratio: float,
    had_tyre_map: bool = False,
) -> FitReport:
    """The pot map's report. A new pot map redefines the wheel angle, so a palm tree's
    tyre map measured through the old one no longer holds: merging drops it (the constant
    ratio stands in) and the report says to drive the palm tree again."""
    verdict = result.verdict
    rejected = with_unread(result.rejected, taken, result.samples)
    lines = [
        f"pot map: {sum(1 for p in result.pauses if p.used)} rests used of "
        f"{len(result.pauses)} and {result.motion_samples} samples turning, counts "
        f"{result.usable_min_counts:.0f}..{result.usable_max_counts:.0f}"
        f" (valid {result.pot_valid_min_counts}..{result.pot_valid_max_counts})",
        f"  centre {counts_text(result.pot_centre_counts)} ({result.centre_from}), backlash "
        f"{abs(result.backlash_rad):.4f} rad of wheel (+-{result.backlash_std_error_rad:.4f}), "
        f"monotonic {'yes' if result.monotonic else 'NO'}",
        f"  residuals {result.residual_rms_tyre_deg:.3f} deg tyre rms, "
        f"{result.residual_max_tyre_deg:.3f} max",
        *tail_lines(taken, result.accepted, rejected, result.method, verdict),
    ]
    step_result = None
    if verdict.accepted and result.pot_centre_counts is not None:
        values: dict[str, Any] = {
            "steering.pot_centre_counts": result.pot_centre_counts,
            "steering.pot_to_wheel_coeffs": list(result.pot_to_wheel_coeffs),
            "steering.pot_valid_min_counts": result.pot_valid_min_counts,
            "steering.pot_valid_max_counts": result.pot_valid_max_counts,
            "steering.steering_ratio": steering_ratio,
            "steering.wheel_to_tyre_coeffs": None,
        }
        if had_tyre_map:
            lines.append(
                "  the palm tree's tyre map was measured through the old pot map: merging "
                "drops it; drive dbw calibrate palm-tree again"
            )
        record = item_record(
            method=result.method,
            accepted=True,
            residual_rms=result.residual_rms_tyre_deg,
            residual_max=result.residual_max_tyre_deg,
            residual_unit="deg tyre",
            samples_used=result.accepted,
            rejected=rejected,
            summary=lines[0],
            raw_data=raw_data,
        )
        step_result = StepResult("pot_map", values, record)
    return FitReport(
        step="pot-map",
        accepted=step_result is not None,
        lines=tuple(lines),
        reasons=verdict.reasons,
        result=step_result,
        draw=lambda plt: _draw_pot_map(plt, result),
        figures={
            "pot_centre_counts": result.pot_centre_counts,
            "backlash_rad": result.backlash_rad,
            "residual_rms_tyre_deg": result.residual_rms_tyre_deg,
            "residual_max_tyre_deg": result.residual_max_tyre_deg,
            "valid_counts": [result.pot_valid_min_counts, result.pot_valid_max_counts],
        },
    )


def _draw_pot_map(plt: Any, result: PotMapResult) -> Any:
    """Fig. 17: the rests (pot against encoder, by sweep direction) and the fitted map."""
    figure, axes = plt.subplots(figsize=(7, 5))
    zero = result.encoder_at_centre_rad
    for direction, colour, label in ((1, "tab:blue", "turning left"), (-1, "tab:orange", "back")):
        rests = [p for p in result.pauses if p.direction == direction]
        axes.scatter(
            [p.pot_counts for p in rests],
            [p.encoder_rad - zero for p in rests],
            c=colour,
            marker="o",
            label=label,
        )
    if result.pot_centre_counts is not None:
        counts = np.linspace(result.pot_valid_min_counts, result.pot_valid_max_counts, 200)
        wheel = wheel_rad_at(result.pot_to_wheel_coeffs, counts - result.pot_centre_counts)
        axes.plot(counts, wheel, "k-", lw=1, label="map")
    axes.set_xlabel("pot (counts)")
    axes.set_ylabel("steering wheel from the encoder (rad)")
    axes.set_title("pot map (Stanley et al., Fig. 17)")
    axes.legend()
    return figure
