"""The merged map: the vehicle's pallets, plus the worker's the vehicle has not seen
(Kinouchi et al., section 2.2 (2) (iii)-(iv), and the "reference area" of 2.1).

A worker pallet enters the vehicle's map with its pose moved by ``T⁻¹`` and a covariance
that holds both its own and the fit's uncertainty, because a worker's terminal is not an
industrial sensor: the paper never drives to a worker's pallet pose, it drives to where
the vehicle can see that pose's *reference area* and detects the pallet again. So each
added pallet carries that area: a disc that holds the whole pallet whenever its centre is
within ``reference_area_sigmas`` standard deviations of where the map puts it.

The steps (`merge_maps`): associate with the floor marker's ``T0`` (wide gates), fit
robustly (if too few pairs agree, again over every candidate pair within a wider gate,
the floor marker ruling out look-alike transforms); associate again with the fitted
transform (narrow gates: pallets ``T0`` was too far off for) and refit if that finds
more pairs; then every worker pallet that no vehicle pallet matches under the final
transform is added.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from appliance.mapping.association import (
    AssociationGate,
    Pair,
    RobustFit,
    RobustParams,
    associate,
    candidate_pairs,
    robust_transform,
    t0_covariance,
)
from appliance.mapping.pallets import Pallet, PalletMap
from appliance.mapping.transform_fit import (
    DEFAULT_W_M2_PER_RAD2,
    MergeRefusal,
    TransformFit,
    solve_transform,
)
from drivers.geometry import Pose2D

__all__ = [
    "DEFAULT_W_M2_PER_RAD2",
    "AssociationGate",
    "MergeParams",
    "MergeRefusal",
    "MergeResult",
    "MergedPallet",
    "ReferenceArea",
    "RobustParams",
    "TransformFit",
    "associate",
    "candidate_pairs",
    "merge_maps",
    "move_worker_pallet",
    "reference_area",
    "robust_transform",
    "solve_transform",
]


# Two pallets on the floor stand at least a pallet's width apart, centre to centre (0.8 m
# side by side): two readings nearer than half of that are one pallet.
SAME_PALLET_M = 0.4


@dataclass(frozen=True)
class MergeParams:
    """The gates of `associate`, the consensus and fit of `robust_transform` (w among
    them, `DEFAULT_W_M2_PER_RAD2` says why its default), the reference areas' margin."""

    gate: AssociationGate = field(default_factory=AssociationGate)
    robust: RobustParams = field(default_factory=RobustParams)
    # How many standard deviations (along the worst axis) of an added pallet's position
    # its reference area allows: with 3, a 2D Gaussian centre falls inside at least
    # 98.9 % of times (99.5 % of footprints in benchmarks/bench_map_merge.py).
    reference_area_sigmas: float = 3.0


@dataclass(frozen=True)
class ReferenceArea:
    """Where the vehicle must look to detect a worker's pallet again: a disc in the
    vehicle map, of the footprint's half diagonal plus k sigma of the centre's position."""

    centre_x_m: float
    centre_y_m: float
    radius_m: float

    def contains(self, x_m: float, y_m: float) -> bool:
        return math.hypot(x_m - self.centre_x_m, y_m - self.centre_y_m) <= self.radius_m


@dataclass(frozen=True)
class MergedPallet:
    """One pallet of the merged map, and where it came from."""

    pallet: Pallet  # in the vehicle map's frame
    from_worker: bool
    vehicle_index: int | None  # into the vehicle's map; None for an added worker pallet
    worker_index: int | None  # into the worker's map, when the worker saw it
    reference_area: ReferenceArea | None  # for an added worker pallet only


@dataclass(frozen=True, eq=False)
class MergeResult:
    """The merged map: the vehicle's pallets first, in its order, then the added ones."""

    pallets: tuple[MergedPallet, ...]
    robust: RobustFit  # the fit, its pairs, the pairs it rejected
    frame: str  # the vehicle map's

    @property
    def fit(self) -> TransformFit:
        return self.robust.fit

    @property
    def worker_in_vehicle(self) -> Pose2D:
        return self.robust.fit.worker_in_vehicle

    @property
    def added(self) -> tuple[MergedPallet, ...]:
        return tuple(p for p in self.pallets if p.from_worker)

    def pallet_map(self, source: str = "") -> PalletMap:
        return PalletMap(tuple(p.pallet for p in self.pallets), self.frame, source)


def move_worker_pallet(pallet: Pallet, fit: TransformFit) -> Pallet:
    """A worker pallet in the vehicle map: pose ``T⁻¹ ∘ p``, covariance the worker's
    rotated with it plus ``A Σ_T Aᵀ``, ``A`` the Jacobian of ``T⁻¹ ∘ p`` with respect to
    ``T``'s (x, y, θ) (first order; the pallet was not in the fit, so the two are
    independent). Yaw wrapped to [-π, π]."""
    x, y, theta = fit.vehicle_in_worker
    c, s = math.cos(theta), math.sin(theta)
    rotation_t = np.array([[c, s], [-s, c]])  # Rᵀ: worker into vehicle
    offset = np.array([pallet.x_m - x, pallet.y_m - y])
    position = rotation_t @ offset
    jacobian = np.zeros((3, 3))
    jacobian[:2, :2] = -rotation_t
    jacobian[:2, 2] = np.array([[-s, c], [-c, -s]]) @ offset  # d(Rᵀ)/dθ (p − t)
    jacobian[2, 2] = -1.0
    rotate = np.eye(3)
    rotate[:2, :2] = rotation_t
    covariance = rotate @ pallet.covariance @ rotate.T + jacobian @ fit.covariance @ jacobian.T
    return Pallet(
        float(position[0]),
        float(position[1]),
        math.remainder(pallet.yaw_rad - theta, 2.0 * math.pi),
        0.5 * (covariance + covariance.T),
        pallet.kind,
        pallet.name,
        pallet.support,
    )


def reference_area(pallet: Pallet, sigmas: float) -> ReferenceArea:
    """The disc around ``pallet`` that holds its whole footprint, whatever its yaw, if the
    true centre is within ``sigmas`` standard deviations along the covariance's worst axis."""
    half_diagonal_m = 0.5 * math.hypot(pallet.kind.length_m, pallet.kind.width_m)
    worst_m2 = float(np.linalg.eigvalsh(pallet.covariance[:2, :2])[-1])
    return ReferenceArea(
        pallet.x_m, pallet.y_m, half_diagonal_m + sigmas * math.sqrt(max(worst_m2, 0.0))
    )


def _better(candidate: RobustFit | MergeRefusal, incumbent: RobustFit) -> bool:
    if isinstance(candidate, MergeRefusal):
        return False
    more = len(candidate.inliers) - len(incumbent.inliers)
    return more > 0 or (more == 0 and candidate.fit.cost < incumbent.fit.cost)


def merge_maps(
    vehicle: PalletMap,
    worker: PalletMap,
    t0: Pose2D,
    params: MergeParams,
    alternatives: Sequence[Pallet] = (),
) -> MergeResult | MergeRefusal:
    """The vehicle's map completed by the worker's. ``t0`` is the floor marker's estimate
    of the worker map's frame in the vehicle map's (the fit's ``T⁻¹``, not ``T``).

    ``alternatives`` are the worker's readings of faces whose kind its map could not
    tell (a 1.1 m face: a 1100x1100's side or a 1200x800's long one), one per kind: they
    may pair with the vehicle's pallets and so fix T, but are never added themselves
    (their indices follow the map's). With them, an added worker pallet on top of one
    the vehicle sees (centres nearer than `SAME_PALLET_M`) is that pallet misread, and
    is left out."""
    definite = len(worker.pallets)
    if alternatives:
        worker = PalletMap(tuple(worker.pallets) + tuple(alternatives), worker.frame, worker.source)
    if not all(map(math.isfinite, t0)):
        return MergeRefusal("the floor marker's T0 is not finite")
    prior = (t0, t0_covariance(params.gate))
    pairs: list[Pair] = associate(vehicle, worker, t0, params.gate)
    robust = robust_transform(vehicle, worker, pairs, params.robust, prior)
    if isinstance(robust, MergeRefusal):
        candidates = candidate_pairs(vehicle, worker, t0, params.gate)
        if len(candidates) > len(pairs):
            robust = robust_transform(vehicle, worker, candidates, params.robust, prior)
    if isinstance(robust, MergeRefusal):
        return MergeRefusal(f"with the floor marker's T0, {len(pairs)} pairs: {robust.reason}")
    fit = robust.fit
    again = associate(
        vehicle, worker, fit.worker_in_vehicle, params.gate, fit.worker_in_vehicle_covariance()
    )
    if set(again) != set(robust.inliers):
        retried = robust_transform(vehicle, worker, again, params.robust)
        if _better(retried, robust):
            assert not isinstance(retried, MergeRefusal)
            robust = retried
    fit = robust.fit
    if not np.isfinite(fit.covariance).all():
        return MergeRefusal("the fitted transform's covariance is not finite")
    final = associate(
        vehicle, worker, fit.worker_in_vehicle, params.gate, fit.worker_in_vehicle_covariance()
    )
    worker_of: dict[int, int] = dict(robust.inliers)
    in_fit = set(worker_of.values())
    for i, j in final:  # the fit's own pairs win over a re-association
        if i not in worker_of and j not in in_fit:
            worker_of[i] = j
    # Seen: in the fit, or matching a vehicle pallet under it (a pair the consensus
    # rejected may still be the vehicle's pallet, just not the one it was paired with).
    seen = {j for _, j in final} | {j for _, j in robust.inliers}
    merged = [
        MergedPallet(pallet, False, i, worker_of.get(i), None)
        for i, pallet in enumerate(vehicle.pallets)
    ]
    for j, pallet in enumerate(worker.pallets[:definite]):
        if j in seen:
            continue
        moved = move_worker_pallet(pallet, fit)
        if alternatives and any(
            math.hypot(moved.x_m - m.pallet.x_m, moved.y_m - m.pallet.y_m) < SAME_PALLET_M
            for m in merged
        ):
            continue
        area = reference_area(moved, params.reference_area_sigmas)
        merged.append(MergedPallet(moved, True, None, j, area))
    return MergeResult(tuple(merged), robust, vehicle.frame)
