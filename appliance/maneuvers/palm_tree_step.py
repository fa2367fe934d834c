"""The palm tree done by hand (Stanley et al., Figs. 18-19): the wheel-to-tyre map.

The technician holds the wheel at full left and drives an arc forward (and back, to stay
on the ground available), turns the wheel half a turn right at a standstill, and repeats
to full right. The step takes one sample per GNSS/INS epoch (the fit's jump detection
compares steps between epochs; the control cycle's repeats of one epoch would be steps of
zero), with the wheel angle through the calibration file's pot map, which must therefore
be measured first. The fit (``calibration.palm_tree``) splits the recording into arcs at
every change of the wheel and every discontinuity, fits a circle to each and solves both
tyre angles through the four-wheel-steer model; its map replaces the constant steering
ratio in the file.

By hand it only watches, like the other steps done by hand: engaging aborts it. With
``--auto``, where the vehicle file allows it (``[palm_tree_drive]``, under hold-to-move),
the daemon drives the same arcs at walking pace (``appliance.guidance.palm_tree_drive``)
while the operator walks beside it holding ENGAGE; the step then watches the program's
arcs go by and fits the same samples the same way.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import click
import numpy as np

from appliance.config.calibration import Calibration
from appliance.config.palm_tree_models import palm_tree_drive_problems
from appliance.maneuvers.merge import StepResult
from appliance.maneuvers.report import FitReport, item_record
from appliance.maneuvers.runner import Progress
from appliance.maneuvers.steps import (
    STILL_MPS,
    HandStep,
    bar,
    sample_number,
    sample_speed,
    tail_lines,
)
from calibration.fit_checks import Verdict
from calibration.k_ratio import KRatioFit, fit_k_from_palm_tree
from calibration.palm_tree import PalmTreeFit, PalmTreeParams, fit_palm_tree
from calibration.palm_tree_samples import PalmTreeRecorder

HALF_TURN_RAD = math.pi
# Arc driven per half-turn bin before the bin counts as covered. With a 2 cm fix an arc
# needs about this much for the fit's 0.1 deg tyre-angle precision (the curvature's error
# falls with the square of the arc's length); shorter ones are refused as imprecise.
ARC_NEEDED_M = 8.0
BETWEEN_EPOCHS = "between fixes"  # control cycles that repeat the last epoch: not samples
AUTO_OPTION = click.option(
    "--auto",
    "x_auto",
    is_flag=True,
    help="The daemon drives the arcs at walking pace under hold-to-move, where the vehicle "
    "file allows it ([palm_tree_drive] allowed = true); you walk beside it holding ENGAGE.",
)


class PalmTreeStep(HandStep):
    name = "palm-tree"
    summary = "Arcs at held wheel angles, full left to full right (Fig. 18): the tyre map."
    extra_options = (AUTO_OPTION,)
    instructions: tuple[str, ...] = (
        "palm-tree: on open level ground, at walking pace (below 2 m/s):",
        "  turn the wheel to full LEFT lock at a standstill and hold it there;",
        "  drive forward at least 10 m of arc at a steady walking pace, then reverse",
        "  back over it (or stop);",
        "  stopped, turn the wheel half a turn RIGHT and hold it; drive the next arc;",
        "  and so on, half a turn at a time, to full RIGHT lock. Then stop.",
    )

    def reset(self) -> None:
        self.auto = bool(self.context.options.get("x_auto"))
        self.moves_vehicle = self.auto
        if self.auto:  # a minute or so per arc, and the operator's pauses
            self.default_timeout_s = 3600.0
            self.instructions = self._auto_instructions()
        # The program's phase and arc (0-based) in the last sample, while driven.
        self._palm_phase: str | None = None
        self._palm_arc = 0
        self.recorder = PalmTreeRecorder(bin_width_rad=HALF_TURN_RAD)
        self._last_epoch_s: float | None = None
        self._skipped: dict[str, int] = {}
        self._calibration: Calibration | None = None
        self._speed_mps = 0.0
        self._epochs = 0

    def _converter(self) -> Calibration:
        if self._calibration is None:
            calibration = self.context.calibration
            if calibration is None:
                raise click.UsageError(
                    "the palm tree reads the wheel angle through the pot map: run dbw "
                    "calibrate pot-center and pot-map first (no calibration file given)"
                )
            self._calibration = Calibration.from_file(calibration)
        return self._calibration

    def params(self) -> PalmTreeParams:
        config = self.context.config
        return PalmTreeParams(
            wheelbase_m=config.geometry.wheelbase_m,
            antenna_forward_m=config.positioning.antenna_forward_m,
            antenna_left_m=config.positioning.antenna_left_m,
            characteristic_speed_mps=config.geometry.characteristic_speed_mps,
        )

    def _auto_instructions(self) -> tuple[str, ...]:
        drive = self.context.config.palm_tree_drive
        return (
            "palm-tree --auto: the daemon drives an arc forward at each half turn of the wheel,",
            f"  full left to full right, {drive.arc_m:g} m each at {drive.speed_mps:g} m/s, "
            "turning the wheel only standing,",
            f"  on open level ground (about {2.0 * drive.arc_m:.0f} m clear all round). Press "
            "ENGAGE and keep",
            "  it held, walking beside the vehicle, then SPEED +. Letting go of ENGAGE stops it;",
            "  hold it again to go on. OVERRIDE, a brake tap or the wheel take it back. At the",
            "  end the wheel is centred and the vehicle held standing: OVERRIDE to take over.",
        )

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = super().preconditions(status)
        if self.auto:
            problems += self._auto_problems(status)
        gnss = status.get("gnss")
        if not isinstance(gnss, dict) or not gnss.get("fix") or gnss.get("yaw_deg") is None:
            problems.append(
                "no GNSS/INS fix with a heading: the arcs are fitted to its positions "
                "(is the receiver connected and fixed?)"
            )
        if self.context.calibration is None:
            problems.append("no calibration file: run dbw calibrate pot-center and pot-map first")
        return problems

    def _auto_problems(self, status: Mapping[str, Any]) -> list[str]:
        config = self.context.config
        problems = palm_tree_drive_problems(
            config.palm_tree_drive, config.limits, config.engagement
        )
        if str(status.get("mode")) == "self_check":
            problems.append("the daemon is in SELF_CHECK: the palm tree driven starts from READY")
        speed = status.get("measured_speed_mps")
        if not isinstance(speed, int | float):
            problems.append("no measured speed: is the GNSS/INS receiver fixed?")
        elif abs(speed) > STILL_MPS:
            problems.append(f"the vehicle is moving ({abs(speed):.2f} m/s): stop first")
        return problems

    def update(self, sample: Mapping[str, Any]) -> str | None:
        """Driven, the run is engaged by design: only the program's absence ends it."""
        return self.take(sample) if self.auto else super().update(sample)

    def start_step(self) -> str:
        """Driven: "palm-tree@N" arms the program from its arc N, the first whose half
        turn the samples so far have not covered (by hand or driven: a run begun by hand
        can go on driven), the last when all are."""
        if not self.auto:
            return self.name
        drive = self.context.config.palm_tree_drive
        targets = drive.params(self._converter().valid_wheel_range_rad).wheel_targets_rad
        coverage = self.recorder.coverage_m()
        for index, target in enumerate(targets):
            if coverage.get(round(target / HALF_TURN_RAD) * HALF_TURN_RAD, 0.0) < ARC_NEEDED_M:
                return f"{self.name}@{index}"
        return f"{self.name}@{len(targets) - 1}"

    def _skip(self, reason: str) -> None:
        self._skipped[reason] = self._skipped.get(reason, 0) + 1

    def take(self, sample: Mapping[str, Any]) -> str | None:
        self._take_epoch(sample)
        if not self.auto:
            return None
        phase = sample.get("palm_phase")
        arc = sample.get("palm_arc")
        if phase is None:
            return "the daemon is not driving the palm tree (it restarted?): resume the run"
        self._palm_phase = str(phase)
        self._palm_arc = arc if isinstance(arc, int) else self._palm_arc
        speed = sample_speed(sample)
        self._speed_mps = abs(speed) if speed is not None else self._speed_mps
        return None

    def _take_epoch(self, sample: Mapping[str, Any]) -> None:
        epoch_s = sample_number(sample, "gnss_time_s")
        if epoch_s is None:
            self._skip("no fix")
            return None
        if self._last_epoch_s is not None and epoch_s <= self._last_epoch_s:
            self._skip(BETWEEN_EPOCHS)
            return
        values = [
            sample_number(sample, key)
            for key in ("east_m", "north_m", "yaw_rad", "gnss_speed_mps", "sigma_m")
        ]
        pot = sample_number(sample, "pot_counts")
        if pot is None or any(v is None for v in values):
            self._skip("no reading")
            return
        wheel = self._converter().wheel_rad_from_counts(pot)
        if wheel is None:
            self._skip("pot outside its valid range")
            return
        east, north, yaw, speed, sigma = (float(v) for v in values if v is not None)
        self.recorder.update(epoch_s, east, north, yaw, speed, wheel, sigma)
        self._last_epoch_s = epoch_s
        self._speed_mps = abs(speed)
        self._epochs += 1

    def _bins(self) -> list[float]:
        """Half-turn bins from full left (positive) to full right, as the arcs are driven."""
        low, high = self._converter().valid_wheel_range_rad
        first, last = round(low / HALF_TURN_RAD), round(high / HALF_TURN_RAD)
        return [k * HALF_TURN_RAD for k in range(last, first - 1, -1)]

    def progress(self) -> Progress:
        bins = self._bins()
        coverage = self.recorder.coverage_m()
        driven = [min(ARC_NEEDED_M, coverage.get(b, 0.0)) for b in bins]
        fraction = sum(driven) / (ARC_NEEDED_M * len(bins))
        grid = "".join("#" if d >= ARC_NEEDED_M else ("+" if d > 0.0 else ".") for d in driven)
        program = ""
        if self.auto:
            program = f"; driving arc {self._palm_arc + 1}, {self._palm_phase or 'armed'}"
        return Progress(
            min(1.0, fraction),
            bar(fraction),
            f"arcs left to right [{grid}] ({sum(d >= ARC_NEEDED_M for d in driven)}/"
            f"{len(bins)} half turns, {ARC_NEEDED_M:.0f} m each){program}",
        )

    def complete(self) -> bool:
        """Every half turn driven, and the vehicle stopped (not cut off mid-arc); driven,
        the program done (it stops standing, the wheel centred)."""
        if self.auto:
            return self._palm_phase == "done" and self._speed_mps < STILL_MPS
        coverage = self.recorder.coverage_m()
        covered = all(coverage.get(b, 0.0) >= ARC_NEEDED_M for b in self._bins())
        return covered and self._speed_mps < STILL_MPS

    def fit_result(self) -> PalmTreeFit | None:
        """The fit over the epochs taken so far; None without any."""
        if self._epochs == 0:
            return None
        return fit_palm_tree(self.recorder.samples(), self.params())

    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        self.reset()
        for sample in samples:
            self.take(sample)
        skipped = {k: v for k, v in self._skipped.items() if k != BETWEEN_EPOCHS}
        result = self.fit_result()
        if result is None:
            lines = ("palm tree: no GNSS/INS epoch with a pot reading in the samples",)
            return FitReport(self.name, False, lines, reasons=("no epochs",))
        k_fit = fit_k_from_palm_tree(result) if result.arcs else None
        ratio = (
            self.context.calibration.steering.steering_ratio if self.context.calibration else None
        )
        return palm_tree_report(result, k_fit, len(samples), skipped, raw_data, ratio)


def palm_tree_report(
    result: PalmTreeFit,
    k_fit: KRatioFit | None,
    taken: int,
    skipped: Mapping[str, int],
    raw_data: str | None,
    old_ratio: float | None,
) -> FitReport:
    rejected = {**result.rejected_samples, **skipped}
    fit = result.tyre_map
    wheel = [a.wheel_rad for a in result.arcs]
    lines = [
        f"palm tree: {len(result.arcs)} arcs accepted of "
        f"{len(result.arcs) + sum(result.rejected.values())}"
        + (f", wheel {min(wheel):+.2f}..{max(wheel):+.2f} rad" if wheel else "")
        + (f"; breaks {dict(result.breaks)}" if result.breaks else ""),
    ]
    if fit is not None:
        tyre_map = fit.tyre_map
        ends = (tyre_map.wheel_min_rad, tyre_map.wheel_max_rad)
        lines.append(
            f"  tyre map: centre ratio {tyre_map.centre_ratio:.3f} wheel per tyre"
            + (f" (the file had {old_ratio:.3f})" if old_ratio is not None else "")
            + f", at the measured ends {math.degrees(tyre_map.tyre_rad(ends[0])):+.2f}"
            f"..{math.degrees(tyre_map.tyre_rad(ends[1])):+.2f} deg tyre"
        )
        lines.append(
            f"  residuals {fit.residual_rms_deg:.3f} deg tyre rms, {fit.residual_max_deg:.3f} max"
            f" (limit 0.3); monotonic {'yes' if fit.monotonic else 'NO'}"
        )
    if k_fit is not None and k_fit.arcs_used:
        lines.append(
            f"  rear/front counter-steer from the arcs: k = {k_fit.k:.3f} +- {k_fit.k_sigma:.3f} "
            f"over {k_fit.arcs_used} arcs (dbw calibrate k-ratio confirms it with turns)"
        )
    verdict = Verdict(result.accepted, result.reasons)
    lines += tail_lines(taken, result.samples_used, rejected, result.method, verdict)
    step_result = None
    if result.accepted and fit is not None:
        coeffs = [float(c) for c in fit.tyre_map.coeffs]
        record = item_record(
            method=result.method,
            accepted=True,
            residual_rms=fit.residual_rms_deg,
            residual_max=fit.residual_max_deg,
            residual_unit="deg tyre",
            samples_used=result.samples_used,
            rejected=rejected,
            summary=lines[0],
            raw_data=raw_data,
        )
        values = {
            "steering.wheel_to_tyre_coeffs": coeffs,
            "steering.steering_ratio": 1.0 / coeffs[0],
        }
        step_result = StepResult("palm_tree", values, record)
    return FitReport(
        step="palm-tree",
        accepted=step_result is not None,
        lines=tuple(lines),
        reasons=result.reasons,
        result=step_result,
        draw=lambda plt: _draw_palm_tree(plt, result),
        figures={
            "arcs": len(result.arcs),
            "tyre_coeffs": None if fit is None else list(fit.tyre_map.coeffs),
            "residual_rms_deg": None if fit is None else fit.residual_rms_deg,
            "residual_max_deg": None if fit is None else fit.residual_max_deg,
            "k_from_arcs": None if k_fit is None else k_fit.k,
        },
    )


def _draw_palm_tree(plt: Any, result: PalmTreeFit) -> Any:
    """Fig. 19: the arcs' tyre angles against the wheel angle, and the fitted map."""
    figure, axes = plt.subplots(figsize=(7, 5))
    arcs = result.arcs
    wheel = np.array([a.wheel_rad for a in arcs])
    for attr, sigma, colour, label in (
        ("front_rad", "front_sigma_rad", "tab:blue", "front tyre"),
        ("rear_rad", "rear_sigma_rad", "tab:orange", "rear tyre (counter-steer)"),
    ):
        axes.errorbar(
            wheel,
            np.degrees([getattr(a, attr) for a in arcs]),
            yerr=np.degrees([getattr(a, sigma) for a in arcs]),
            fmt="o",
            color=colour,
            label=label,
        )
    if result.tyre_map is not None and arcs:
        tyre_map = result.tyre_map.tyre_map
        grid = np.linspace(tyre_map.wheel_min_rad, tyre_map.wheel_max_rad, 200)
        axes.plot(grid, np.degrees(tyre_map.tyre_rad(grid)), "k-", lw=1, label="map")
    axes.set_xlabel("steering wheel (rad)")
    axes.set_ylabel("tyre angle (deg)")
    axes.set_title("palm tree: tyre angle per held wheel angle (Stanley et al., Fig. 19)")
    axes.legend()
    return figure
