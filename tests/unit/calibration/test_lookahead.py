"""The look-ahead schedule: scoring runs, choosing among candidates, Figs. 20 and 21."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.lookahead import (
    MISSING_RUNS,
    NEVER_CAPTURED,
    TOO_SHORT,
    LookaheadCandidate,
    LookaheadParams,
    TrackingRun,
    candidate_grid,
    choose_lookahead,
    score_run,
)
from tests.unit.calibration.tracking_runs import SPEEDS_MPS, tuning_runs, vehicle

T = np.arange(0.0, 30.0, 0.05)
GRID = candidate_grid((0.0, 1.5, 3.0, 4.5), (0.0, 0.6, 1.2), min_m=1.5, speeds_mps=SPEEDS_MPS)


def run(
    error: np.ndarray, candidate: LookaheadCandidate | None = None, **kw: object
) -> TrackingRun:
    fields: dict[str, object] = {"course": "line", "offset_m": 3.0, "speed_mps": 2.2}
    fields.update(kw)
    return TrackingRun(
        candidate or LookaheadCandidate(2.0, 0.5, 1.5), t_s=T, cross_track_m=error, **fields
    )  # type: ignore[arg-type]


def test_capture_rms_and_overshoot_of_a_known_response() -> None:
    error = 3.0 * np.exp(-T / 2.0) - 0.25 * np.exp(-((T - 8.0) ** 2))
    score = score_run(run(error))
    first = int(np.argmax(np.abs(error) <= 0.2))
    assert score.captured
    assert score.capture_s == pytest.approx(T[first])
    assert score.rms_m == pytest.approx(float(np.sqrt(np.mean(error[first:] ** 2))))
    assert score.overshoot_m == pytest.approx(-float(np.min(error)), rel=1e-9)


def test_a_weave_scores_worse_than_a_bias_of_the_same_rms() -> None:
    """Why the oscillation term: both miss by the same RMS, one of them is a weave."""
    bias = score_run(run(np.full(T.size, 0.1), offset_m=0.0))
    weave = score_run(run(0.1 * math.sqrt(2) * np.sin(2 * math.pi * T / 4.0), offset_m=0.0))
    assert bias.rms_m == pytest.approx(weave.rms_m, rel=1e-3)
    assert bias.oscillation_m < 1e-12
    assert weave.oscillation_m == pytest.approx(weave.rms_m, rel=0.05)
    assert weave.score_m == pytest.approx(math.sqrt(2) * bias.score_m, rel=0.05)


def test_a_run_that_never_captures_scores_infinite() -> None:
    score = score_run(run(np.full(T.size, 0.5)))
    assert not score.captured
    assert score.score_m == math.inf


def test_the_grid_drops_schedules_that_behave_alike() -> None:
    grid = candidate_grid((0.0, 0.5), (0.0, 0.1), min_m=2.5, speeds_mps=(2.2, 4.5))
    assert grid == (LookaheadCandidate(0.0, 0.0, 2.5),)
    grid = candidate_grid((0.0, 1.0), (0.5, 1.0), min_m=1.0, speeds_mps=(2.0, 4.0))
    top = [c.lookahead_m(4.0) for c in grid]
    assert top == sorted(top)
    assert len(grid) == 4
    with pytest.raises(ValueError, match="test speeds"):
        candidate_grid((0.0,), (0.5,), min_m=1.0, speeds_mps=())


def test_the_chosen_schedule_tracks_the_paper_s_tests_within_a_foot() -> None:
    choice = choose_lookahead(tuning_runs(GRID, vehicle()))
    assert choice.accepted, choice.reasons
    assert choice.chosen is not None
    slow, fast = choice.per_speed
    assert (slow.speed_mps, fast.speed_mps) == SPEEDS_MPS
    # Closer at 5 mph than at 10 (Fig. 7b's reason for a schedule), and not the shortest:
    # those weave with the servo's lag.
    assert slow.chosen_lookahead_m < fast.chosen_lookahead_m
    shortest = choice.candidates[0]
    assert not shortest.usable or shortest.score_m > 3 * min(c.score_m for c in choice.candidates)
    assert max(slow.chosen_rms_m, fast.chosen_rms_m) < 0.1
    assert max(slow.chosen_worst_overshoot_m, fast.chosen_worst_overshoot_m) < 0.3


def test_a_weaker_servo_moves_the_look_ahead_out() -> None:
    """Fig. 21: with less torque (a slower, laggier servo) the schedule chosen looks further."""
    strong = choose_lookahead(tuning_runs(GRID, vehicle()))
    weak = choose_lookahead(tuning_runs(GRID, vehicle(rate_deg_per_s=8.0, lag_s=0.4)))
    assert weak.accepted, weak.reasons
    for before, after in zip(strong.per_speed, weak.per_speed, strict=True):
        assert after.chosen_lookahead_m > before.chosen_lookahead_m + 1.0


def test_ties_go_to_the_longer_look_ahead_and_failures_are_counted() -> None:
    short, long, lost, partial = (
        LookaheadCandidate(1.0, 0.0, 1.0),
        LookaheadCandidate(3.0, 0.0, 1.0),
        LookaheadCandidate(0.5, 0.0, 0.5),
        LookaheadCandidate(5.0, 0.0, 1.0),
    )
    good = 3.0 * np.exp(-T)
    runs = [
        run(good, short),
        run(good, short, course="arc"),
        run(good * 1.01, long),
        run(good * 1.01, long, course="arc"),
        run(np.full(T.size, 3.0), lost),  # never gets within the band
        run(good, lost, course="arc"),
        run(good, partial),  # no arc run
    ]
    choice = choose_lookahead(runs)
    assert choice.chosen == long
    assert choice.rejected == {NEVER_CAPTURED: 1}
    assert choice.rejected_candidates == {NEVER_CAPTURED: 1, MISSING_RUNS: 1}
    assert choice.accepted, choice.reasons  # bracketed: 0.5 m and 5 m were tried, and lost
    alone = choose_lookahead(runs[:4])
    assert alone.chosen == long
    assert "the grid's longest: extend the grid" in alone.reasons[0]


def test_a_run_too_short_after_capture_rules_its_candidate_out() -> None:
    late = np.where(T < 25.0, 3.0, 0.0)
    choice = choose_lookahead([run(late)], LookaheadParams(min_scored_s=10.0))
    assert choice.chosen is None
    assert choice.rejected == {TOO_SHORT: 1}
    assert not choice.accepted


def test_garbage_raises_value_error() -> None:
    with pytest.raises(ValueError, match="no tracking runs"):
        choose_lookahead([])
    with pytest.raises(ValueError, match="non-finite"):
        run(np.full(T.size, math.nan))
    with pytest.raises(ValueError, match="differ in length"):
        run(np.zeros(T.size - 1))
    with pytest.raises(ValueError, match="at least 10"):
        TrackingRun(LookaheadCandidate(1, 0, 1), "line", 0.0, 2.0, np.arange(3.0), np.zeros(3))
