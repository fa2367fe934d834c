"""`dbw calibrate lookahead`: line and arc tracking runs into a look-ahead schedule (Fig. 20).

The daemon drives (``appliance.core.route_tuning``): the client arms its runs, and for
each the technician stops where the course has room straight ahead (and to the arc's
side), engages and presses SPEED + up to the run's speed; the route source lays the course
at the vehicle, runs up to speed, steps the course sideways by the run's offset, tracks it
with the run's candidate schedule and stops at its end; the technician disengages, and the
next run is laid where the vehicle next stands. This side files the samples (the anchor's
cross-track error against the course, per run and phase), shows the runs filling, and
fits when every run's test is in (``calibration.lookahead``: the method, rejections,
verdict). The servo's load over the same runs (``calibration.servo_torque``) is kept as
the baseline the schedule was tuned with, and compared with the last tuning's (Fig. 21).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from appliance.config.calibration import LookaheadScheduleCalibration, ServoTorqueBaseline
from appliance.config.tuning_models import room_m
from appliance.core.route_autopilot import tuning_params
from appliance.guidance.lookahead_samples import RunSample, collect_runs
from appliance.maneuvers.merge import StepResult
from appliance.maneuvers.report import FitReport, item_record
from appliance.maneuvers.runner import Progress
from appliance.maneuvers.steps import DrivenStep, bar, sample_number, sample_speed, tail_lines
from calibration.fit_checks import Verdict
from calibration.lookahead import LookaheadChoice, choose_lookahead
from calibration.servo_torque import (
    TorqueComparison,
    TorqueStats,
    compare_torque,
    torque_stats,
)

STANDING_MPS = 0.1
MAX_RATE_GAP_S = 0.2  # consecutive cycles (50 Hz) with a few missed: a rate; longer, a gap


class LookaheadStep(DrivenStep):
    name = "lookahead"
    summary = "Line and arc tracking runs, driven by the daemon: the look-ahead schedule."
    # 36 runs of about a minute, each with a drive back to a start: an afternoon.
    default_timeout_s = 4 * 3600.0
    needed_inputs: tuple[str, ...] = (
        "board.steering",
        "steering.pot",
        "board.throttle",
        "board.brake",
    )

    def reset(self) -> None:
        self.params = tuning_params(self.context.config)
        self.candidates = self.context.config.lookahead_tuning.candidates()
        self._samples: list[RunSample] = []
        # Engaged: t, the wheel (the pot through the calibration), the servo's encoder (for
        # the rate: smoother than the pot, and its offset does not matter there), torque.
        self._torque: list[tuple[float, float, float, float]] = []
        self._run = 0
        self._phase: str | None = None
        self._done = False
        self._speed: float | None = None
        self._finished: set[int] = set()
        self._last_phase: tuple[int | None, str | None] = (None, None)
        self.instructions = self._instructions()

    def _instructions(self) -> tuple[str, ...]:
        tuning = self.context.config.lookahead_tuning
        return (
            f"lookahead: {len(self.params.runs)} runs, each from standing: a clear straight "
            f"{room_m(tuning):.0f} m ahead",
            f"  (an arc run turns {tuning.arc_radius_m:g} m round to its side after "
            f"{tuning.runup_m:g} m). For each run: stop, press ENGAGE, then SPEED + up to",
            "  the run's speed or more (the course caps it). The daemon runs up, moves the",
            "  course sideways by the run's offset and tracks it, and stops at its end:",
            "  disengage (OVERRIDE), drive to the next start, stop. A disengagement before",
            "  the end of a test repeats that run.",
        )

    def preconditions(self, status: Mapping[str, Any]) -> list[str]:
        problems = super().preconditions(status)
        if self.context.config.engagement.autopilot_source != "route":
            problems.append('the look-ahead runs need engagement.autopilot_source = "route"')
        return problems

    def take(self, sample: Mapping[str, Any]) -> str | None:
        phase = sample.get("tune_phase")
        if phase is None:
            return "the daemon is not running the look-ahead runs (it restarted?): resume"
        run = sample.get("tune_run")
        self._phase = str(phase)
        self._done = self._phase == "done"
        if isinstance(run, int):
            if self._last_phase == (run, "test") and self._phase == "finish":
                self._finished.add(run)
            self._run = run
            self._last_phase = (run, self._phase)
        t_s = sample_number(sample, "t_s")
        self._speed = sample_speed(sample)
        if t_s is None:
            return None
        self._samples.append(
            RunSample(
                t_s,
                run if isinstance(run, int) else None,
                self._phase,
                sample_number(sample, "cross_track_m"),
                self._speed,
            )
        )
        wheel = sample_number(sample, "steer_wheel_rad")
        encoder = sample_number(sample, "servo_position_rad")
        torque = sample_number(sample, "servo_torque_nm")
        engaged = bool(sample.get("engaged"))
        if engaged and wheel is not None and encoder is not None and torque is not None:
            self._torque.append((t_s, wheel, encoder, torque))
        return None

    def progress(self) -> Progress:
        runs = len(self.params.runs)
        fraction = 1.0 if self._done else len(self._finished) / runs
        run = self.params.runs[min(self._run, runs - 1)]
        return Progress(
            fraction,
            bar(fraction),
            f"run {min(self._run + 1, runs)}/{runs} {self._phase or 'armed'}: "
            f"{run.describe()}; tests in {len(self._finished)}",
        )

    def start_step(self) -> str:
        """A resumed run goes on from the run its samples stopped at."""
        return f"lookahead@{self._run}" if 0 < self._run < len(self.params.runs) else "lookahead"

    def complete(self) -> bool:
        return self._done and self._speed is not None and abs(self._speed) < STANDING_MPS

    def fit(self, samples: Sequence[Mapping[str, Any]], raw_data: str | None) -> FitReport:
        self.reset()
        for sample in samples:
            self.take(sample)
        collected = collect_runs(self._samples, self.params, self.candidates)
        missing = len(self.params.runs) - len(collected.complete)
        torque = _torque(self._torque)
        baseline = self.context.calibration
        before = None
        if baseline is not None and baseline.guidance is not None:
            before = baseline.guidance.servo_torque
        if not collected.runs:
            return FitReport(
                "lookahead", False, ("look-ahead: no run's test is in",), ("no tests",)
            )
        choice = choose_lookahead(collected.runs, self.context.config.lookahead_tuning.fit_params())
        comparison = None
        if before is not None and isinstance(torque, TorqueStats):
            comparison = compare_torque(before.stats(), torque)
        used = sum(1 for s in self._samples if s.phase == "test" and s.run in collected.complete)
        return lookahead_report(
            choice, collected.rejected, missing, torque, comparison, used, raw_data
        )


def _torque(rows: list[tuple[float, float, float, float]]) -> TorqueStats | str:
    """The servo's load over the engaged samples: the rate between consecutive cycles only
    (not across the gap between two runs)."""
    if len(rows) < 3:
        return "no servo telemetry while engaged"
    t, wheel, encoder, torque = (np.array(c) for c in zip(*rows, strict=True))
    dt = np.diff(t)
    pairs = (dt > 0.0) & (dt < MAX_RATE_GAP_S)
    rate = np.diff(encoder)[pairs] / dt[pairs]
    try:
        return torque_stats(wheel[1:][pairs], rate, torque[1:][pairs])
    except ValueError as exc:
        return str(exc)


def lookahead_report(
    choice: LookaheadChoice,
    rejected: Mapping[str, int],
    missing: int,
    torque: TorqueStats | str,
    comparison: TorqueComparison | None,
    used: int,
    raw_data: str | None,
) -> FitReport:
    chosen = choice.chosen
    reasons = list(choice.reasons)
    if missing:
        reasons.append(f"{missing} run(s) without a complete test: resume to drive them")
    lines = [
        "look-ahead: "
        + (
            "no candidate usable"
            if chosen is None
            else f"L(v) = clamp({chosen.offset_m:g} + {chosen.gain_s:g} s x v, "
            f"{chosen.min_m:g}, {chosen.max_m:g}) m"
        ),
    ]
    for row in choice.per_speed:
        lines.append(
            f"  at {row.speed_mps:.2f} m/s: look-ahead {row.chosen_lookahead_m:.2f} m, RMS "
            f"{100 * row.chosen_rms_m:.1f} cm, oscillation {100 * row.chosen_oscillation_m:.1f} "
            f"cm, overshoot {100 * row.chosen_worst_overshoot_m:.0f} cm, capture "
            f"{row.chosen_mean_capture_s:.1f} s (best there alone: {row.best_lookahead_m:.2f} m)"
        )
    for scored in choice.candidates:
        c = scored.candidate
        score = f"{100 * scored.score_m:.2f} cm" if math.isfinite(scored.score_m) else "--"
        lines.append(
            f"  candidate {c.offset_m:g} + {c.gain_s:g} s x v: score {score}"
            + (f" ({scored.reason})" if scored.reason else "")
        )
    if isinstance(torque, str):
        lines.append(f"  servo torque: not measured ({torque})")
    else:
        c0, c_wheel, c_rate = torque.coeffs
        lines.append(
            f"  servo load: {c0:.2f} + {c_wheel:.2f} |wheel| + {c_rate:.2f} |rate| N m, "
            f"stalls {100 * torque.stall_fraction:.1f} %"
        )
    if comparison is not None:
        lines.append(
            f"  against the last tuning's servo: {100 * comparison.relative_change:+.0f} % "
            + ("(changed: this tuning replaces the old one)" if comparison.retune else "(same)")
        )
    all_rejected = {**rejected, **choice.rejected}
    scores = [s.score_m for s in choice.candidates if s.usable]
    verdict = Verdict.from_reasons(reasons)
    lines += tail_lines(used, used, all_rejected, choice.method, verdict)
    step_result = None
    if verdict.accepted and chosen is not None:
        values: dict[str, Any] = {
            "guidance.look_ahead": LookaheadScheduleCalibration(
                offset_m=chosen.offset_m,
                gain_s=chosen.gain_s,
                min_m=chosen.min_m,
                max_m=chosen.max_m if math.isfinite(chosen.max_m) else 100.0,
            ).model_dump()
        }
        if isinstance(torque, TorqueStats):
            values["guidance.servo_torque"] = ServoTorqueBaseline.of(torque).model_dump()
        best = min(scores)
        worst_rms = max(r.rms_m for c in choice.candidates if c.candidate == chosen for r in c.runs)
        record = item_record(
            method=choice.method,
            accepted=True,
            residual_rms=best,
            residual_max=worst_rms,
            residual_unit="m",
            samples_used=used,
            rejected=dict(all_rejected),
            summary=lines[0],
            raw_data=raw_data,
        )
        step_result = StepResult("lookahead", values, record)
    return FitReport(
        step="lookahead",
        accepted=step_result is not None,
        lines=tuple(lines),
        reasons=verdict.reasons,
        result=step_result,
        draw=lambda plt: _draw(plt, choice),
        figures={
            "chosen": None
            if chosen is None
            else {"offset_m": chosen.offset_m, "gain_s": chosen.gain_s, "min_m": chosen.min_m},
            "scores_m": [s.score_m if s.usable else None for s in choice.candidates],
            "retune": None if comparison is None else comparison.retune,
        },
    )


def _draw(plt: Any, choice: LookaheadChoice) -> Any:
    """Fig. 20's question: the error and the weave against the look-ahead, per speed."""
    speeds = sorted({r.speed_mps for c in choice.candidates for r in c.runs})
    figure, axes = plt.subplots(1, len(speeds), figsize=(5.5 * len(speeds), 4.2), squeeze=False)
    for ax, speed in zip(axes[0], speeds, strict=True):
        rows = []
        for scored in choice.candidates:
            at = [r for r in scored.runs if r.speed_mps == speed and r.captured]
            if at:
                rows.append(
                    (
                        at[0].lookahead_m,
                        float(np.mean([r.rms_m for r in at])),
                        float(np.mean([r.oscillation_m for r in at])),
                        float(np.mean([r.score_m for r in at])),
                    )
                )
        rows.sort()
        if rows:
            table = np.array(rows)
            ax.plot(table[:, 0], 100 * table[:, 1], "o-", label="RMS after capture")
            ax.plot(table[:, 0], 100 * table[:, 2], "s-", label="oscillation")
            ax.plot(table[:, 0], 100 * table[:, 3], "^-", label="score")
        if choice.chosen is not None:
            ax.axvline(choice.chosen.lookahead_m(speed), color="k", ls="--", label="chosen")
        ax.set_xlabel("look-ahead (m)")
        ax.set_ylabel("cross-track (cm)")
        ax.set_title(f"{speed:.2f} m/s")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    figure.tight_layout()
    return figure
