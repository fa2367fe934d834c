"""Which vehicle pallet is which worker pallet (Kinouchi et al.'s step (iii), collation),
and which of those pairings to believe (a consensus that survives wrong ones).

Direction: ``worker_in_vehicle`` is the pose of the worker map's frame in the vehicle
map's, the floor marker's ``T0`` (the inverse of the fit's ``T``, see
`appliance.mapping.transform_fit`): a worker pallet ``p`` is at ``T0 ∘ p`` in the vehicle
map. Pairs are ``(vehicle_index, worker_index)`` into the two maps' pallets.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from scipy.optimize import linear_sum_assignment

from appliance.mapping.pallets import FloatArray, PalletMap
from appliance.mapping.transform_fit import (
    DEFAULT_W_M2_PER_RAD2,
    MergeRefusal,
    TransformFit,
    solve_transform,
)
from drivers.geometry import Pose2D

Pair = tuple[int, int]
BoolArray = npt.NDArray[np.bool_]
_FLOOR_M2 = 1e-6  # no detection is better than a millimetre: keeps a gate's S invertible


@dataclass(frozen=True)
class AssociationGate:
    """When a worker pallet moved by ``T0`` may be a vehicle pallet."""

    # Squared Mahalanobis distance of the centres, with both pallets' covariances and
    # T0's: chi-square with 2 degrees of freedom at 99.9 %.
    mahalanobis2: float = 13.8
    max_distance_m: float = 1.0  # hard gate: pallets stand >= 0.8 m apart centre to centre
    # `candidate_pairs`' hard gate: a floor marker 5° off moves a pallet 20 m away by 1.7 m.
    candidate_distance_m: float = 3.0
    max_posture_rad: float = math.radians(15.0)  # modulo the kind's symmetry
    # T0's uncertainty, the floor marker's: its yaw is what makes far pallets' gates wide.
    t0_sigma_xy_m: float = 0.1
    t0_sigma_yaw_rad: float = math.radians(3.0)


def _posture_difference(a: FloatArray, b: FloatArray, symmetry: FloatArray) -> FloatArray:
    """`posture_difference_rad` over arrays (the same reduction)."""
    half = 0.5 * symmetry
    reduced: FloatArray = (a - b + half) % symmetry - half
    return reduced


def _arrays(pallet_map: PalletMap) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Positions (N, 2), yaws (N,), covariances (N, 3, 3) of a map's pallets."""
    pallets = pallet_map.pallets
    xy = np.array([(p.x_m, p.y_m) for p in pallets], dtype=np.float64).reshape(-1, 2)
    yaw = np.array([p.yaw_rad for p in pallets], dtype=np.float64)
    covariance = np.array([p.covariance for p in pallets], dtype=np.float64).reshape(-1, 3, 3)
    return xy, yaw, covariance


def t0_covariance(gate: AssociationGate) -> FloatArray:
    """The floor marker's covariance over (x, y, yaw), from the gate's sigmas."""
    sigmas = (gate.t0_sigma_xy_m, gate.t0_sigma_xy_m, gate.t0_sigma_yaw_rad)
    return np.diag(np.square(sigmas))


def _gated(
    vehicle: PalletMap,
    worker: PalletMap,
    worker_in_vehicle: Pose2D,
    gate: AssociationGate,
    transform_covariance: FloatArray,
    max_distance_m: float,
) -> tuple[BoolArray, FloatArray]:
    """Which (vehicle, worker) pallets may be one (V, W), and their squared Mahalanobis
    distance: centres with both pallets' covariances and the transform's (its yaw's
    through each worker pallet's lever arm)."""
    x0, y0, yaw0 = worker_in_vehicle
    c, s = math.cos(yaw0), math.sin(yaw0)
    rotation = np.array([[c, -s], [s, c]])
    xy_v, yaw_v, cov_v = _arrays(vehicle)
    xy_w, yaw_w, cov_w = _arrays(worker)
    moved = xy_w @ rotation.T + (x0, y0)
    jacobian = np.zeros((len(xy_w), 2, 3))  # ∂(T0 ∘ p)/∂T0 per worker pallet
    jacobian[:, :, :2] = np.eye(2)
    jacobian[:, 0, 2] = -s * xy_w[:, 0] - c * xy_w[:, 1]
    jacobian[:, 1, 2] = c * xy_w[:, 0] - s * xy_w[:, 1]
    cov_moved = rotation @ cov_w[:, :2, :2] @ rotation.T
    cov_moved = cov_moved + jacobian @ transform_covariance @ jacobian.transpose(0, 2, 1)
    spread = cov_v[:, None, :2, :2] + cov_moved[None] + _FLOOR_M2 * np.eye(2)  # (V, W, 2, 2)
    delta = xy_v[:, None, :] - moved[None, :, :]
    a, b, d = spread[..., 0, 0], spread[..., 0, 1], spread[..., 1, 1]
    dx, dy = delta[..., 0], delta[..., 1]
    mahalanobis2: FloatArray = (d * dx * dx - 2.0 * b * dx * dy + a * dy * dy) / (a * d - b * b)
    kinds_v = [p.kind for p in vehicle.pallets]
    kinds_w = [p.kind for p in worker.pallets]
    same_kind = np.array([[kv == kw for kw in kinds_w] for kv in kinds_v], dtype=bool)
    symmetry = np.array([[kv.symmetry_rad for _ in kinds_w] for kv in kinds_v])
    posture = _posture_difference(yaw_v[:, None], yaw_w[None, :] + yaw0, symmetry)
    allowed: BoolArray = (
        same_kind
        & (np.hypot(dx, dy) <= max_distance_m)
        & (mahalanobis2 <= gate.mahalanobis2)
        & (np.abs(posture) <= gate.max_posture_rad)
    )
    return allowed, mahalanobis2


def associate(
    vehicle: PalletMap,
    worker: PalletMap,
    worker_in_vehicle: Pose2D,
    gate: AssociationGate,
    transform_covariance: FloatArray | None = None,
) -> list[Pair]:
    """One-to-one pairs of vehicle and worker pallets once the worker's map is moved by
    ``worker_in_vehicle``: same kind, postures agreeing modulo the kind's symmetry, centres
    within both gates; among those, the assignment of least total Mahalanobis distance
    (the Hungarian method, so a pallet between two others goes to the nearer in the sum).

    ``transform_covariance`` is over ``worker_in_vehicle``'s (x, y, yaw); ``None`` takes
    the gate's T0 sigmas. Sorted by vehicle index.
    """
    if not vehicle.pallets or not worker.pallets:
        return []
    covariance = t0_covariance(gate) if transform_covariance is None else transform_covariance
    allowed, mahalanobis2 = _gated(
        vehicle, worker, worker_in_vehicle, gate, covariance, gate.max_distance_m
    )
    if not allowed.any():
        return []
    rows, cols = linear_sum_assignment(np.where(allowed, mahalanobis2, 1e12))
    return sorted((int(i), int(j)) for i, j in zip(rows, cols, strict=True) if allowed[i, j])


def candidate_pairs(
    vehicle: PalletMap, worker: PalletMap, worker_in_vehicle: Pose2D, gate: AssociationGate
) -> list[Pair]:
    """Every pair (many to many) within the Mahalanobis and posture gates and the wider
    `candidate_distance_m`, for when `associate`'s one-to-one pairs are too few (a floor
    marker some degrees off puts far pallets past the metre gate): `robust_transform`,
    given the floor marker as its prior, picks the consistent ones."""
    if not vehicle.pallets or not worker.pallets:
        return []
    allowed, _ = _gated(
        vehicle, worker, worker_in_vehicle, gate, t0_covariance(gate), gate.candidate_distance_m
    )
    return [(int(i), int(j)) for i, j in np.argwhere(allowed)]


@dataclass(frozen=True)
class RobustParams:
    """How `robust_transform` tells right pairs from wrong ones, and the fit it refits."""

    w_m2_per_rad2: float = DEFAULT_W_M2_PER_RAD2
    min_pairs: int = 2  # for `solve_transform`
    # Fewer than three pairs cannot outvote a wrong one: two that disagree are a tie.
    min_inliers: int = 3
    # A right pair's residual: both maps' noise (20 mm, 1° for a worker's) with margin;
    # a wrong pair is off by at least a pallet's width (0.8 m).
    inlier_gate_m: float = 0.15
    inlier_gate_rad: float = math.radians(10.0)
    min_baseline_m: float = 0.5  # two pallets nearer than this hardly fix a rotation
    max_exhaustive_pairs: int = 30  # up to here every pair of pairs is a hypothesis
    sampled_hypotheses: int = 500  # beyond it, this many pairs of pairs, seeded
    seed: int = 0
    # A hypothesis's T⁻¹ against the floor marker's T0: chi-square, 3 dof, 99.9 %.
    prior_mahalanobis2: float = 16.3


@dataclass(frozen=True)
class RejectedPair:
    """A pairing the consensus did not believe, and how far off it is under the fit."""

    vehicle_index: int
    worker_index: int
    position_residual_m: float
    posture_residual_rad: float


@dataclass(frozen=True, eq=False)
class RobustFit:
    """`robust_transform`'s answer: the fit over the pairs it believed, and the others."""

    fit: TransformFit  # `solve_transform` over the inliers
    inliers: tuple[Pair, ...]
    rejected: tuple[RejectedPair, ...]
    hypotheses: int  # how many were scored


def _hypotheses(
    xy_v: FloatArray, xy_w: FloatArray, params: RobustParams
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position-only (w = 0) transforms from pairs of pairs: for two points, eq. 2's
    rotation is the angle between the two difference vectors. Returns yaw (H,), t (H, 2)
    and the rigidity misfit (H,) (the difference of the two baselines)."""
    n = len(xy_v)
    first, second = np.triu_indices(n, k=1)
    if n > params.max_exhaustive_pairs:
        rng = np.random.default_rng(params.seed)
        chosen = rng.choice(len(first), min(params.sampled_hypotheses, len(first)), replace=False)
        first, second = first[chosen], second[chosen]
    dq = xy_v[second] - xy_v[first]
    dp = xy_w[second] - xy_w[first]
    baseline = np.hypot(dq[:, 0], dq[:, 1])
    keep = baseline >= params.min_baseline_m
    dq, dp, first, second = dq[keep], dp[keep], first[keep], second[keep]
    yaw = np.arctan2(dp[:, 1], dp[:, 0]) - np.arctan2(dq[:, 1], dq[:, 0])
    c, s = np.cos(yaw), np.sin(yaw)
    mean_q = 0.5 * (xy_v[first] + xy_v[second])
    mean_p = 0.5 * (xy_w[first] + xy_w[second])
    t = mean_p - np.stack(
        [c * mean_q[:, 0] - s * mean_q[:, 1], s * mean_q[:, 0] + c * mean_q[:, 1]], 1
    )
    misfit = np.abs(np.hypot(dp[:, 0], dp[:, 1]) - baseline[keep])
    return yaw, t, misfit


def _residuals(
    yaw: FloatArray,
    t: FloatArray,
    xy_v: FloatArray,
    yaw_v: FloatArray,
    xy_w: FloatArray,
    yaw_w: FloatArray,
    symmetry: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Position (H, N) and posture (H, N) residuals of every pair under every transform."""
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    ex = c * xy_v[None, :, 0] - s * xy_v[None, :, 1] + t[:, None, 0] - xy_w[None, :, 0]
    ey = s * xy_v[None, :, 0] + c * xy_v[None, :, 1] + t[:, None, 1] - xy_w[None, :, 1]
    posture = _posture_difference(yaw[:, None] + yaw_v[None, :], yaw_w[None, :], symmetry[None, :])
    return np.hypot(ex, ey), posture


def _one_to_one(candidates: BoolArray, position: FloatArray, pairs: Sequence[Pair]) -> list[int]:
    """The candidate pairs (indices into ``pairs``), with at most one per vehicle and per
    worker pallet: the least residual keeps it."""
    used_v: set[int] = set()
    used_w: set[int] = set()
    kept = []
    for k in sorted((int(k) for k in np.flatnonzero(candidates)), key=lambda k: position[k]):
        i, j = pairs[k]
        if i not in used_v and j not in used_w:
            used_v.add(i)
            used_w.add(j)
            kept.append(k)
    return sorted(kept)


def _agrees_with(
    yaw: FloatArray, t: FloatArray, prior: tuple[Pose2D, FloatArray], gate: float
) -> BoolArray:
    """Which hypotheses ``T`` have a ``T⁻¹`` within ``gate`` (squared Mahalanobis) of the
    prior's worker_in_vehicle pose: the floor marker rules out a layout's look-alikes (a
    row of pallets shifted by one)."""
    pose, covariance = prior
    c, s = np.cos(yaw), np.sin(yaw)
    delta = np.stack(
        [
            -(c * t[:, 0] + s * t[:, 1]) - pose.x_m,
            s * t[:, 0] - c * t[:, 1] - pose.y_m,
            np.remainder(-yaw - pose.yaw_rad + np.pi, 2.0 * np.pi) - np.pi,
        ],
        axis=1,
    )
    information = np.linalg.pinv(covariance + 1e-12 * np.eye(3))
    agrees: BoolArray = np.einsum("hi,ij,hj->h", delta, information, delta) <= gate
    return agrees


def robust_transform(
    vehicle: PalletMap,
    worker: PalletMap,
    pairs: Sequence[Pair],
    params: RobustParams,
    prior: tuple[Pose2D, FloatArray] | None = None,
) -> RobustFit | MergeRefusal:
    """``T`` (vehicle map into worker map, as `solve_transform`) from ``pairs`` of which
    some may be wrong: each pair of pairs proposes a position-only ``T``; the one most
    pairs agree with (position and posture residuals within the inlier gates; ties to the
    least truncated squared residual) wins; its inliers are refitted by `solve_transform`,
    and inliers and fit re-chosen under the refit until they stay. Deterministic: every
    pair of pairs up to `max_exhaustive_pairs` pairs, seeded sampling beyond.

    ``prior``: the floor marker's worker_in_vehicle pose (``T0``, the inverse of ``T``)
    and its covariance; hypotheses it rules out are not scored. Pairs need not be one to
    one (`candidate_pairs`): the inliers are made so, the least residual kept."""
    pairs = [(int(i), int(j)) for i, j in pairs]
    if any(not (0 <= i < len(vehicle) and 0 <= j < len(worker)) for i, j in pairs):
        return MergeRefusal("a pair names a pallet that is not in its map")
    if len(pairs) < max(params.min_inliers, 2):
        return MergeRefusal(
            f"{len(pairs)} common pallet(s); at least {params.min_inliers} are needed to tell "
            "a wrong association from a right one"
        )
    xy_v_all, yaw_v_all, cov_v_all = _arrays(vehicle)
    xy_w_all, yaw_w_all, cov_w_all = _arrays(worker)
    v_idx = np.array([i for i, _ in pairs])
    w_idx = np.array([j for _, j in pairs])
    xy_v, yaw_v, xy_w, yaw_w = xy_v_all[v_idx], yaw_v_all[v_idx], xy_w_all[w_idx], yaw_w_all[w_idx]
    symmetry = np.array([vehicle.pallets[i].kind.symmetry_rad for i, _ in pairs])
    # A pallet paired with one of another kind is wrong whatever the residuals say.
    same_kind = np.array([vehicle.pallets[i].kind == worker.pallets[j].kind for i, j in pairs])
    yaw, t, misfit = _hypotheses(xy_v, xy_w, params)
    rigid = misfit <= 2.0 * params.inlier_gate_m  # two pallets' distance is the same in both maps
    yaw, t = yaw[rigid], t[rigid]
    if len(yaw) == 0:
        return MergeRefusal("no two common pallets are far enough apart and agree in distance")
    if prior is not None:
        agrees = _agrees_with(yaw, t, prior, params.prior_mahalanobis2)
        yaw, t = yaw[agrees], t[agrees]
        if len(yaw) == 0:
            return MergeRefusal("no two common pallets agree with the floor marker's T0")
    position, posture = _residuals(yaw, t, xy_v, yaw_v, xy_w, yaw_w, symmetry)
    inlier = (
        (position <= params.inlier_gate_m) & (np.abs(posture) <= params.inlier_gate_rad) & same_kind
    )
    truncated = np.minimum(
        (position / params.inlier_gate_m) ** 2 + (posture / params.inlier_gate_rad) ** 2, 1.0
    ).sum(axis=1)
    best = int(np.lexsort((truncated, -inlier.sum(axis=1)))[0])
    chosen = _one_to_one(inlier[best], position[best], pairs)
    fit: TransformFit | MergeRefusal = MergeRefusal("no consensus")
    fitted: list[int] = []
    for _ in range(5):
        if len(chosen) < params.min_inliers:
            return MergeRefusal(
                f"only {len(chosen)} of {len(pairs)} common pallets agree on one transform; "
                f"at least {params.min_inliers} are needed"
            )
        fit = solve_transform(
            xy_v[chosen],
            yaw_v[chosen],
            xy_w[chosen],
            yaw_w[chosen],
            symmetry[chosen],
            params.w_m2_per_rad2,
            min_pairs=params.min_pairs,
            vehicle_covariance=cov_v_all[v_idx[chosen]],
            worker_covariance=cov_w_all[w_idx[chosen]],
        )
        if isinstance(fit, MergeRefusal):
            return fit
        pose = fit.vehicle_in_worker
        position, posture = _residuals(
            np.array([pose.yaw_rad]),
            np.array([[pose.x_m, pose.y_m]]),
            xy_v,
            yaw_v,
            xy_w,
            yaw_w,
            symmetry,
        )
        within = (
            (position[0] <= params.inlier_gate_m)
            & (np.abs(posture[0]) <= params.inlier_gate_rad)
            & same_kind
        )
        fitted, chosen = chosen, _one_to_one(within, position[0], pairs)
        if chosen == fitted:
            break
    assert isinstance(fit, TransformFit)
    rejected = tuple(
        RejectedPair(i, j, float(position[0, k]), float(posture[0, k]))
        for k, (i, j) in enumerate(pairs)
        if k not in set(fitted)
    )
    return RobustFit(fit, tuple(pairs[k] for k in fitted), rejected, len(yaw))
