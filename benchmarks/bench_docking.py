"""Docking to the launcher from random starts: the issue's figures, printed, never asserted.

Each approach is `dbw sim dock` (``appliance.sim.dock_run``): the daemon's perception,
localizer and docking controller on the simulated flat-bed, judged by the truth. Starts
are drawn from a fixed seed: the front end 10 m out, ±1 m lateral, ±5° heading; each
start also draws its own scanner errors (a different vehicle each time). Three
conditions: realistic scanners calibrated (the localizer knows each true mount and range
offset, as a perfect `dbw calibrate scanners` would give), realistic uncalibrated (only
the configured mounts: the alignment gate then finds the estimate too uncertain to go in,
and refuses), the same with the gate's certainty check off (what the uncalibrated error
would do at the troughs), and the ideal scanner.

Run: ``python -m benchmarks.bench_docking [RUNS [WORKERS [CONDITION ...]]]`` (100 starts,
2 workers and every condition by default; a condition by its name as printed). The
approaches share the cores there, so their real-time factor is not `dbw sim dock`'s:
``python -m benchmarks.bench_docking speed [RUNS]`` runs approaches one at a time (5 by
default), inline and with the scans rendered by a worker on the other core.

Figures per condition: success rate (docked, both teeth inside their troughs, no tooth at
a trough misaligned), the lateral error at the teeth and the heading error (median, p95,
max), pattern switches per approach (median, max), attempts, time per approach, the
estimate's mean NEES against the truth per approach (whole, and within 2 m of the
board; 3 if its covariance is right), real-time factor.
"""

from __future__ import annotations

import math
import sys
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace

import numpy as np

from appliance.config import load_config
from appliance.guidance.docking import DockingParams
from appliance.sim.dock_run import NEAR_GAP_M, DockResult, DockRunParams, run_dock

CONDITIONS = {
    "realistic, calibrated": DockRunParams(),
    "realistic, uncalibrated": DockRunParams(calibrated=False),
    # What-if: the gate's certainty check off, to show what the uncalibrated estimate's
    # extra error would do at the troughs (the shipped controller refuses instead).
    "realistic, uncalibrated, gate sigma check off": DockRunParams(
        calibrated=False, docking=DockingParams(gate_sigma_m=math.inf)
    ),
    "ideal scanner": DockRunParams(ideal_scanner=True),
}


def starts(runs: int, seed: int = 20261203) -> list[tuple[float, float, int]]:
    rng = np.random.default_rng(seed)
    return [
        (float(rng.uniform(-1.0, 1.0)), float(rng.uniform(-5.0, 5.0)), int(rng.integers(2**31)))
        for _ in range(runs)
    ]


def _one(job: tuple[DockRunParams, float, float, int]) -> DockResult:
    base, y_m, heading_deg, seed = job
    params = replace(base, start_y_m=y_m, start_heading_deg=heading_deg, seed=seed)
    return run_dock(load_config("flatbed"), params)


def _figures(name: str, values: list[float], unit: str) -> str:
    data = np.asarray(values, dtype=float)
    if data.size == 0:
        return f"  {name}: none"
    p50, p95 = np.percentile(data, [50, 95])
    return f"  {name}: median {p50:.3f} {unit}, p95 {p95:.3f} {unit}, max {data.max():.3f} {unit}"


def report(name: str, results: list[DockResult]) -> None:
    docked = [r for r in results if r.success]
    share = 100.0 * len(docked) / len(results)
    print(f"{name}: {len(docked)} of {len(results)} docked ({share:.0f} %)")
    lateral = [max(abs(t) for t in r.teeth_lateral_m) * 1000.0 for r in docked]
    heading = [abs(r.heading_error_deg) for r in docked]
    print(_figures("lateral error at the teeth (docked)", lateral, "mm"))
    print(_figures("heading error (docked)", heading, "deg"))
    switches = [r.pattern_switches for r in results]
    print(f"  pattern switches: median {np.median(switches):.0f}, max {max(switches)}")
    print(f"  more than one attempt: {sum(r.attempts > 1 for r in results)}")
    print(
        f"  a tooth at a trough misaligned (contact): {sum(r.contact_misaligned for r in results)}"
    )
    failures: dict[str, int] = {}
    for r in results:
        if not r.success:
            # The controller's own "docked", with a tooth at a trough or outside its gap.
            reason = "stopped as docked, the teeth not in" if r.reason == "docked" else r.reason
            failures[reason] = failures.get(reason, 0) + 1
    if failures:
        print(f"  not docked: {failures}")
    for label, values in (
        ("whole approach", [r.mean_nees for r in results]),
        (f"within {NEAR_GAP_M:g} m of the board", [r.mean_nees_near for r in results]),
    ):
        kept = [v for v in values if math.isfinite(v)]
        print(_figures(f"estimate's mean NEES per approach, {label} (3 if consistent)", kept, ""))
    print(_figures("simulated time per approach", [r.sim_time_s for r in results], "s"))
    print(_figures("real-time factor", [r.real_time_factor for r in results], "x"))


def speed(runs: int) -> None:
    """`dbw sim dock`'s own speed: approaches one after another, nothing else running,
    the scans rendered inline and by the forked worker (the command's default on two
    cores); the same runs, so only the wall time differs."""
    print(f"`dbw sim dock` alone, {runs} approaches one after another")
    for label, worker in (("scans rendered inline (--one-core)", False), ("by a worker", True)):
        results = [
            _one((replace(CONDITIONS["realistic, calibrated"], render_worker=worker), *job))
            for job in starts(runs)
        ]
        print(f"  {label}:")
        print("  " + _figures("real-time factor", [r.real_time_factor for r in results], "x"))


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["speed"]:
        speed(int(args[1]) if len(args) > 1 else 5)
        return
    runs = int(args[0]) if args else 100
    workers = int(args[1]) if len(args) > 1 else 2
    chosen = args[2:] or list(CONDITIONS)  # e.g. "realistic, calibrated" alone
    unknown = [name for name in chosen if name not in CONDITIONS]
    if unknown:
        sys.exit(f"unknown condition {unknown}; the conditions are {list(CONDITIONS)}")
    jobs = starts(runs)
    print(f"docking from {runs} random starts (10 m out, ±1 m lateral, ±5° heading)")
    print(f"{workers} worker processes")
    with ProcessPoolExecutor(max_workers=workers) as pool:
        for name in chosen:
            base = CONDITIONS[name]
            results = list(pool.map(_one, [(base, *job) for job in jobs]))
            report(name, results)


if __name__ == "__main__":
    main()
