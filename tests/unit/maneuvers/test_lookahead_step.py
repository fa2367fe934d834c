"""`dbw calibrate lookahead` without the daemon: the runs driven faster than real time on
the simulated vehicle by the daemon's own tuning (:mod:`appliance.sim.tuning_run`), their
samples in the tap's fields, the fit, the merge into ``[guidance.look_ahead]`` and the route
source driving with the merged schedule."""

from __future__ import annotations

from datetime import UTC, datetime
from functools import cache
from pathlib import Path
from typing import Any

from appliance.config import load_config
from appliance.config.calibration import Calibration
from appliance.config.calibration_file import read_calibration_file, write_calibration
from appliance.config.simulated_calibration import simulated_calibration
from appliance.config.tuning_models import LookaheadTuningSettings, TuningCondition
from appliance.core.autopilot import make_source
from appliance.core.route_autopilot import RouteAutopilot
from appliance.guidance.pure_pursuit import LookaheadSchedule
from appliance.maneuvers.lookahead_step import LookaheadStep
from appliance.maneuvers.merge import merge_result
from appliance.maneuvers.steps import StepContext
from appliance.sim.tuning_run import TuningSimResult, run_tuning

BASE = load_config("husky-sim")
# Two of the paper's conditions at both its speeds, three candidates: 12 runs.
SETTINGS = LookaheadTuningSettings(
    conditions=(
        TuningCondition(course="line", offset_m=3.0),
        TuningCondition(course="arc_left", offset_m=-3.0),
    )
)
CONFIG = BASE.model_copy(update={"lookahead_tuning": SETTINGS})
WHEN = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)


@cache
def driven() -> TuningSimResult:
    return run_tuning(CONFIG, SETTINGS)


def tap_samples(result: TuningSimResult) -> list[dict[str, Any]]:
    return [
        {
            "t_s": s.t_s,
            "tune_run": s.run,
            "tune_phase": s.phase,
            "cross_track_m": s.cross_track_m,
            "speed_mps": s.speed_mps,
            "engaged": s.phase in ("runup", "test", "finish"),
        }
        for s in result.samples
    ]


def test_the_runs_choose_the_middle_gain_and_the_route_source_drives_with_it(
    tmp_path: Path,
) -> None:
    result = driven()
    assert result.aborted == 0 and len(result.run_durations_s) == 12
    step = LookaheadStep(StepContext(CONFIG, None))
    report = step.fit(tap_samples(result), "lookahead.jsonl")
    assert report.accepted and report.result is not None, report.lines
    assert report.figures["chosen"] == {"offset_m": 0.5, "gain_s": 0.5, "min_m": 1.5}
    scores = report.figures["scores_m"]
    assert scores[1] < min(scores[0], scores[2])
    path = tmp_path / "cal.toml"
    write_calibration(path, simulated_calibration("husky-sim", created_utc=WHEN))
    assert merge_result(CONFIG, path, report.result).endswith("lookahead merged")
    written = read_calibration_file(path, "husky-sim", simulation_enabled=True)
    assert written.items is not None and written.items.lookahead is not None
    calibration = Calibration.from_file(written)
    assert calibration.guidance_schedule == LookaheadSchedule(0.5, 0.5, 1.5, 12.0)
    source = make_source(CONFIG, calibration)
    assert isinstance(source, RouteAutopilot)
    assert source.params.pursuit.schedule == LookaheadSchedule(0.5, 0.5, 1.5, 12.0)


def test_a_tuning_with_runs_missing_is_refused_and_says_how_many() -> None:
    samples = [s for s in tap_samples(driven()) if s["tune_run"] != 5]
    report = LookaheadStep(StepContext(CONFIG, None)).fit(samples, None)
    assert not report.accepted and report.result is None
    assert any("1 run(s) without a complete test" in r for r in report.reasons)


def test_a_resumed_tuning_starts_from_the_run_its_samples_reached() -> None:
    step = LookaheadStep(StepContext(CONFIG, None))
    for sample in tap_samples(driven()):
        if sample["tune_run"] == 7:
            break
        step.take(sample)
    assert step.start_step() == "lookahead@6"
    assert "run 7/12" in step.progress().detail


def test_the_default_timeout_leaves_the_default_tuning_an_afternoon() -> None:
    """36 runs of about a minute's driving (35 min on the simulated Husky), a minute's drive
    back to a start for each: well inside the command's default, which a hand step's 15
    minutes would not be."""
    step = LookaheadStep(StepContext(BASE, None))
    runs = len(step.params.runs)
    assert runs == 36
    assert step.default_timeout_s >= 2106.0 + 60.0 * runs > 900.0
