"""The look-ahead tuning's program: its courses (against geometry worked out by hand) and
its phases (engage, step, finish, abort and repeat), and the samples into the fit's runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.guidance.lookahead_samples import (
    ABORTED,
    NOT_AT_SPEED,
    RunSample,
    collect_runs,
)
from appliance.guidance.lookahead_tuning import (
    LookaheadTuning,
    TuningParams,
    TuningPhase,
    TuningRun,
    course_points,
)
from appliance.guidance.pure_pursuit import LookaheadSchedule
from drivers.geometry import Pose2D

A, B = LookaheadSchedule(0.5, 0.3, 1.5), LookaheadSchedule(0.5, 0.9, 1.5)


def params(*runs: TuningRun, **kwargs: float) -> TuningParams:
    return TuningParams(runs=runs, **kwargs)


LINE = TuningRun(0, A, "line", 3.0, 2.0, (0,))
ARC = TuningRun(1, B, "arc_left", -3.0, 4.0, (1,))


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(-1e4, 1e4),
    y=st.floats(-1e4, 1e4),
    yaw=st.floats(-math.pi, math.pi),
    shift=st.floats(-5.0, 5.0),
)
def test_a_line_course_runs_straight_ahead_of_the_vehicle_moved_sideways(
    x: float, y: float, yaw: float, shift: float
) -> None:
    p = params(LINE)
    points = course_points(Pose2D(x, y, yaw), LINE, p, shift_left_m=shift)
    rel = points - np.array([x, y])
    along = rel @ np.array([math.cos(yaw), math.sin(yaw)])
    left = rel @ np.array([-math.sin(yaw), math.cos(yaw)])
    np.testing.assert_allclose(left, shift, atol=1e-6)
    assert along[0] == pytest.approx(-p.behind_m, abs=1e-6)
    assert along[-1] >= p.runup_m + LINE.speed_mps * p.test_s + p.stop_m - 1e-6


def test_an_arc_course_bends_at_the_end_of_the_run_up_on_a_circle_of_its_radius() -> None:
    p = params(ARC, arc_radius_m=20.0)
    points = course_points(Pose2D(0.0, 0.0, 0.0), ARC, p, shift_left_m=3.0)
    bend = points[:, 0] > p.runup_m + 1e-6
    # Left turn: the centre 20 m left of the run-up's end (moved with the course).
    radius = np.hypot(points[bend, 0] - p.runup_m, points[bend, 1] - (3.0 + 20.0))
    np.testing.assert_allclose(radius, 20.0, atol=1e-6)
    # Never the whole circle: at most 0.9 of it, stop included.
    turned = np.sum(np.hypot(*np.diff(points[bend], axis=0).T)) / 20.0
    assert turned <= 0.9 * math.tau + 1e-6
    assert p.test_s_for(ARC) < p.test_s  # 25 s at 4 m/s would not fit


def test_the_program_lays_at_a_standing_vehicle_steps_at_the_run_up_and_finishes() -> None:
    p = params(LINE, ARC)
    program = LookaheadTuning(p)
    pose = Pose2D(10.0, 5.0, 0.3)
    moving = program.update(False, 1.0, pose, None, 0.0)
    assert moving.phase is TuningPhase.STAND and "stop" in moving.reason and moving.lay is None
    laid = program.update(False, 0.0, pose, None, 0.1)
    assert laid.lay is not None and laid.reason  # laid this cycle, engageable the next
    np.testing.assert_allclose(laid.lay, course_points(pose, LINE, p))
    again = program.update(False, 0.0, pose, None, 0.2)
    assert again.lay is None and not again.reason
    assert program.update(True, 0.0, pose, 6.0, 0.3).phase is TuningPhase.RUNUP
    assert program.update(True, 2.0, pose, p.behind_m + p.runup_m - 0.1, 10.0).lay is None
    step = program.update(True, 2.0, pose, p.behind_m + p.runup_m, 10.02)
    assert step.phase is TuningPhase.TEST and step.lay is not None
    np.testing.assert_allclose(step.lay, course_points(pose, LINE, p, shift_left_m=-3.0))
    assert program.update(True, 2.0, pose, 60.0, 10.02 + p.test_s - 0.1).phase is TuningPhase.TEST
    assert program.update(True, 2.0, pose, 90.0, 10.02 + p.test_s).phase is TuningPhase.FINISH
    # Disengaged after its test: the next run, laid where the vehicle now stands.
    there = Pose2D(60.0, 30.0, 1.0)
    following = program.update(False, 0.0, there, None, 50.0)
    assert following.run == ARC and following.lay is not None and program.aborted == 0


def test_a_disengagement_before_the_test_ends_repeats_the_run() -> None:
    p = params(LINE)
    program = LookaheadTuning(p)
    pose = Pose2D(0.0, 0.0, 0.0)
    program.update(False, 0.0, pose, None, 0.0)
    program.update(True, 0.0, pose, 6.0, 1.0)
    program.update(True, 2.0, pose, 40.0, 10.0)  # the step
    step = program.update(False, 1.5, pose, 45.0, 12.0)
    assert step.run == LINE and step.phase is TuningPhase.STAND and program.aborted == 1
    assert program.run_index == 0
    with pytest.raises(ValueError, match=r"runs 0\.\.0"):
        program.reset(1)


def _samples(run: int, test: list[float], then: str, speed: float = 2.0) -> list[RunSample]:
    t0 = 100.0 * run + (50.0 if then != TuningPhase.FINISH else 0.0)
    out = [RunSample(t0, run, "runup", 0.0, speed)]
    out += [RunSample(t0 + 0.1 * (i + 1), run, "test", e, speed) for i, e in enumerate(test)]
    out.append(RunSample(t0 + 0.1 * (len(test) + 1), run, then, 0.0, speed))
    return out


def test_only_tests_driven_to_their_end_at_speed_become_runs() -> None:
    p = params(LINE, TuningRun(1, B, "line", 3.0, 2.0, (1, 2)))
    errors = list(np.linspace(3.0, 0.0, 40))
    samples = (
        _samples(0, errors[:20], TuningPhase.STAND)  # broken off
        + _samples(0, errors, TuningPhase.FINISH)  # again, to its end
        + _samples(1, errors, TuningPhase.FINISH, speed=1.0)  # not at its speed
    )
    collected = collect_runs(samples, p, (A, B, B))
    assert collected.complete == {0}
    assert collected.rejected == {ABORTED: 1, NOT_AT_SPEED: 1}
    (run,) = collected.runs
    assert run.condition == ("line", 3.0, 2.0)
    np.testing.assert_allclose(run.cross_track_m, errors)
    # A run shared by candidates alike at its speed stands for each of them.
    shared = collect_runs(_samples(1, errors, TuningPhase.FINISH), p, (A, B, B))
    assert len(shared.runs) == 2
