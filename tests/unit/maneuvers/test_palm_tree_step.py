"""The palm-tree step on the synthetic palm tree of tests/unit/calibration/vehicle_runs.py.

The samples are shaped as the daemon's tap gives them (50 Hz control cycles, a GNSS/INS
epoch every fifth, the pot in raw counts); the truth is the run's own linkage and k,
independent of the step and its fit.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from appliance.config import load_config
from appliance.config.calibration import Calibration, CalibrationFile
from appliance.config.simulated_calibration import simulated_calibration
from appliance.core.maneuver_tap import ManeuverSample
from appliance.maneuvers.merge import _apply
from appliance.maneuvers.palm_tree_step import BETWEEN_EPOCHS, PalmTreeStep
from appliance.maneuvers.steps import StepContext
from tests.unit.calibration.vehicle_runs import (
    ANTENNA_FORWARD_M,
    TRUE_K,
    palm_tree,
    true_tyre_rad,
)

BASE = load_config("husky")
CONFIG = BASE.model_copy(
    update={
        "positioning": BASE.positioning.model_copy(update={"antenna_forward_m": ANTENNA_FORWARD_M})
    }
)
CALIBRATION = simulated_calibration(CONFIG.name)
CONTEXT = StepContext(CONFIG, CALIBRATION)
CYCLES_PER_EPOCH = 5


def tap_samples(seed: int = 1) -> list[dict[str, Any]]:
    return as_tap_samples(palm_tree(seed=seed).rows)


def as_tap_samples(rows: list[tuple[float, ...]]) -> list[dict[str, Any]]:
    """Receiver epochs (t, x, y, yaw, speed, wheel, sigma) as the tap's cycles."""
    converter = Calibration.from_file(CALIBRATION)
    samples: list[dict[str, Any]] = []
    for t_s, x, y, yaw, speed, wheel, sigma in rows:
        counts = round(converter.counts_from_wheel_rad(float(wheel)))
        for cycle in range(CYCLES_PER_EPOCH):  # the control cycles repeat the last epoch
            fields: dict[str, Any] = dict.fromkeys(ManeuverSample.__dataclass_fields__)
            fields.update(
                seq=len(samples),
                t_s=float(t_s) + 0.02 * cycle,
                mode="ready",
                engaged=False,
                stale=[],
                faults=[],
                pot_counts=counts,
                speed_mps=float(speed),
                gnss_time_s=float(t_s),
                east_m=float(x),
                north_m=float(y),
                yaw_rad=float(yaw),
                gnss_speed_mps=float(speed),
                sigma_m=float(sigma),
                fix_quality="rtk_fixed",
            )
            samples.append(fields)
    return samples


@pytest.fixture(scope="module")
def samples() -> list[dict[str, Any]]:
    return tap_samples()


def test_the_fit_recovers_the_linkage_and_k(samples: list[dict[str, Any]]) -> None:
    report = PalmTreeStep(CONTEXT).fit(samples, raw_data="palm.jsonl")
    assert report.accepted, report.lines
    assert report.result is not None
    coeffs = report.result.values["steering.wheel_to_tyre_coeffs"]
    ratio = report.result.values["steering.steering_ratio"]
    assert ratio == pytest.approx(1.0 / coeffs[0])
    wheel = np.linspace(-3 * math.pi, 3 * math.pi, 301)
    fitted = np.polynomial.polynomial.polyval(wheel, (0.0, *coeffs))
    assert np.max(np.abs(np.degrees(fitted - true_tyre_rad(wheel)))) < 0.3
    assert abs(report.figures["k_from_arcs"] - TRUE_K) < 0.02 * TRUE_K
    # Only the epochs are samples: the repeated cycles are not counted as rejected.
    assert not any(BETWEEN_EPOCHS in line for line in report.lines)


def test_the_result_merges_into_a_valid_file(samples: list[dict[str, Any]]) -> None:
    report = PalmTreeStep(CONTEXT).fit(samples, raw_data=None)
    assert report.result is not None
    data = CALIBRATION.model_dump()
    _apply(data, report.result)
    merged = Calibration.from_file(CalibrationFile.model_validate(data))
    assert merged.wheel_to_tyre_coeffs is not None
    assert merged.tyre_rad_from_wheel(math.pi) == pytest.approx(
        float(true_tyre_rad(math.pi)), abs=math.radians(0.3)
    )


def test_coverage_fills_half_turn_by_half_turn_and_completes_at_a_standstill(
    samples: list[dict[str, Any]],
) -> None:
    step = PalmTreeStep(CONTEXT)
    fractions = []
    done_at = None
    for index, sample in enumerate(samples):
        assert step.update(sample) is None
        if index % 50 == 0:
            fractions.append(step.progress().fraction)
        if done_at is None and step.complete():
            done_at = index
    assert fractions == sorted(fractions) and fractions[-1] == 1.0
    assert done_at is not None
    assert abs(samples[done_at]["gnss_speed_mps"]) < 0.3
    assert "[#######] (7/7 half turns" in step.progress().detail


def test_engaging_ends_the_step() -> None:
    step = PalmTreeStep(CONTEXT)
    assert step.update({"engaged": True}) is not None


def test_without_a_calibration_the_step_refuses_with_the_steps_to_run_first() -> None:
    step = PalmTreeStep(StepContext(CONFIG, None))
    problems = step.preconditions({"mode": "ready", "vehicle": CONFIG.name, "gnss": None})
    assert any("pot-center and pot-map first" in p for p in problems), problems
    assert any("GNSS/INS fix" in p for p in problems), problems


def test_samples_without_epochs_are_refused_clearly() -> None:
    step = PalmTreeStep(CONTEXT)
    report = step.fit([{"seq": 0, "t_s": 0.0, "pot_counts": 2000}], raw_data=None)
    assert not report.accepted and "no GNSS/INS epoch" in report.lines[0]


def auto_context(**drive: Any) -> StepContext:
    """The vehicle file allowing the palm tree driven by the daemon, --auto given."""
    data = CONFIG.model_dump(mode="json")
    data["engagement"] |= {"hold_to_move": True, "hold_to_move_stop_distance_m": 3.0}
    data["palm_tree_drive"] = {"allowed": True} | drive
    config = type(CONFIG).model_validate(data)
    return StepContext(config, simulated_calibration(config.name), {"x_auto": True})


def driven(
    samples: list[dict[str, Any]], phase: str = "drive", arc: int = 0
) -> list[dict[str, Any]]:
    return [dict(s, palm_phase=phase, palm_arc=arc, engaged=True) for s in samples]


READY = {
    "mode": "ready",
    "vehicle": CONFIG.name,
    "gnss": {"fix": True, "yaw_deg": 10.0},
    "measured_speed_mps": 0.0,
}


def test_auto_is_refused_where_the_vehicle_file_does_not_allow_it() -> None:
    step = PalmTreeStep(StepContext(CONFIG, CALIBRATION, {"x_auto": True}))
    assert step.moves_vehicle and step.default_timeout_s == 3600.0
    problems = " ".join(step.preconditions(READY))
    assert "does not allow" in problems and "hold-to-move" in problems
    allowed = PalmTreeStep(auto_context())
    assert allowed.preconditions(READY) == []
    moving = allowed.preconditions(dict(READY, measured_speed_mps=1.2))
    assert any("moving (1.20 m/s)" in p for p in moving)
    assert any("READY" in p for p in allowed.preconditions(dict(READY, mode="self_check")))


def test_auto_follows_the_program_and_completes_when_it_is_done(
    samples: list[dict[str, Any]],
) -> None:
    step = PalmTreeStep(auto_context())
    assert step.start_step() == "palm-tree@0"
    assert "ENGAGE" in " ".join(step.instructions)
    for sample in driven(samples[:200], arc=3):  # engaged: by design, not an abort
        assert step.update(sample) is None
    assert not step.complete()
    assert "driving arc 4, drive" in step.progress().detail
    last = dict(samples[-1], palm_phase="done", palm_arc=7, speed_mps=0.0, gnss_speed_mps=0.0)
    step.update(last)
    assert step.complete()
    # A daemon that restarted has no program: the run ends, to be resumed.
    ended = step.update(dict(samples[0], palm_phase=None))
    assert ended is not None and "resume" in ended
    by_hand = PalmTreeStep(CONTEXT)
    assert by_hand.update(driven(samples[:1])[0]) is not None  # engaged ends a hand run


def test_auto_resumes_from_the_first_half_turn_not_yet_covered_by_hand_or_driven() -> None:
    """The program drives full left (+) to full right; arcs already in the samples, by
    hand or driven, are not driven again."""
    step = PalmTreeStep(auto_context())
    for sample in as_tap_samples(palm_tree(wheels_rad=(3 * math.pi, 2 * math.pi)).rows):
        step.update(sample)  # by hand: the program's absence is said, the arcs kept
    assert step.start_step() == "palm-tree@2"
    right = PalmTreeStep(auto_context())
    for sample in as_tap_samples(palm_tree(wheels_rad=(-3 * math.pi,)).rows):
        right.update(sample)
    assert right.start_step() == "palm-tree@0"
    everything = PalmTreeStep(auto_context())
    for sample in tap_samples():
        everything.update(sample)
    assert everything.start_step() == "palm-tree@6"  # the last: never past the end


def test_auto_fits_the_same_samples_as_by_hand(samples: list[dict[str, Any]]) -> None:
    by_hand = PalmTreeStep(CONTEXT).fit(samples, raw_data=None)
    auto = PalmTreeStep(auto_context()).fit(driven(samples), raw_data=None)
    assert auto.accepted and by_hand.accepted
    assert auto.figures == by_hand.figures
