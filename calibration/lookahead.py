"""The look-ahead schedule from tracking runs (Stanley et al., Fig. 20).

The paper tuned the look-ahead on the vehicle with line and arc tracking tests at 0 and
±3 m parallel offsets, at 5 and 10 mph, "based on the observed error and oscillation". Here
each candidate schedule ``L(v) = clamp(offset + gain v, min, max)`` (the same form as the
tracker's ``LookaheadSchedule``) is driven on every such condition, and each run is scored:

* capture: the run's first time within ``capture_band_m`` of the line; before it the error
  is the offset being closed, which every candidate has to do and none is judged by;
* the RMS cross-track error after capture, overshoot included;
* oscillation: the RMS of the error's high-pass part (the error minus its moving average
  over ``oscillation_window_s``). Chosen over the zero-crossing rate because that counts
  localization noise around zero as oscillation, and over the RMS alone because a weave is
  a small stability margin, which the paper saw shrink when the servo's torque dropped
  (Fig. 21), while a steady bias on an arc is not.

A run's score is ``sqrt(rms² + w osc²)``; a candidate's is the mean over its runs, and it is
out when any run never captured or a condition is missing. Among the rest the lowest score
wins; within ``tie_tolerance`` of it, the longest look-ahead at the top speed, for margin.
The choice is accepted when its every run stays within the paper's foot, and when the grid
brackets it (a choice at the grid's edge may have a better one beyond).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from calibration.fit_inputs import (
    FloatArray,
    count,
    positive,
    same_length,
    sample_array,
    strictly_increasing,
)

NEVER_CAPTURED = "never_captured"
TOO_SHORT = "too_short"
MISSING_RUNS = "missing_runs"
METHOD = (
    "per run: RMS after first capture and RMS of the high-pass error (oscillation), "
    "score sqrt(rms² + w osc²); mean over runs; exhaustive over the candidates given"
)


@dataclass(frozen=True)
class LookaheadCandidate:
    offset_m: float
    gain_s: float
    min_m: float
    max_m: float = math.inf

    def lookahead_m(self, speed_mps: float) -> float:
        return max(self.min_m, min(self.max_m, self.offset_m + self.gain_s * abs(speed_mps)))


def candidate_grid(
    offsets_m: Iterable[float],
    gains_s: Iterable[float],
    *,
    min_m: float,
    speeds_mps: Sequence[float],
    max_m: float = math.inf,
) -> tuple[LookaheadCandidate, ...]:
    """Every (offset, gain) pair, less those that behave alike: two schedules with the same
    look-ahead (to 1 cm) at every test speed are one candidate, the first of them kept.
    Sorted by look-ahead at the top speed, then at the lowest."""
    if not speeds_mps:
        raise ValueError("candidate_grid needs the test speeds")
    positive("min_m", min_m)
    seen: set[tuple[int, ...]] = set()
    chosen: list[LookaheadCandidate] = []
    for offset, gain in itertools.product(offsets_m, gains_s):
        candidate = LookaheadCandidate(float(offset), float(gain), min_m, max_m)
        key = tuple(round(100 * candidate.lookahead_m(v)) for v in speeds_mps)
        if key not in seen:
            seen.add(key)
            chosen.append(candidate)
    top, low = max(speeds_mps), min(speeds_mps)
    return tuple(sorted(chosen, key=lambda c: (c.lookahead_m(top), c.lookahead_m(low))))


@dataclass(frozen=True)
class TrackingRun:
    """One tracking test: a candidate on a course, at an offset and a speed; checked."""

    candidate: LookaheadCandidate
    course: str  # "line", "arc": any label naming the course
    offset_m: float  # the parallel offset it started from
    speed_mps: float
    t_s: FloatArray
    cross_track_m: FloatArray  # signed, at the anchor

    def __post_init__(self) -> None:
        t = sample_array("t_s", self.t_s, min_samples=10)
        e = sample_array("cross_track_m", self.cross_track_m, min_samples=10)
        same_length({"t_s": t, "cross_track_m": e})
        strictly_increasing("t_s", t)
        object.__setattr__(self, "t_s", t)
        object.__setattr__(self, "cross_track_m", e)

    @property
    def condition(self) -> tuple[str, float, float]:
        return self.course, round(self.offset_m, 3), round(self.speed_mps, 3)


@dataclass(frozen=True)
class LookaheadParams:
    capture_band_m: float = 0.2  # inside it the offset counts as closed
    min_scored_s: float = 10.0  # of tracking after capture, for an RMS to mean anything
    # Longer than the weave of a pure-pursuit loop at walking to 10 mph speeds (seconds),
    # shorter than a course's steady part, which the moving average keeps out.
    oscillation_window_s: float = 8.0
    oscillation_weight: float = 1.0
    tie_tolerance: float = 0.05  # relative: within it, scores are the same to us
    # The paper's tolerance "on the order of 1 ft", for the chosen schedule's every run.
    max_rms_m: float = 0.3
    max_overshoot_m: float = 0.3


@dataclass(frozen=True)
class RunScore:
    course: str
    offset_m: float
    speed_mps: float
    lookahead_m: float
    captured: bool
    capture_s: float  # from the run's start; inf when never
    overshoot_m: float  # past the line, on the side away from the start
    rms_m: float
    oscillation_m: float
    score_m: float


def score_run(run: TrackingRun, params: LookaheadParams = LookaheadParams()) -> RunScore:
    """The run's capture, RMS, oscillation and score (see the module's method)."""
    e, t = run.cross_track_m, run.t_s
    inside = np.flatnonzero(np.abs(e) <= params.capture_band_m)
    lookahead = run.candidate.lookahead_m(run.speed_mps)
    if inside.size == 0:
        return RunScore(
            run.course,
            run.offset_m,
            run.speed_mps,
            lookahead,
            False,
            math.inf,
            math.nan,
            math.nan,
            math.nan,
            math.inf,
        )
    first = int(inside[0])
    after = e[first:]
    side = math.copysign(1.0, e[0]) if abs(e[0]) > params.capture_band_m else 0.0
    overshoot = max(0.0, float(np.max(-side * after))) if side else 0.0
    rms = float(np.sqrt(np.mean(after**2)))
    step_s = float(np.median(np.diff(t)))
    window = max(1, round(params.oscillation_window_s / step_s))
    # Imported here: scipy.ndimage costs 0.13 s to import, and this module is imported
    # by the vehicle file's schema, so by every command and the daemon's start.
    import scipy.ndimage

    trend = scipy.ndimage.uniform_filter1d(after, size=window, mode="nearest")
    oscillation = float(np.sqrt(np.mean((after - trend) ** 2)))
    score = math.sqrt(rms**2 + params.oscillation_weight * oscillation**2)
    return RunScore(
        run.course,
        run.offset_m,
        run.speed_mps,
        lookahead,
        True,
        float(t[first] - t[0]),
        overshoot,
        rms,
        oscillation,
        score,
    )


@dataclass(frozen=True)
class CandidateScore:
    candidate: LookaheadCandidate
    runs: tuple[RunScore, ...]
    score_m: float  # mean over runs; inf when not usable
    usable: bool
    reason: str | None  # why not usable


@dataclass(frozen=True)
class SpeedRow:
    """One test speed: the best look-ahead there alone, and what the chosen schedule did."""

    speed_mps: float
    best_lookahead_m: float
    best_score_m: float
    chosen_lookahead_m: float
    chosen_score_m: float
    chosen_rms_m: float
    chosen_oscillation_m: float
    chosen_worst_overshoot_m: float
    chosen_mean_capture_s: float


@dataclass(frozen=True)
class LookaheadChoice:
    chosen: LookaheadCandidate | None
    candidates: tuple[CandidateScore, ...]  # in the order given
    per_speed: tuple[SpeedRow, ...]
    rejected: dict[str, int]  # runs, by reason
    rejected_candidates: dict[str, int]
    accepted: bool
    reasons: tuple[str, ...]
    method: str = METHOD


def _score_candidate(
    candidate: LookaheadCandidate,
    runs: list[TrackingRun],
    conditions: set[tuple[str, float, float]],
    params: LookaheadParams,
    rejected: dict[str, int],
) -> CandidateScore:
    scores = tuple(score_run(run, params) for run in runs)
    reason: str | None = None
    for run, score in zip(runs, scores, strict=True):
        if not score.captured:
            count(rejected, NEVER_CAPTURED)
            reason = reason or NEVER_CAPTURED
        elif run.t_s[-1] - run.t_s[0] - score.capture_s < params.min_scored_s:
            count(rejected, TOO_SHORT)
            reason = reason or TOO_SHORT
    if reason is None and {run.condition for run in runs} != conditions:
        reason = MISSING_RUNS
    if reason is not None:
        return CandidateScore(candidate, scores, math.inf, False, reason)
    return CandidateScore(
        candidate, scores, float(np.mean([s.score_m for s in scores])), True, None
    )


def _speed_rows(scored: list[CandidateScore], chosen: CandidateScore) -> tuple[SpeedRow, ...]:
    rows = []
    for speed in sorted({s.speed_mps for s in chosen.runs}):

        def at(c: CandidateScore, speed: float = speed) -> list[RunScore]:
            return [s for s in c.runs if s.speed_mps == speed]

        best = min(scored, key=lambda c: float(np.mean([s.score_m for s in at(c)])))
        mine = at(chosen)
        rows.append(
            SpeedRow(
                speed_mps=speed,
                best_lookahead_m=best.candidate.lookahead_m(speed),
                best_score_m=float(np.mean([s.score_m for s in at(best)])),
                chosen_lookahead_m=chosen.candidate.lookahead_m(speed),
                chosen_score_m=float(np.mean([s.score_m for s in mine])),
                chosen_rms_m=float(np.mean([s.rms_m for s in mine])),
                chosen_oscillation_m=float(np.mean([s.oscillation_m for s in mine])),
                chosen_worst_overshoot_m=max(s.overshoot_m for s in mine),
                chosen_mean_capture_s=float(np.mean([s.capture_s for s in mine])),
            )
        )
    return tuple(rows)


def _grid_edge(
    chosen: LookaheadCandidate, candidates: list[LookaheadCandidate], runs: Sequence[TrackingRun]
) -> str | None:
    """Why the choice is not bracketed, if it is not: at some test speed its look-ahead is
    the longest or the shortest of the grid, so a better one may lie beyond."""
    for speed in sorted({run.speed_mps for run in runs}):
        values = [c.lookahead_m(speed) for c in candidates]
        mine = chosen.lookahead_m(speed)
        if min(values) < max(values) and mine in (min(values), max(values)):
            end = "longest" if mine == max(values) else "shortest"
            return (
                f"at {speed:g} m/s the chosen look-ahead ({mine:.2f} m) is the grid's {end}: "
                "extend the grid past it"
            )
    return None


def choose_lookahead(
    runs: Sequence[TrackingRun], params: LookaheadParams = LookaheadParams()
) -> LookaheadChoice:
    """Score every candidate on its runs and choose the schedule (module docstring)."""
    if not runs:
        raise ValueError("no tracking runs given")
    by_candidate: dict[LookaheadCandidate, list[TrackingRun]] = {}
    for run in runs:
        by_candidate.setdefault(run.candidate, []).append(run)
    conditions = {run.condition for run in runs}
    rejected: dict[str, int] = {}
    rejected_candidates: dict[str, int] = {}
    scored = []
    for candidate, its_runs in by_candidate.items():
        score = _score_candidate(candidate, its_runs, conditions, params, rejected)
        if score.reason is not None:
            count(rejected_candidates, score.reason)
        scored.append(score)
    usable = [c for c in scored if c.usable]
    if not usable:
        failed = ("no candidate captured and tracked every condition",)
        return LookaheadChoice(
            None, tuple(scored), (), rejected, rejected_candidates, False, failed
        )
    best_score = min(c.score_m for c in usable)
    top = max(run.speed_mps for run in runs)
    ties = [c for c in usable if c.score_m <= best_score * (1.0 + params.tie_tolerance)]
    chosen = max(ties, key=lambda c: c.candidate.lookahead_m(top))
    reasons: list[str] = []
    worst_rms = max(s.rms_m for s in chosen.runs)
    if worst_rms > params.max_rms_m:
        reasons.append(
            f"the chosen schedule's worst run RMS {worst_rms:.2f} m > {params.max_rms_m} m"
        )
    worst_overshoot = max(s.overshoot_m for s in chosen.runs)
    if worst_overshoot > params.max_overshoot_m:
        reasons.append(
            f"the chosen schedule overshoots by {worst_overshoot:.2f} m > "
            f"{params.max_overshoot_m} m"
        )
    edge = _grid_edge(chosen.candidate, [c.candidate for c in scored], runs)
    if edge:
        reasons.append(edge)
    return LookaheadChoice(
        chosen=chosen.candidate,
        candidates=tuple(scored),
        per_speed=_speed_rows(usable, chosen),
        rejected=rejected,
        rejected_candidates=rejected_candidates,
        accepted=not reasons,
        reasons=tuple(reasons),
    )
