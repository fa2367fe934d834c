"""The counter-steer ratio k, confirmed by steady turns (Stanley et al.: "extracting the
value from a palm tree test using vehicle heading and wheel angle, then adjusting the
value based on simple turning tests").

The technician drives steady circles at a held wheel angle, at least one to each side.
Each turn's yaw rate over its speed is the path curvature, which the four-wheel
counter-steer model turns into k given the front tyre angle from the palm tree's map
(``calibration.k_ratio.fit_k_from_turns``). The palm tree's own arcs give k a second way
(both tyre angles per arc); the step refits them from the palm tree's samples file (named
in the calibration's ``[items.palm_tree]``, or ``--palm-tree FILE``) and merges k only
when the two agree within 2 %, as their inverse-variance mean: a larger difference means
one of them, or the tyre map, is off, and neither number should steer the vehicle.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import click
import numpy as np

from appliance.config.calibration import Calibration
from appliance.maneuvers.merge import StepResult
from appliance.maneuvers.palm_tree_step import PalmTreeStep
from appliance.maneuvers.report import FitReport, item_record
from appliance.maneuvers.runner import Progress
from appliance.maneuvers.samples_file import SamplesFileError, read_samples_file
from appliance.maneuvers.steps import STILL_MPS, HandStep, bar, sample_number, sample_speed
from calibration.k_ratio import (
    KRatioFit,
    SteadyTurn,
    TurningKFit,
    TurnParams,
    centre_speed_ratio,
    check_k,
    fit_k_from_palm_tree,
    fit_k_from_turns,
)
from calibration.tyre_map import TyreMap

HOLD_TOLERANCE_RAD = 0.05  # the wheel held: as the fits' own tolerance
SETTLE_S = 3.0  # after the wheel is set and the vehicle moves: getting up to a steady pace
TURN_NEEDED_S = 8.0  # of steady turning per side before the side counts as covered
MIN_TURN_WHEEL_RAD = 1.5  # a turn: the front tyre well past the fit's 5 deg
MIN_SPEED_MPS = TurnParams.min_speed_mps  # below it the turn's yaw rate is noise
STEADY_FRACTION = 0.05  # the speed within 5 % of the turn's median: a steady turn


class KRatioStep(HandStep):
    name = "k-ratio"
    summary = "Steady circles at a held wheel angle, left and right: k, checked by the turns."
    extra_options = (
        click.option(
            "--palm-tree",
            "x_palm_tree_samples",
            type=click.Path(dir_okay=False),
            help="The palm tree's samples file (default: the one its calibration item names).",
        ),
    )
    instructions: tuple[str, ...] = (
        "k-ratio: on open level ground, at a steady walking pace:",
        "  hold the wheel a turn or more LEFT and drive a steady circle for 15 s;",
        "  stop; the same to the RIGHT. The palm tree must have been merged before.",
    )

    def reset(self) -> None:
        self._calibration: Calibration | None = None
        self._runs: list[list[tuple[float, float, float, float]]] = []  # t, heading, v, wheel
        self._last_epoch_s: float | None = None
        self._speed_mps = 0.0

    def _converter(self) -> Calibration:
        if self._calibration is None:
            calibration = self.context.calibration
            if calibration is None or calibration.steering.wheel_to_tyre_coeffs is None:
                raise click.UsageError(
                    "k from turns needs the palm tree's tyre map: run dbw calibrate "
                    "palm-tree first (and restart the daemon)"
                )
            self._calibration = Calibration.from_file(calibration)
        return self._calibration

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = super().preconditions(status)
        gnss = status.get("gnss")
        if not isinstance(gnss, dict) or not gnss.get("fix") or gnss.get("yaw_deg") is None:
            problems.append("no GNSS/INS fix with a heading: the turns' yaw rate is its heading's")
        calibration = self.context.calibration
        if calibration is None or calibration.steering.wheel_to_tyre_coeffs is None:
            problems.append("no tyre map in the calibration: run dbw calibrate palm-tree first")
        return problems

    def take(self, sample: Mapping[str, Any]) -> str | None:
        epoch_s = sample_number(sample, "gnss_time_s")
        if epoch_s is None or (self._last_epoch_s is not None and epoch_s <= self._last_epoch_s):
            return None  # between epochs: the heading has not moved on
        yaw = sample_number(sample, "yaw_rad")
        speed = sample_speed(sample)
        pot = sample_number(sample, "pot_counts")
        if yaw is None or speed is None or pot is None:
            return None
        wheel = self._converter().wheel_rad_from_counts(pot)
        if wheel is None:
            return None
        self._last_epoch_s = epoch_s
        self._speed_mps = abs(speed)
        run = self._runs[-1] if self._runs else None
        if run is None or abs(wheel - run[0][3]) > HOLD_TOLERANCE_RAD:
            self._runs.append([(epoch_s, yaw, speed, wheel)])
        else:
            run.append((epoch_s, yaw, speed, wheel))
        return None

    def turns(self) -> list[SteadyTurn]:
        """Every held-wheel run driven forward, from SETTLE_S after it got moving."""
        turns = []
        for run in self._runs:
            rows = np.array(run)
            moving = np.flatnonzero(rows[:, 2] >= MIN_SPEED_MPS)
            if abs(rows[0, 3]) < MIN_TURN_WHEEL_RAD or moving.size == 0:
                continue
            start_s = rows[moving[0], 0] + SETTLE_S
            settled = rows[rows[:, 0] >= start_s]
            steady = _longest_steady(settled)
            if steady.shape[0] >= 10:
                turns.append(SteadyTurn(steady[:, 0], steady[:, 1], steady[:, 2], steady[:, 3]))
        return turns

    def _covered_s(self) -> tuple[float, float]:
        left = right = 0.0
        for turn in self.turns():
            seconds = float(turn.t_s[-1] - turn.t_s[0])
            if float(np.mean(turn.wheel_rad)) > 0.0:
                left += seconds
            else:
                right += seconds
        return left, right

    def progress(self) -> Progress:
        left, right = self._covered_s()
        fraction = (min(left, TURN_NEEDED_S) + min(right, TURN_NEEDED_S)) / (2 * TURN_NEEDED_S)
        return Progress(
            fraction,
            bar(fraction),
            f"steady turning: left {left:.0f}/{TURN_NEEDED_S:.0f} s, "
            f"right {right:.0f}/{TURN_NEEDED_S:.0f} s",
        )

    def complete(self) -> bool:
        left, right = self._covered_s()
        return min(left, right) >= TURN_NEEDED_S and self._speed_mps < STILL_MPS

    def _at_the_centre(self, turn: SteadyTurn, tyre_map: TyreMap, prior_k: float) -> SteadyTurn:
        """The turn with the antenna's speed made the geometric centre's (the model's
        curvature is the centre's), through the sideslip the model gives for ``prior_k``
        (the palm tree's): a few per mille of k for an antenna metres off the centre."""
        positioning = self.context.config.positioning
        t = turn.t_s - turn.t_s[0]
        yaw_rate = float(np.polyfit(t, np.unwrap(turn.heading_rad), 1)[0])
        front = float(tyre_map.tyre_rad(float(np.mean(turn.wheel_rad))))
        beta = math.atan((math.tan(front) - math.tan(prior_k * front)) / 2.0)
        try:
            ratio = centre_speed_ratio(
                float(np.mean(turn.speed_mps)),
                yaw_rate,
                positioning.antenna_forward_m,
                positioning.antenna_left_m,
                beta,
            )
        except ValueError:
            return turn  # refused by the fit's own checks (no k in range) instead
        return SteadyTurn(turn.t_s, turn.heading_rad, turn.speed_mps * ratio, turn.wheel_rad)

    def _palm_tree_k(self) -> tuple[KRatioFit | None, str]:
        """The palm tree's arcs' k, refitted from its samples; None and why where not."""
        path = self.context.options.get("x_palm_tree_samples")
        calibration = self.context.calibration
        if not path and calibration is not None and calibration.items is not None:
            record = calibration.items.palm_tree
            path = record.raw_data if record is not None else None
        if not path:
            return None, "no palm tree samples file named (give --palm-tree FILE)"
        try:
            samples = read_samples_file(Path(str(path)), self.context.config.name)
        except SamplesFileError as exc:
            return None, f"the palm tree's samples cannot be read: {exc}"
        if samples.step != PalmTreeStep.name:
            return None, f"{path} holds {samples.step!r} samples, not the palm tree's"
        palm = PalmTreeStep(self.context)
        for sample in samples.samples:
            palm.take(sample)
        fit = palm.fit_result()
        if fit is None or not fit.arcs:
            return None, f"{path}: no palm tree arcs to take k from"
        return fit_k_from_palm_tree(fit), str(path)

    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        self.reset()
        for sample in samples:
            self.take(sample)
        turns = self.turns()
        if not turns:
            lines = ("k-ratio: no steady turn at a held wheel angle in the samples",)
            return FitReport(self.name, False, lines, reasons=("no steady turns",))
        calibration = self._converter()
        low, high = calibration.valid_wheel_range_rad
        coeffs = calibration.wheel_to_tyre_coeffs
        assert coeffs is not None  # _converter() refuses a calibration without
        config = self.context.config
        params = TurnParams(
            wheelbase_m=config.geometry.wheelbase_m,
            characteristic_speed_mps=config.geometry.characteristic_speed_mps,
        )
        tyre_map = TyreMap(coeffs, low, high)
        palm, source = self._palm_tree_k()
        prior_k = palm.k if palm is not None else config.geometry.counter_steer_ratio_k
        centred = [self._at_the_centre(turn, tyre_map, prior_k) for turn in turns]
        turning = fit_k_from_turns(centred, tyre_map, params)
        used = {round(t.wheel_rad, 9) for t in turning.turns}
        epochs = sum(t.t_s.size for t in turns if round(float(np.mean(t.wheel_rad)), 9) in used)
        return k_ratio_report(turning, palm, source, epochs, raw_data)


def k_ratio_report(
    turning: TurningKFit,
    palm: KRatioFit | None,
    palm_source: str,
    epochs_used: int,
    raw_data: str | None,
) -> FitReport:
    lines = [
        f"k ratio from {len(turning.turns)} steady turn(s): "
        + (f"{turning.k:.4f} +- {turning.k_sigma:.4f}" if turning.turns else "none"),
    ]
    for turn in turning.turns:
        lines.append(
            f"  turn at {turn.wheel_rad:+.2f} rad wheel ({math.degrees(turn.front_rad):+.2f} deg "
            f"tyre), {turn.speed_mps:.2f} m/s: k {turn.k:.4f} +- {turn.k_sigma:.4f}"
        )
    reasons = list(turning.reasons)
    if palm is None:
        reasons.append(f"no palm tree k to check against: {palm_source}")
    else:
        lines.append(
            f"  palm tree arcs ({palm_source}): k {palm.k:.4f} +- {palm.k_sigma:.4f} "
            f"over {palm.arcs_used} arcs"
        )
        reasons += [f"palm tree: {r}" for r in palm.reasons]
        if turning.turns:
            check = check_k(palm, turning)
            reasons += list(check.reasons)
            lines.append(
                f"  the two differ by {100 * check.relative_difference:+.2f} % (limit 2 %)"
            )
    k = math.nan
    sigma = math.inf
    if palm is not None and turning.turns:
        weights = (1.0 / palm.k_sigma**2, 1.0 / turning.k_sigma**2)
        k = (weights[0] * palm.k + weights[1] * turning.k) / sum(weights)
        sigma = 1.0 / math.sqrt(sum(weights))
    accepted = not reasons and math.isfinite(k)
    rejected = dict(turning.rejected)
    outcome = "ACCEPTED" if accepted else "REFUSED: " + "; ".join(reasons)
    lines += [
        f"  k = {k:.4f} +- {sigma:.4f} (both, inverse-variance weighted)",
        f"  turns rejected: {', '.join(f'{r} {n}' for r, n in rejected.items()) or 'none'}",
        f"  method: {turning.method}; checked against the palm tree's arcs",
        f"  verdict: {outcome}",
    ]
    step_result = None
    if accepted:
        residuals = [abs(t.k - k) for t in turning.turns]
        record = item_record(
            method=f"{turning.method}; palm tree arcs: {palm.method if palm else ''}",
            accepted=True,
            residual_rms=float(np.sqrt(np.mean(np.square(residuals)))),
            residual_max=max(residuals),
            residual_unit="k",
            samples_used=epochs_used,
            rejected=rejected,
            summary=lines[0],
            raw_data=raw_data,
        )
        step_result = StepResult("k_ratio", {"counter_steer.k_ratio": k}, record)
    return FitReport(
        step="k-ratio",
        accepted=step_result is not None,
        lines=tuple(lines),
        reasons=tuple(reasons),
        result=step_result,
        figures={
            "k": k if math.isfinite(k) else None,
            "k_turns": turning.k if turning.turns else None,
            "k_palm_tree": None if palm is None else palm.k,
            "turns": len(turning.turns),
        },
    )


def _longest_steady(rows: np.ndarray) -> np.ndarray:
    """The longest block of consecutive epochs within STEADY_FRACTION of the median speed:
    the turn without its braking at the end (a slowing vehicle's heading rate is not
    its steady curvature times the mean speed)."""
    if rows.shape[0] == 0:
        return rows
    median = float(np.median(rows[:, 2]))
    if median < MIN_SPEED_MPS:
        return rows[:0]
    inside = np.abs(rows[:, 2] - median) <= STEADY_FRACTION * median
    best, best_len, start = 0, 0, None
    for i, flag in enumerate([*inside.tolist(), False]):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            if i - start > best_len:
                best, best_len = start, i - start
            start = None
    return rows[best : best + best_len]
