"""Guidance to a pallet in the blind area: the issue's figures, printed, never asserted.

Each run is `dbw sim pallet` (``appliance.sim.pallet_run``): a simulated worker's 3D map
(consumer terminal; trial 2 at its worst), the vehicle's own pallets from its first
scans, the merge from the floor marker, the plan, the approach with the pallet detected
again, judged by the truth at the fork tips. First the paper's three trials (seed 1),
then RUNS seeded runs cycling through the three trials (each seed draws its own worker
walk errors, scanner errors, odometry errors and noise).

Run: ``python -m benchmarks.bench_pallet [RUNS [WORKERS [FORM ...]]]`` (100 runs, 2
workers, both forms of the worker's map: ``cloud`` (the 3D cloud, its pallets found
through proximity points) and ``objects`` (the terminal's own list of pallets)).

Figures: success rate; translation error at the fork tips (hypot of the lateral offset
from the pallet's axis and the stop before or past its face) and angle error (median,
p95, max); the merge's error (the fitted worker frame against its truth); simulated time
and the real-time factor per run. Failures are listed with their reasons.
"""

from __future__ import annotations

import sys
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from appliance.config import load_config
from appliance.sim.pallet_run import TRIALS, PalletResult, PalletRunParams, run_pallet
from benchmarks.stats import summarize


def _one(job: tuple[int, int, str]) -> PalletResult:
    trial, seed, form = job
    params = PalletRunParams(trial=trial, seed=seed, worker_form=form)
    return run_pallet(load_config("forklift-sim"), params)


def _line(result: PalletResult) -> str:
    return (
        f"trial {result.trial} seed {result.seed}: "
        f"{'at the pallet' if result.success else 'FAILED: ' + result.reason}; "
        f"translation {result.translation_error_m * 1e3:.2f} mm (lateral "
        f"{result.tips_lateral_m * 1e3:+.2f}, along {result.tips_along_m * 1e3:+.2f}), angle "
        f"{result.heading_error_deg:+.3f} deg; merge {result.merge_error_m * 1e3:.1f} mm "
        f"{result.merge_error_deg:.2f} deg; {result.sim_time_s:.0f} s simulated, "
        f"{result.real_time_factor:.1f}x real time"
    )


def report(results: list[PalletResult]) -> None:
    done = [r for r in results if r.success]
    print(f"  success: {len(done)} of {len(results)}")
    if done:
        translation = [r.translation_error_m * 1e3 for r in done]
        angle = [abs(r.heading_error_deg) for r in done]
        p95_t, p95_a = np.percentile(translation, 95), np.percentile(angle, 95)
        print("  " + summarize("translation error", translation, "mm") + f", p95 {p95_t:.3f} mm")
        print("  " + summarize("angle error", angle, "deg") + f", p95 {p95_a:.4f} deg")
        print("  " + summarize("merge error", [r.merge_error_m * 1e3 for r in done], "mm"))
        print("  " + summarize("merge angle error", [r.merge_error_deg for r in done], "deg"))
        print("  " + summarize("simulated time", [r.sim_time_s for r in done], "s"))
        print("  " + summarize("real-time factor", [r.real_time_factor for r in done], "x"))
    for failed in (r for r in results if not r.success):
        print("  " + _line(failed))


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    runs = int(args[0]) if args else 100
    workers = int(args[1]) if len(args) > 1 else 2
    forms = args[2:] or ["cloud", "objects"]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for form in forms:
            print(f"worker's map as a {'3D cloud' if form == 'cloud' else 'list of objects'}")
            print("the paper's three trials (seed 1; trial 2: the terminal at its worst)")
            for result in pool.map(_one, [(trial, 1, form) for trial in TRIALS]):
                print("  " + _line(result))
            print(f"{runs} seeded runs, trials 1-3 in turn, {workers} worker processes")
            jobs = [(1 + k % len(TRIALS), 1000 + k, form) for k in range(runs)]
            report(list(pool.map(_one, jobs)))


if __name__ == "__main__":
    main()
