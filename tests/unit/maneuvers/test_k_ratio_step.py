"""The k-ratio step: steady turns on the vehicle model, checked against the palm tree's
arcs refitted from its samples file; the truth is the model's k."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from appliance.config.calibration import CalibrationFile
from appliance.maneuvers.k_ratio_step import KRatioStep
from appliance.maneuvers.merge import _apply
from appliance.maneuvers.palm_tree_step import PalmTreeStep
from appliance.maneuvers.samples_file import SamplesWriter, header
from appliance.maneuvers.steps import StepContext
from tests.unit.calibration.vehicle_runs import TRUE_K, Driver, GnssErrors, true_tyre_rad
from tests.unit.maneuvers.test_palm_tree_step import (
    CALIBRATION,
    CONFIG,
    CONTEXT,
    as_tap_samples,
    tap_samples,
)

TURNS_RAD = (2 * math.pi, -2 * math.pi)


def turn_samples(wheels_rad: tuple[float, ...] = TURNS_RAD) -> list[dict[str, Any]]:
    """Steady circles at 1.5 m/s, one per wheel angle, stopped between."""
    driver = Driver(GnssErrors(jump_m=0.0), seed=5)
    for wheel in wheels_rad:
        driver.front_rad = float(true_tyre_rad(wheel))
        driver.hold(2.0)
        driver.drive(1.5, 25.0)
        driver.hold(1.0)
    return as_tap_samples(driver.recorder.rows)


@pytest.fixture(scope="module")
def with_palm_tree(tmp_path_factory: pytest.TempPathFactory) -> tuple[CalibrationFile, Path]:
    """The calibration after the palm tree merged, its samples file where it says."""
    path = tmp_path_factory.mktemp("palm") / "palm-tree.jsonl"
    samples = tap_samples()
    writer = SamplesWriter(path, header("palm-tree", CONFIG.name, "test", "2026-12-05T00:00:00Z"))
    writer.append(samples)
    writer.close()
    report = PalmTreeStep(CONTEXT).fit(samples, raw_data=str(path))
    assert report.result is not None, report.lines
    data = CALIBRATION.model_dump()
    _apply(data, report.result)
    return CalibrationFile.model_validate(data), path


def test_the_turns_confirm_the_palm_trees_k(with_palm_tree: tuple[CalibrationFile, Path]) -> None:
    calibration, _ = with_palm_tree
    report = KRatioStep(StepContext(CONFIG, calibration)).fit(turn_samples(), raw_data=None)
    assert report.accepted, report.lines
    assert report.figures["turns"] == 2
    assert abs(report.figures["k_turns"] - TRUE_K) < 0.02 * TRUE_K
    assert report.result is not None
    k = report.result.values["counter_steer.k_ratio"]
    assert abs(k - TRUE_K) < 0.02 * TRUE_K
    merged = CalibrationFile.model_validate(
        {**calibration.model_dump(), "counter_steer": {"k_ratio": k}}
    )
    assert merged.counter_steer is not None


def test_without_the_palm_trees_samples_k_is_refused_and_says_why(
    with_palm_tree: tuple[CalibrationFile, Path], tmp_path: Path
) -> None:
    calibration, _ = with_palm_tree
    options = {"x_palm_tree_samples": str(tmp_path / "gone.jsonl")}
    report = KRatioStep(StepContext(CONFIG, calibration, options)).fit(turn_samples(), None)
    assert not report.accepted
    assert any("palm tree" in r and "cannot be read" in r for r in report.reasons), report.reasons


def test_one_side_only_is_not_complete(with_palm_tree: tuple[CalibrationFile, Path]) -> None:
    calibration, _ = with_palm_tree
    step = KRatioStep(StepContext(CONFIG, calibration))
    for sample in turn_samples((math.pi,)):
        step.update(sample)
    assert not step.complete()
    assert "right 0/" in step.progress().detail


def test_without_a_tyre_map_the_step_refuses_before_it_starts() -> None:
    step = KRatioStep(StepContext(CONFIG, CALIBRATION))
    problems = step.preconditions({"mode": "ready", "vehicle": CONFIG.name, "gnss": None})
    assert any("palm-tree first" in p for p in problems), problems
