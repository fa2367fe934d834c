"""The look-ahead tuning runs (`dbw calibrate lookahead`): Stanley et al.'s line and arc tests.

The paper tuned the look-ahead "based on the observed error and oscillation" of line and
arc tracking tests at 0 and ±3 m parallel offsets, at 5 and 10 mph (Fig. 20). Here each
run is one candidate schedule on one such condition, driven by the daemon's own route
chain (the same dead reckoning, frame blend, planner, tracker and speed profile as a
route), so what is tuned is the loop the vehicle will drive with.

Why a course laid at the vehicle, and a step in it: a technician has a field, not a
surveyed test track. The course starts where the vehicle stands, straight ahead of it
(a run-up to the run's speed), then goes on straight (``line``) or into an arc of
``arc_radius_m`` to the left or right. Once the anchor is past the run-up at speed, the
course moves sideways by the run's offset: from then on the vehicle is ``offset_m`` to the
left of its course, heading along it, at speed, which is the paper's test without having
to start it at speed. The test lasts ``test_s`` (shorter on an arc: never the whole
circle, so the course cannot pass the vehicle's own point again); the course then runs
on far enough for the speed profile to stop the vehicle at its end.

A run goes STAND (not engaged: the course is laid, and laid again while the vehicle
stands somewhere else) → RUNUP (engaged) → TEST → FINISH (the test is over; stopping at
the course's end), and it is done when the operator disengages after its test. A
disengagement before the test is over aborts it: the same run again from STAND. After
the last run, DONE. Deny by default: the program only ever lays courses; the route chain
makes wishes from them, and the mode machine and the safety layer judge those.

Pure: poses and time in, a phase and courses out; no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal

import numpy as np
import numpy.typing as npt

from appliance.guidance.pure_pursuit import LookaheadSchedule
from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]
Course = Literal["line", "arc_left", "arc_right"]
COURSES: tuple[Course, ...] = ("line", "arc_left", "arc_right")
# An arc test never drives more than this share of the circle (the rest of it is the
# stopping distance), so the course never passes the same point twice.
MAX_ARC_TURNS = 0.9


class TuningPhase(StrEnum):
    STAND = "stand"
    RUNUP = "runup"
    TEST = "test"
    FINISH = "finish"
    DONE = "done"


@dataclass(frozen=True)
class TuningRun:
    """One candidate schedule on one condition."""

    index: int
    schedule: LookaheadSchedule
    course: Course
    offset_m: float  # after the step the vehicle is this far left of the course
    speed_mps: float
    # The candidates (their indices in the tuning's list) this run stands for: those with
    # the same look-ahead at this speed share it.
    candidates: tuple[int, ...] = (0,)

    def describe(self) -> str:
        s = self.schedule
        return (
            f"{self.course.replace('_', ' ')} {self.offset_m:+g} m at {self.speed_mps:.2f} m/s, "
            f"look-ahead {s.offset_m:g} + {s.gain_s:g} s x v (min {s.min_m:g} m)"
        )


@dataclass(frozen=True)
class TuningParams:
    runs: tuple[TuningRun, ...]
    arc_radius_m: float = 25.0
    # Straight ahead from the vehicle's centre to the step (and an arc's start): the
    # vehicle must reach the run's speed in it (a run not at speed is the fit's to refuse).
    runup_m: float = 30.0
    test_s: float = 25.0
    stop_m: float = 30.0  # beyond the test: the speed profile stops the vehicle in it
    behind_m: float = 5.0  # the course starts this far behind the centre
    spacing_m: float = 0.5
    standing_mps: float = 0.1
    # Standing this far (or this much turned) from where the course was laid: laid again.
    relay_m: float = 0.3
    relay_yaw_rad: float = math.radians(2.0)

    def __post_init__(self) -> None:
        if not self.runs:
            raise ValueError("the look-ahead tuning needs at least one run")
        for name in ("arc_radius_m", "runup_m", "test_s", "stop_m", "spacing_m"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be positive (got {getattr(self, name)})")
        for run in self.runs:
            if run.course != "line" and abs(run.offset_m) >= self.arc_radius_m / 2.0:
                raise ValueError(
                    f"run {run.index}: an offset of {run.offset_m} m on a "
                    f"{self.arc_radius_m} m arc is not a parallel offset"
                )

    def test_s_for(self, run: TuningRun) -> float:
        """The test's duration: ``test_s``, shorter where an arc would close its circle."""
        if run.course == "line":
            return self.test_s
        room_m = MAX_ARC_TURNS * math.tau * self.arc_radius_m - self.stop_m
        return max(0.0, min(self.test_s, room_m / run.speed_mps))


def course_points(
    start: Pose2D, run: TuningRun, params: TuningParams, shift_left_m: float = 0.0
) -> FloatArray:
    """The run's course from the vehicle's centre pose ``start``, moved ``shift_left_m``
    to the left (a parallel offset): ``behind_m`` back, the run-up straight ahead, then
    the straight or the arc (its radius the same whatever the shift), long enough for the
    test and the stop. East-north points, ``spacing_m`` apart."""
    runup_m = params.runup_m
    after_m = run.speed_mps * params.test_s_for(run) + params.stop_m
    s = np.arange(-params.behind_m, runup_m + after_m + params.spacing_m, params.spacing_m)
    along, left = s.copy(), np.full_like(s, shift_left_m)
    if run.course != "line":
        radius = params.arc_radius_m
        sign = 1.0 if run.course == "arc_left" else -1.0
        bend = s > runup_m
        angle = (s[bend] - runup_m) / radius
        along[bend] = runup_m + radius * np.sin(angle)
        left[bend] += sign * radius * (1.0 - np.cos(angle))
    c, s_yaw = math.cos(start.yaw_rad), math.sin(start.yaw_rad)
    east = start.x_m + c * along - s_yaw * left
    north = start.y_m + s_yaw * along + c * left
    return np.column_stack([east, north])


@dataclass(frozen=True)
class TuningStep:
    """One cycle of the program: where it is, and a course to lay (None: keep it)."""

    phase: TuningPhase
    run: TuningRun | None  # None once DONE
    runs: int
    lay: FloatArray | None = None
    reason: str = ""  # why the vehicle may not be engaged now ("" : it may)
    test_left_s: float | None = None

    def as_status(self) -> dict[str, Any]:
        run = self.run
        return {
            "phase": str(self.phase),
            "run": None if run is None else run.index,
            "runs": self.runs,
            "describe": None if run is None else run.describe(),
            "speed_mps": None if run is None else run.speed_mps,
            "test_left_s": None if self.test_left_s is None else round(self.test_left_s, 1),
        }


class LookaheadTuning:
    """The runs, one after another (see the module); ``reset()``/``update()``."""

    def __init__(self, params: TuningParams) -> None:
        self.params = params
        self.reset()

    def reset(self, first_run: int = 0) -> None:
        if not 0 <= first_run < len(self.params.runs):
            raise ValueError(f"the tuning has runs 0..{len(self.params.runs) - 1}")
        self.run_index = first_run
        self.phase = TuningPhase.STAND
        self.laid_at: Pose2D | None = None
        self.step_at_s: float | None = None
        self.aborted = 0

    @property
    def run(self) -> TuningRun | None:
        runs = self.params.runs
        return runs[self.run_index] if self.run_index < len(runs) else None

    def update(
        self,
        engaged: bool,
        speed_mps: float | None,
        pose: Pose2D | None,
        progress_m: float | None,
        now_s: float,
    ) -> TuningStep:
        """``pose`` the vehicle centre's (the route chain's blended one; None: none yet),
        ``progress_m`` the anchor's along the laid course (None: not on it)."""
        run, p = self.run, self.params
        n = len(p.runs)
        if run is None:
            return TuningStep(TuningPhase.DONE, None, n, reason="the look-ahead runs are done")
        if not engaged:
            if self.phase is TuningPhase.FINISH:
                self.run_index += 1  # the test is in: the operator took over at its end
                run = self.run
                if run is None:
                    self.phase = TuningPhase.DONE
                    return TuningStep(self.phase, None, n, reason="the look-ahead runs are done")
            elif self.phase is not TuningPhase.STAND:
                self.aborted += 1
            self.phase, self.step_at_s = TuningPhase.STAND, None
            return self._stand(run, speed_mps, pose)
        if self.phase is TuningPhase.STAND:
            if self.laid_at is None:
                return TuningStep(self.phase, run, n, reason="no course laid yet")
            self.phase = TuningPhase.RUNUP
        if self.phase is TuningPhase.RUNUP:
            return self._runup(run, progress_m, now_s)
        assert self.step_at_s is not None
        left_s = self.step_at_s + p.test_s_for(run) - now_s
        if self.phase is TuningPhase.TEST and left_s <= 0.0:
            self.phase = TuningPhase.FINISH
        return TuningStep(self.phase, run, n, test_left_s=max(0.0, left_s))

    def _stand(self, run: TuningRun, speed_mps: float | None, pose: Pose2D | None) -> TuningStep:
        p, n = self.params, len(self.params.runs)
        if pose is None:
            return TuningStep(TuningPhase.STAND, run, n, reason="waiting for the pose")
        if speed_mps is None or not math.isfinite(speed_mps):
            return TuningStep(TuningPhase.STAND, run, n, reason="speed unknown")
        if abs(speed_mps) > p.standing_mps:
            return TuningStep(
                TuningPhase.STAND, run, n, reason="stop: each look-ahead run starts standing"
            )
        laid = self.laid_at
        moved = (
            laid is None
            or math.hypot(pose.x_m - laid.x_m, pose.y_m - laid.y_m) > p.relay_m
            or abs(math.remainder(pose.yaw_rad - laid.yaw_rad, math.tau)) > p.relay_yaw_rad
        )
        if not moved:
            return TuningStep(TuningPhase.STAND, run, n)
        self.laid_at = pose
        # Laid this cycle, judged next: not engaged before the course is the one driven.
        return TuningStep(
            TuningPhase.STAND, run, n, lay=course_points(pose, run, p), reason="laying the course"
        )

    def _runup(self, run: TuningRun, progress_m: float | None, now_s: float) -> TuningStep:
        p, n = self.params, len(self.params.runs)
        if progress_m is None or progress_m < p.behind_m + p.runup_m:
            return TuningStep(TuningPhase.RUNUP, run, n)
        assert self.laid_at is not None
        self.phase, self.step_at_s = TuningPhase.TEST, now_s
        lay = course_points(self.laid_at, run, p, shift_left_m=-run.offset_m)
        return TuningStep(TuningPhase.TEST, run, n, lay=lay, test_left_s=p.test_s_for(run))
