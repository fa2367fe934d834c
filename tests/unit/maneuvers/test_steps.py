"""The pot-map step's rules, and a resumed run, on the servo model's synthetic sweep.

The samples are shaped as the daemon's tap gives them; the truth is the sweep's own
model (tests/unit/calibration/synthetic.py), independent of the step and its fit.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from appliance.config import load_config
from appliance.core.maneuver_tap import ManeuverSample
from appliance.maneuvers.pot_map_step import PotMapStep
from appliance.maneuvers.runner import sample_problem
from appliance.maneuvers.samples_file import SamplesWriter, header, read_samples_file
from appliance.maneuvers.steps import StepContext
from calibration.pot_map import wheel_rad_at
from tests.unit.calibration.synthetic import pot_sweep

CONFIG = load_config("husky")
CONTEXT = StepContext(CONFIG, None, {"x_steering_ratio": 18.0, "x_pot_centre_counts": None})


def tap_samples(seed: int = 3) -> list[dict[str, Any]]:
    sweep = pot_sweep(seed)
    samples = []
    for seq, (t_s, encoder, pot, command) in enumerate(
        zip(
            sweep.t_s,
            sweep.encoder_wheel_rad,
            sweep.pot_counts,
            sweep.commanded_wheel_rad,
            strict=True,
        )
    ):
        fields: dict[str, Any] = dict.fromkeys(ManeuverSample.__dataclass_fields__)
        fields.update(
            seq=seq,
            t_s=float(t_s),
            mode="ready",
            engaged=False,
            stale=[],
            faults=[],
            pot_counts=int(pot),
            servo_position_rad=float(encoder),
            steer_setpoint_rad=float(command),
            speed_mps=0.0,
        )
        samples.append(fields)
    return samples


def test_a_resumed_run_fits_as_the_run_it_continues(tmp_path: Path) -> None:
    samples = tap_samples()
    whole = PotMapStep(CONTEXT).fit(samples, raw_data=None)
    assert whole.accepted, whole.lines

    # Interrupted a third of the way, resumed after the 3 s it took to run the command
    # again (the wheel held still meanwhile: those samples are lost).
    path = tmp_path / "pot-map.jsonl"
    cut = len(samples) // 3
    first = SamplesWriter(path, header("pot-map", CONFIG.name, "0.1.0", "x"))
    first.append(samples[:cut])
    first.mark("stopped", reason="interrupted (Ctrl-C)")
    first.close()
    gap_end = samples[cut]["t_s"] + 3.0
    resumed = SamplesWriter(path, None)
    resumed.mark("resumed", samples=cut)
    resumed.append(s for s in samples[cut:] if s["t_s"] >= gap_end)
    resumed.close()
    again = PotMapStep(CONTEXT).fit(read_samples_file(path, CONFIG.name).samples, raw_data=None)
    assert again.accepted, again.lines
    # The same within what the lost rest can move: a count of centre is 0.02° of tyre.
    tolerances = {"pot_centre_counts": 1.0, "backlash_rad": 0.005}
    for name, tolerance in tolerances.items():
        assert again.figures[name] == pytest.approx(whole.figures[name], abs=tolerance), name
    result, other = whole.result, again.result
    assert result is not None and other is not None
    counts = np.linspace(800.0, 3400.0, 50)
    ours = wheel_rad_at(result.values["steering.pot_to_wheel_coeffs"], counts - 2131.0)
    theirs = wheel_rad_at(other.values["steering.pot_to_wheel_coeffs"], counts - 2131.0)
    assert np.max(np.abs(np.degrees((ours - theirs) / 18.0))) < 0.05


def test_the_sweep_is_complete_only_back_at_full_right_and_resting() -> None:
    step = PotMapStep(CONTEXT)
    samples = tap_samples()
    done_at = None
    for index, sample in enumerate(samples):
        assert step.update(sample) is None
        if done_at is None and step.complete():
            done_at = index
    assert done_at is not None
    assert samples[done_at]["servo_position_rad"] < -9.0  # at the right lock
    assert done_at > 0.9 * len(samples)  # not half way, where the counts first match
    assert step.progress().fraction == pytest.approx(1.0)


def test_moving_for_a_second_ends_a_standing_step_and_a_noisy_reading_does_not() -> None:
    step = PotMapStep(CONTEXT)
    samples = tap_samples()[:200]
    for sample in samples[:100]:
        assert step.update(sample | {"speed_mps": 0.2}) is None  # GNSS/INS noise standing
    for sample in samples[100:120]:
        assert step.update(sample | {"speed_mps": 0.5}) is None  # a spike, not yet a second
    said = [step.update(sample | {"speed_mps": 0.5}) for sample in samples[120:200]]
    assert any(text and "the vehicle moved" in text for text in said)
    assert step.update(samples[0] | {"engaged": True}) == (
        "the operator engaged: a maneuver by hand runs with the autopilot off"
    )


def test_faults_the_step_measures_do_not_end_it_others_do() -> None:
    step = PotMapStep(CONTEXT)
    base = tap_samples()[0]
    assert sample_problem(base | {"mode": "error", "faults": ["steering_unknown"]}, step) is None
    said = sample_problem(base | {"mode": "error", "faults": ["steering_unknown", "x"]}, step)
    assert said == "the daemon went to ERROR (faults: x)"
    said = sample_problem(base | {"mode": "estop", "faults": []}, step)
    assert said == "the daemon went to ESTOP (faults: none named)"
    said = sample_problem(base | {"stale": ["steering.pot"]}, step)
    assert said == "input stale: steering.pot"
