"""From the look-ahead runs' samples to the fit's tracking runs (``calibration.lookahead``).

The daemon's tap gives one sample per control cycle with the run, its phase and the
anchor's cross-track error against the run's course. A run's test counts when it was
driven to its end (the phase went from TEST to FINISH); a test the operator broke off is
counted as ``aborted`` and the run's next attempt is the one used (the last complete
attempt of a run wins: a resumed tuning may drive a run again). A test not driven at the
run's speed is not the test the candidates are compared on (``not_at_speed``). A run
stands for every candidate with its look-ahead at that speed (``TuningRun.candidates``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from appliance.guidance.lookahead_tuning import TuningParams, TuningPhase
from appliance.guidance.pure_pursuit import LookaheadSchedule
from calibration.lookahead import LookaheadCandidate, TrackingRun

ABORTED = "aborted"
NOT_AT_SPEED = "not_at_speed"
NO_CROSS_TRACK = "no_cross_track"
TOO_FEW = "too_few_samples"
SPEED_TOLERANCE = 0.15  # relative, on the test's median speed


@dataclass(frozen=True)
class RunSample:
    t_s: float
    run: int | None
    phase: str | None
    cross_track_m: float | None
    speed_mps: float | None


@dataclass(frozen=True)
class CollectedRuns:
    runs: tuple[TrackingRun, ...]
    complete: frozenset[int]  # the tuning runs with a test that counts
    rejected: dict[str, int]  # tests (or samples, for no_cross_track), by reason


def candidate_of(schedule: LookaheadSchedule) -> LookaheadCandidate:
    return LookaheadCandidate(schedule.offset_m, schedule.gain_s, schedule.min_m, schedule.max_m)


def _count(rejected: dict[str, int], reason: str, n: int = 1) -> None:
    rejected[reason] = rejected.get(reason, 0) + n


def collect_runs(
    samples: Sequence[RunSample],
    params: TuningParams,
    candidates: Sequence[LookaheadSchedule],
) -> CollectedRuns:
    """The tracking runs the samples hold (see the module)."""
    rejected: dict[str, int] = {}
    tests: dict[int, list[RunSample]] = {}
    current: list[RunSample] = []
    current_run: int | None = None

    def close(finished: bool) -> None:
        if current_run is not None and current:
            if finished:
                tests[current_run] = list(current)
            else:
                _count(rejected, ABORTED)
        current.clear()

    for sample in samples:
        phase, run = sample.phase, sample.run
        if phase == TuningPhase.TEST and run is not None:
            if run != current_run:
                close(False)
                current_run = run
            current.append(sample)
        elif current:
            close(phase == TuningPhase.FINISH and run == current_run)
            current_run = None
    close(False)

    runs: list[TrackingRun] = []
    complete: set[int] = set()
    for index, test in sorted(tests.items()):
        if not 0 <= index < len(params.runs):
            continue
        spec = params.runs[index]
        usable = [s for s in test if s.cross_track_m is not None and math.isfinite(s.cross_track_m)]
        if len(usable) < len(test):
            _count(rejected, NO_CROSS_TRACK, len(test) - len(usable))
        if len(usable) < 10:
            _count(rejected, TOO_FEW)
            continue
        speeds = [s.speed_mps for s in usable if s.speed_mps is not None]
        median = float(np.median(speeds)) if speeds else math.nan
        if not abs(median - spec.speed_mps) <= SPEED_TOLERANCE * spec.speed_mps:
            _count(rejected, NOT_AT_SPEED)
            continue
        t = np.array([s.t_s for s in usable])
        e = np.array([s.cross_track_m for s in usable], dtype=float)
        keep = np.concatenate(([True], np.diff(t) > 0.0))
        complete.add(index)
        for c in spec.candidates:
            runs.append(
                TrackingRun(
                    candidate_of(candidates[c]),
                    spec.course,
                    spec.offset_m,
                    spec.speed_mps,
                    t[keep],
                    e[keep],
                )
            )
    return CollectedRuns(tuple(runs), frozenset(complete), rejected)
