"""Accuracy and cost of merging a worker's pallet map into the vehicle's (Kinouchi et al.,
section 2.2): `appliance.mapping.merge`.

Each trial: 8-12 pallets (centres at least 1.5 m apart, either kind) over 20 x 20 m; the
worker's terminal sees them all, with 20 mm and 1° of noise (1 sigma per axis); the
vehicle sees 70 % of them (blind areas), with 10 mm and 0.5°. The worker's frame is
anywhere on the site at any heading (the floor marker), and ``T0``, its estimate, is off
by 50 mm and 2° (1 sigma).

Figures:

- the error of ``T`` (vehicle map into worker map) from `merge_maps`: translation (mm)
  and angle (deg), median and p95, and the error of the pallets it adds (where the
  vehicle must go), with how often their reference areas hold the true footprint;
- the same error from `robust_transform` with one wrong association in five injected
  (a vehicle pallet paired with a worker pallet the vehicle never saw), how often all
  wrong ones were rejected, and the fit on the same pairs without the consensus
  (`solve_transform` over every pair, what a merge without it would do);
- the error against w (the posture weight) on the same trials;
- the time per merge (median, p99).

Run: ``python -m benchmarks.bench_map_merge [TRIALS]`` (default 1000). Nothing here is
asserted.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from appliance.mapping.association import RobustFit, RobustParams, robust_transform
from appliance.mapping.merge import MergeParams, MergeResult, merge_maps
from appliance.mapping.pallets import (
    Pallet,
    PalletKind,
    PalletMap,
    inverse_pose,
    transform_pallet,
)
from appliance.mapping.transform_fit import DEFAULT_W_M2_PER_RAD2, TransformFit, solve_transform
from benchmarks.stats import summarize
from drivers.geometry import Pose2D

TRIALS = 1000
WORKER_SIGMAS = (0.02, 0.02, math.radians(1.0))
VEHICLE_SIGMAS = (0.01, 0.01, math.radians(0.5))
T0_SIGMAS = (0.05, 0.05, math.radians(2.0))
SEEN_FRACTION = 0.7


@dataclass(frozen=True)
class Trial:
    truth: tuple[Pallet, ...]  # vehicle map frame
    vehicle: PalletMap
    worker: PalletMap
    worker_in_vehicle: Pose2D
    t0: Pose2D


def _noisy(pallet: Pallet, sigmas: tuple[float, float, float], rng: np.random.Generator) -> Pallet:
    noise = rng.normal(0.0, sigmas)
    return Pallet(
        pallet.x_m + noise[0],
        pallet.y_m + noise[1],
        pallet.yaw_rad + noise[2],
        np.diag(np.square(sigmas)),
        pallet.kind,
        pallet.name,
    )


def _trial(rng: np.random.Generator) -> Trial:
    count = int(rng.integers(8, 13))
    centres: list[np.ndarray] = []
    while len(centres) < count:
        centre = rng.uniform(0.0, 20.0, 2)
        if all(math.dist(centre, other) >= 1.5 for other in centres):
            centres.append(centre)
    kinds = (PalletKind.JIS, PalletKind.EUR)
    truth = tuple(
        Pallet(x, y, rng.uniform(-math.pi, math.pi), np.zeros((3, 3)), kinds[rng.integers(2)])
        for x, y in centres
    )
    x_m, y_m = rng.uniform(0.0, 20.0, 2)
    marker = Pose2D(float(x_m), float(y_m), float(rng.uniform(-math.pi, math.pi)))
    vehicle_in_worker = inverse_pose(marker)
    seen = max(5, round(SEEN_FRACTION * count))
    worker = tuple(
        _noisy(transform_pallet(vehicle_in_worker, p), WORKER_SIGMAS, rng) for p in truth
    )
    vehicle = tuple(_noisy(p, VEHICLE_SIGMAS, rng) for p in truth[:seen])
    t0 = Pose2D(*(float(v) for v in np.array(marker) + rng.normal(0.0, T0_SIGMAS)))
    return Trial(truth, PalletMap(vehicle, "vehicle"), PalletMap(worker, "worker"), marker, t0)


def _error(fit: TransformFit, trial: Trial) -> tuple[float, float]:
    """Translation (mm) and angle (deg) error of the fit's T (vehicle into worker)."""
    truth = inverse_pose(trial.worker_in_vehicle)
    x, y, yaw = fit.vehicle_in_worker
    return (
        1e3 * math.hypot(x - truth.x_m, y - truth.y_m),
        abs(math.degrees(math.remainder(yaw - truth.yaw_rad, 2.0 * math.pi))),
    )


def _corrupt(
    pairs: list[tuple[int, int]], trial: Trial, rng: np.random.Generator, swap: bool
) -> tuple[list[tuple[int, int]], set[tuple[int, int]]]:
    """One pair in five (at least one) paired with a worker pallet the vehicle never saw,
    or (``swap``) two pairs' worker pallets swapped: two wrong pairs."""
    corrupted = list(pairs)
    if swap:
        a, b = (int(k) for k in rng.choice(len(pairs), 2, replace=False))
        corrupted[a], corrupted[b] = (pairs[a][0], pairs[b][1]), (pairs[b][0], pairs[a][1])
        return corrupted, {corrupted[a], corrupted[b]}
    unseen = list(range(len(trial.vehicle), len(trial.worker)))
    count = min(max(1, len(pairs) // 5), len(unseen))
    wrong = set()
    for k, j in zip(
        rng.choice(len(pairs), count, replace=False),
        rng.choice(unseen, count, replace=False),
        strict=True,
    ):
        corrupted[k] = (corrupted[k][0], int(j))
        wrong.add(corrupted[k])
    return corrupted, wrong


def _plain_fit(trial: Trial, pairs: list[tuple[int, int]]) -> TransformFit | None:
    """`solve_transform` over every pair, wrong ones too: a merge without the consensus."""
    vehicle = [trial.vehicle.pallets[i] for i, _ in pairs]
    worker = [trial.worker.pallets[j] for _, j in pairs]
    fit = solve_transform(
        np.array([(p.x_m, p.y_m) for p in vehicle]),
        np.array([p.yaw_rad for p in vehicle]),
        np.array([(p.x_m, p.y_m) for p in worker]),
        np.array([p.yaw_rad for p in worker]),
        np.array([p.kind.symmetry_rad for p in vehicle]),
    )
    return fit if isinstance(fit, TransformFit) else None


def _with_wrong_pairs(
    runs: list[Trial], params: RobustParams, swap: bool, rng: np.random.Generator
) -> tuple[list[str], list[float]]:
    """Figures of `robust_transform` on the true pairs with wrong ones injected."""
    robust: list[tuple[float, float]] = []
    naive: list[tuple[float, float]] = []
    rejected_all = wrong_total = false_rejections = refused = 0
    durations_ms: list[float] = []
    for trial in runs:
        pairs = [(i, i) for i in range(len(trial.vehicle))]  # the scene's true pairs
        corrupted, wrong = _corrupt(pairs, trial, rng, swap)
        started = time.perf_counter()
        result = robust_transform(trial.vehicle, trial.worker, corrupted, params)
        durations_ms.append((time.perf_counter() - started) * 1e3)
        plain = _plain_fit(trial, corrupted)
        if plain is not None:
            naive.append(_error(plain, trial))
        if not isinstance(result, RobustFit):
            refused += 1
            continue
        robust.append(_error(result.fit, trial))
        rejected = {(r.vehicle_index, r.worker_index) for r in result.rejected}
        wrong_total += len(wrong)
        rejected_all += wrong <= rejected
        false_rejections += len(rejected - wrong)
    label = "two pairs swapped" if swap else "one pair in five wrong"
    return [
        _line(f"robust_transform, {label} (refused {refused})", robust),
        f"  every wrong pair rejected in {rejected_all} of {len(robust)} fits "
        f"({wrong_total} wrong pairs), right pairs rejected: {false_rejections}",
        _line("  the same pairs fitted without the consensus (solve_transform)", naive),
    ], durations_ms


def _line(label: str, errors: list[tuple[float, float]]) -> str:
    if not errors:
        return f"{label}: no fits"
    data = np.array(errors)
    (t50, a50), (t95, a95) = np.percentile(data, [50, 95], axis=0)
    return (
        f"{label}: translation median {t50:.1f} mm, p95 {t95:.1f} mm; "
        f"angle median {a50:.3f} deg, p95 {a95:.3f} deg (n={len(errors)})"
    )


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    trials = int(args[0]) if args else TRIALS
    params = MergeParams()
    rng = np.random.default_rng(2024)
    runs = [_trial(rng) for _ in range(trials)]

    clean: list[tuple[float, float]] = []
    added_mm: list[float] = []
    inside = refused = 0
    durations_ms: list[float] = []
    nees: list[float] = []
    for trial in runs:
        started = time.perf_counter()
        result = merge_maps(trial.vehicle, trial.worker, trial.t0, params)
        durations_ms.append((time.perf_counter() - started) * 1e3)
        if not isinstance(result, MergeResult):
            refused += 1
            continue
        clean.append(_error(result.fit, trial))
        error = np.array(result.fit.vehicle_in_worker) - inverse_pose(trial.worker_in_vehicle)
        error[2] = math.remainder(error[2], 2.0 * math.pi)
        nees.append(float(error @ np.linalg.solve(result.fit.covariance, error)))
        for added in result.added:
            truth = trial.truth[added.worker_index or 0]
            added_mm.append(
                1e3 * math.hypot(added.pallet.x_m - truth.x_m, added.pallet.y_m - truth.y_m)
            )
            area = added.reference_area
            inside += area is not None and all(area.contains(*c) for c in truth.corners_xy_m())
    print(_line(f"merge_maps, T0 off by 50 mm and 2 deg (refused {refused})", clean))
    print(f"  T's mean Mahalanobis² error under its covariance {np.mean(nees):.2f} (3 if right)")
    p50, p95 = np.percentile(added_mm, [50, 95])
    print(
        f"added worker pallets in the vehicle map: position error median {p50:.1f} mm, "
        f"p95 {p95:.1f} mm; footprint inside its reference area {inside / len(added_mm):.1%} "
        f"(n={len(added_mm)})"
    )
    robust_ms: list[float] = []
    for swap in (False, True):
        lines, durations = _with_wrong_pairs(runs, params.robust, swap, rng)
        print("\n".join(lines))
        robust_ms += durations
    for shared in (None, 3):  # every common pallet; the first three only
        for w in (0.0, 0.33, DEFAULT_W_M2_PER_RAD2):
            errors = []
            for trial in runs:
                pairs = [(i, i) for i in range(len(trial.vehicle))][:shared]
                fit = robust_transform(
                    trial.vehicle, trial.worker, pairs, RobustParams(w_m2_per_rad2=w)
                )
                if isinstance(fit, RobustFit):
                    errors.append(_error(fit.fit, trial))
            which = "all common pallets" if shared is None else f"{shared} common pallets"
            print(_line(f"no wrong pairs, {which}, w = {w:.2f} m²/rad²", errors))
    print(summarize("time per merge_maps (associate, consensus, again, merge)", durations_ms, "ms"))
    print(summarize("time per robust_transform", robust_ms, "ms"))


if __name__ == "__main__":
    main()
