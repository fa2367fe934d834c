"""The pedal sweep's program: its rules for any speed sequence, and its runs on a plant.

The rules are the ones the module promises (never both pedals, no throttle past the top,
an unknown speed brakes, no pedals when they are not the sweep's); the runs are checked on
the simulated vehicle faster than real time (:mod:`appliance.sim.sweep_run`), where the
fit must find the simulated vehicle's own pedal answer, which nobody told it.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.guidance.pedal_sweep import PedalSweep, PedalSweepParams, SweepPhase
from appliance.maneuvers.pedals_step import PedalsStep
from appliance.maneuvers.steps import StepContext
from appliance.sim.sweep_run import full_scale_mps2, map_errors_mps2, run_sweep

PARAMS = PedalSweepParams(
    throttle_levels_pct=(20.0, 40.0),
    brake_levels_pct=(0.0, 10.0, 30.0),
    top_speed_mps=3.0,
    coast_s=1.0,
    max_throttle_s=10.0,
    coast_down_end_mps=0.5,
)


def shaped_husky() -> VehicleConfig:
    """The Husky with pedals that are not linear: a throttle dead band and a progressive
    brake, which the fit is not told."""
    data = load_config("husky-sim").model_dump()
    data["simulation"]["pedals"] = {
        "throttle_deadband_pct": 5.0,
        "throttle_exponent": 0.8,
        "brake_deadband_pct": 2.0,
        "brake_exponent": 1.3,
    }
    return VehicleConfig.model_validate(data)


speeds = st.one_of(
    st.none(),
    st.just(math.nan),
    st.floats(min_value=-1.0, max_value=6.0, allow_nan=False),
)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(speeds, st.booleans(), st.floats(0.001, 2.0)), max_size=120))
def test_the_rules_hold_for_any_speed_sequence(
    cycles: list[tuple[float | None, bool, float]],
) -> None:
    sweep = PedalSweep(PARAMS)
    now_s = 0.0
    for speed, in_control, dt_s in cycles:
        now_s += dt_s
        command = sweep.update(speed, now_s, in_control)
        assert not (command.throttle_pct > 0.0 and command.brake_pct > 0.0)
        assert 0.0 <= command.throttle_pct <= max(PARAMS.throttle_levels_pct)
        if not in_control:
            assert command.phase is SweepPhase.PAUSED
            assert (command.throttle_pct, command.brake_pct) == (0.0, 0.0)
        elif speed is None or not math.isfinite(speed):
            assert command.phase is SweepPhase.NO_SPEED
            assert command.brake_pct == PARAMS.hold_brake_pct
        elif abs(speed) > PARAMS.top_speed_mps + PARAMS.overspeed_margin_mps:
            assert command.throttle_pct == 0.0
            assert command.brake_pct >= PARAMS.hold_brake_pct
        if command.throttle_pct > 0.0:
            assert command.phase in (SweepPhase.THROTTLE, SweepPhase.BOOST, SweepPhase.DESCEND)
        assert 0 <= command.run <= PARAMS.runs


def drive(sweep: PedalSweep, speed_of: list[float], dt_s: float = 0.1) -> list[SweepPhase]:
    phases = []
    for i, speed in enumerate(speed_of):
        phases.append(sweep.update(speed, i * dt_s, True).phase)
    return phases


def test_a_run_waits_standing_then_throttle_coast_brake_and_the_next_run() -> None:
    sweep = PedalSweep(PARAMS)
    assert drive(sweep, [0.0] * 11)[-1] is SweepPhase.THROTTLE  # 1 s standing first
    command = sweep.update(1.0, 1.2, True)
    assert (command.phase, command.throttle_pct, command.brake_pct) == (
        SweepPhase.THROTTLE,
        20.0,
        0.0,
    )
    assert sweep.update(3.0, 1.3, True).phase is SweepPhase.COAST  # the top reached
    assert sweep.update(2.9, 2.35, True).phase is SweepPhase.BRAKE  # coast_s later
    # Brake level 0 is a coast-down: released down to the first band, then held.
    assert sweep.update(1.0, 2.45, True).brake_pct == 0.0
    assert sweep.update(0.4, 2.55, True).brake_pct == PARAMS.hold_brake_pct
    command = sweep.update(0.0, 2.65, True)
    assert (command.phase, command.run) == (SweepPhase.STOPPING, 1)


def test_a_level_that_cannot_reach_the_top_is_boosted_by_the_highest() -> None:
    sweep = PedalSweep(PARAMS)
    drive(sweep, [0.0] * 11)
    # The speed stops rising at 2 m/s: within two windows of plateau_s the boost takes over.
    now_s = 1.1
    command = sweep.update(2.0, now_s, True)
    while command.phase is SweepPhase.THROTTLE:
        now_s += 0.1
        command = sweep.update(2.0, now_s, True)
        assert now_s < 1.0 + 2 * PARAMS.plateau_s + 0.2
    assert (command.phase, command.throttle_pct) == (SweepPhase.BOOST, 40.0)
    # At the top, the run's own level again while the vehicle slows to where it stopped
    # gaining; then the top once more, and the coast and brake from there.
    command = sweep.update(3.0, now_s + 0.1, True)
    assert (command.phase, command.throttle_pct) == (SweepPhase.DESCEND, 20.0)
    assert sweep.update(2.5, now_s + 1.0, True).phase is SweepPhase.DESCEND
    assert sweep.update(2.0, now_s + 2.0, True).phase is SweepPhase.BOOST
    assert sweep.update(3.0, now_s + 3.0, True).phase is SweepPhase.COAST


def test_taking_the_pedals_away_restarts_the_run_from_standstill() -> None:
    sweep = PedalSweep(PARAMS)
    drive(sweep, [0.0] * 11)
    assert sweep.update(1.5, 1.2, True).phase is SweepPhase.THROTTLE
    assert sweep.update(1.5, 1.3, False).phase is SweepPhase.PAUSED
    command = sweep.update(1.5, 1.4, True)
    assert (command.phase, command.run, command.brake_pct) == (
        SweepPhase.STOPPING,
        0,
        PARAMS.hold_brake_pct,
    )


def test_a_sweep_resumes_from_a_run_of_its_own() -> None:
    sweep = PedalSweep(PARAMS)
    sweep.reset(first_run=2)
    assert (sweep.run, sweep.phase) == (2, SweepPhase.STOPPING)
    with pytest.raises(ValueError, match=r"runs 0\.\.2"):
        sweep.reset(first_run=PARAMS.runs)


def test_the_last_run_ends_done_holding_the_brake() -> None:
    sweep = PedalSweep(PARAMS)
    sweep.run = PARAMS.runs - 1
    sweep.phase = SweepPhase.BRAKE
    command = sweep.update(0.0, 0.0, True)
    assert sweep.done and command.phase is SweepPhase.DONE
    assert command.brake_pct == PARAMS.hold_brake_pct and command.throttle_pct == 0.0
    assert command.as_status()["run"] == PARAMS.runs


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"throttle_levels_pct": ()}, "at least one throttle"),
        ({"throttle_levels_pct": (0.0, 20.0)}, "throttle levels must lie"),
        ({"brake_levels_pct": (-5.0,)}, "brake levels must lie"),
        ({"top_speed_mps": math.nan}, "top_speed_mps must be positive"),
        ({"hold_brake_pct": 0.0}, "hold_brake_pct must lie"),
    ],
)
def test_parameters_out_of_range_are_refused(change: dict[str, object], message: str) -> None:
    values: dict[str, object] = {
        "throttle_levels_pct": (20.0,),
        "brake_levels_pct": (10.0,),
        "top_speed_mps": 3.0,
    }
    with pytest.raises(ValueError, match=message):
        PedalSweepParams(**(values | change))  # type: ignore[arg-type]


def test_the_sweep_recovers_the_simulated_pedals_within_five_percent() -> None:
    config = shaped_husky()
    run = run_sweep(config)
    assert run.done
    phases = [s["sweep_phase"] for s in run.samples]
    assert phases.count("boost") > 0  # the 20 % level cannot reach 4.2 m/s
    assert phases.count("descend") > 0  # and is held again from the top
    # Every brake starts from the top speed, less the coast's 4 s at 0.2 m/s².
    starts = [
        run.samples[i]["speed_mps"]
        for i in range(1, len(run.samples))
        if phases[i] == "brake" and phases[i - 1] == "coast"
    ]
    assert len(starts) == run.runs
    assert min(starts) > config.pedal_sweep.top_speed_mps - 1.0
    step = PedalsStep(StepContext(config, None))
    report = step.fit(run.samples, None)
    assert report.accepted, report.reasons
    result = step.accumulator.fit()
    for brake, pedal_map in ((False, result.throttle), (True, result.brake)):
        errors = np.abs(map_errors_mps2(config, pedal_map, brake))[pedal_map.measured]
        assert errors.size >= 12
        assert errors.max() < 0.05 * full_scale_mps2(config, pedal_map, brake)
