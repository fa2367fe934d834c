"""The look-ahead tuning's choice against an exhaustive search on the same simulator.

Each seed drives the vehicle file's default tuning (``[lookahead_tuning]``: the paper's
line and arc runs at 0 and ±3 m offsets, 5 and 10 mph, three candidate gains) faster than
real time through the daemon's own tuning code on the simulated Husky with fixes of σ 2 cm
(``appliance.sim.tuning_run``), and fits the daemon's view of the runs (the blended pose's
cross-track error) as `dbw calibrate lookahead` does. The same runs are then driven for
every schedule of a finer grid (offsets 0, 0.5, 1 m; gains 0.3 to 0.8 s in steps of
0.05 s), same seed, and
each candidate is judged by the truth (the true anchor's error): the mean over its runs of
the RMS after capture, and the fit's score (RMS and oscillation).

    python -m benchmarks.bench_lookahead [SEEDS]      # 3 by default, ~5 min each

Figures, printed and never asserted: the chosen schedule's truth RMS (and score) over the
best of the exhaustive grid's (the issue's goal: within 10 %), the tuning's runs, their
simulated duration (without the technician's drives back to a start) and distance.
"""

from __future__ import annotations

import sys

import numpy as np

from appliance.config import load_config
from appliance.config.tuning_models import LookaheadTuningSettings
from appliance.guidance.lookahead_samples import collect_runs
from appliance.maneuvers.lookahead_step import LookaheadStep
from appliance.maneuvers.steps import StepContext
from appliance.sim.tuning_run import TuningSimParams, run_tuning
from benchmarks.stats import summarize
from calibration.lookahead import CandidateScore, LookaheadCandidate, choose_lookahead

EXHAUSTIVE = LookaheadTuningSettings(
    offsets_m=(0.0, 0.5, 1.0), gains_s=tuple(round(0.3 + 0.05 * g, 2) for g in range(11))
)


def truth_scores(
    settings: LookaheadTuningSettings, seed: int
) -> dict[LookaheadCandidate, CandidateScore]:
    """Every candidate of ``settings`` driven and judged by the truth."""
    config = load_config("husky-sim").model_copy(update={"lookahead_tuning": settings})
    driven = run_tuning(config, settings, TuningSimParams(seed=seed))
    params = LookaheadStep(StepContext(config, None)).params
    collected = collect_runs(driven.truth, params, settings.candidates())
    choice = choose_lookahead(collected.runs, settings.fit_params())
    return {c.candidate: c for c in choice.candidates}


def mean_rms(score: CandidateScore) -> float:
    return float(np.mean([r.rms_m for r in score.runs]))


def main(seeds: int = 3) -> None:
    rms_ratio, score_ratio, durations, distances, runs = [], [], [], [], []
    for seed in range(seeds):
        settings = LookaheadTuningSettings()
        config = load_config("husky-sim").model_copy(update={"lookahead_tuning": settings})
        driven = run_tuning(config, settings, TuningSimParams(seed=seed))
        step = LookaheadStep(StepContext(config, None))
        samples = [
            {
                "t_s": s.t_s,
                "tune_run": s.run,
                "tune_phase": s.phase,
                "cross_track_m": s.cross_track_m,
                "speed_mps": s.speed_mps,
            }
            for s in driven.samples
        ]
        report = step.fit(samples, None)
        chosen = report.figures["chosen"]
        durations.append(float(sum(driven.run_durations_s.values())))
        distances.append(driven.distance_m)
        runs.append(len(step.params.runs))
        if chosen is None:
            print(f"seed {seed}: no choice ({'; '.join(report.reasons)})")
            continue
        grid = truth_scores(EXHAUSTIVE, seed)
        usable = [c for c in grid.values() if c.usable]
        mine = next(
            c
            for c in usable
            if c.candidate.offset_m == chosen["offset_m"] and c.candidate.gain_s == chosen["gain_s"]
        )
        best_rms = min(usable, key=mean_rms)
        best_score = min(usable, key=lambda c: c.score_m)
        rms_ratio.append(mean_rms(mine) / mean_rms(best_rms))
        score_ratio.append(mine.score_m / best_score.score_m)
        print(
            f"seed {seed}: chosen {chosen['offset_m']} + {chosen['gain_s']} s x v "
            f"({'accepted' if report.accepted else 'refused'}): truth RMS "
            f"{100 * mean_rms(mine):.2f} cm, best of {len(usable)} "
            f"{100 * mean_rms(best_rms):.2f} cm ({best_rms.candidate.offset_m} + "
            f"{best_rms.candidate.gain_s} s x v); score {100 * mine.score_m:.2f} vs best "
            f"{100 * best_score.score_m:.2f} cm ({best_score.candidate.offset_m} + "
            f"{best_score.candidate.gain_s} s x v)"
        )
    print(summarize("chosen RMS / exhaustive best RMS", rms_ratio, "x"))
    print(summarize("chosen score / exhaustive best score", score_ratio, "x"))
    print(summarize("tuning runs", runs, "runs"))
    print(summarize("tuning duration (simulated, driving only)", durations, "s"))
    print(summarize("tuning distance", distances, "m"))


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 3)
