"""Association and the consensus fit: kinds apart, one to one, a wrong pair in five
rejected, too few common pallets refused, never an exception."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.mapping.association import (
    AssociationGate,
    RobustFit,
    RobustParams,
    associate,
    candidate_pairs,
    robust_transform,
)
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap, inverse_pose
from appliance.mapping.transform_fit import MergeRefusal, TransformFit, solve_transform
from drivers.geometry import Pose2D

from .merge_scenes import arrays, scene

GATE = AssociationGate()
PARAMS = RobustParams()
COV = np.diag([4e-4, 4e-4, 3e-4])


def _robust(result: RobustFit | MergeRefusal) -> RobustFit:
    assert isinstance(result, RobustFit), result
    return result


def _pallet(x: float, y: float, yaw: float, kind: PalletKind = PalletKind.JIS) -> Pallet:
    return Pallet(x, y, yaw, COV, kind)


def test_the_true_pairs_are_found_with_a_floor_marker_a_few_degrees_off() -> None:
    s = scene(np.random.default_rng(1))
    t0 = s.worker_in_vehicle
    off = Pose2D(t0.x_m + 0.05, t0.y_m - 0.04, t0.yaw_rad + math.radians(1.0))
    pairs = associate(s.vehicle, s.worker, off, GATE)
    assert pairs
    assert all(i == j for i, j in pairs)  # the scene's vehicle pallet i is worker pallet i


def test_association_keeps_kinds_apart() -> None:
    vehicle = PalletMap((_pallet(0.0, 0.0, 0.0, PalletKind.EUR),))
    worker = PalletMap((_pallet(0.0, 0.0, 0.0, PalletKind.JIS),))
    assert associate(vehicle, worker, Pose2D(0.0, 0.0, 0.0), GATE) == []


def test_association_is_one_to_one() -> None:
    vehicle = PalletMap((_pallet(0.0, 0.0, 0.0), _pallet(0.3, 0.0, 0.0), _pallet(5.0, 0.0, 0.0)))
    worker = PalletMap((_pallet(0.25, 0.0, 0.0), _pallet(5.0, 0.0, 0.0)))
    pairs = associate(vehicle, worker, Pose2D(0.0, 0.0, 0.0), GATE)
    assert pairs == [(1, 0), (2, 1)]


@pytest.mark.parametrize(
    ("kind", "turn_rad", "paired"),
    [
        (PalletKind.JIS, math.pi / 2, True),  # a square turned a quarter looks the same
        (PalletKind.EUR, math.pi, True),
        (PalletKind.EUR, math.pi / 2, False),  # a rectangle turned a quarter does not
        (PalletKind.JIS, math.radians(30.0), False),
    ],
)
def test_association_compares_postures_modulo_symmetry(
    kind: PalletKind, turn_rad: float, paired: bool
) -> None:
    vehicle = PalletMap((_pallet(1.0, 2.0, 0.3, kind),))
    worker = PalletMap((_pallet(1.0, 2.0, 0.3 + turn_rad, kind),))
    assert bool(associate(vehicle, worker, Pose2D(0.0, 0.0, 0.0), GATE)) is paired


def test_association_moves_the_worker_map_by_t0_the_worker_frame_in_the_vehicle_frame() -> None:
    t0 = Pose2D(10.0, -3.0, 0.8)
    worker = PalletMap((_pallet(2.0, 1.0, 0.1), _pallet(-4.0, 3.0, 1.0)))
    vehicle = PalletMap(tuple(_pallet(*t0.compose(p.pose)) for p in reversed(worker.pallets)))
    assert associate(vehicle, worker, t0, GATE) == [(0, 1), (1, 0)]
    assert associate(vehicle, worker, inverse_pose(t0), GATE) == []


def test_a_far_pallet_is_gated_by_metres_whatever_its_covariance() -> None:
    loose = np.diag([100.0, 100.0, 1.0])
    vehicle = PalletMap((Pallet(0.0, 0.0, 0.0, loose),))
    worker = PalletMap((Pallet(1.5, 0.0, 0.0, loose),))
    assert associate(vehicle, worker, Pose2D(0.0, 0.0, 0.0), GATE) == []


def _true_pairs(count: int) -> list[tuple[int, int]]:
    return [(i, i) for i in range(count)]


@pytest.mark.parametrize("seed", range(20))
def test_one_wrong_pair_in_five_is_rejected_and_the_transform_unaffected(seed: int) -> None:
    rng = np.random.default_rng(seed)
    s = scene(rng, count=8, seen=5)
    pairs = _true_pairs(5)
    pairs[2] = (2, 6)  # vehicle pallet 2 paired with a pallet only the worker saw
    result = _robust(robust_transform(s.vehicle, s.worker, pairs, PARAMS))
    assert [(r.vehicle_index, r.worker_index) for r in result.rejected] == [(2, 6)]
    assert result.rejected[0].position_residual_m > 1.0
    right = [p for p in pairs if p != (2, 6)]
    alone = solve_transform(*arrays(s.vehicle, s.worker, right), PARAMS.w_m2_per_rad2)
    assert isinstance(alone, TransformFit)
    assert np.allclose(result.fit.vehicle_in_worker, alone.vehicle_in_worker, atol=1e-12)


@pytest.mark.parametrize("seed", range(10))
def test_two_swapped_pairs_among_ten_are_both_rejected(seed: int) -> None:
    s = scene(np.random.default_rng(100 + seed), count=12, seen=10)
    pairs = _true_pairs(10)
    pairs[3], pairs[7] = (3, 7), (7, 3)
    result = _robust(robust_transform(s.vehicle, s.worker, pairs, PARAMS))
    assert sorted((r.vehicle_index, r.worker_index) for r in result.rejected) == [(3, 7), (7, 3)]
    truth = inverse_pose(s.worker_in_vehicle)
    x, y, yaw = result.fit.vehicle_in_worker
    assert math.hypot(x - truth.x_m, y - truth.y_m) < 0.1
    assert abs(math.remainder(yaw - truth.yaw_rad, 2 * math.pi)) < math.radians(0.5)


def test_too_few_common_pallets_are_refused() -> None:
    s = scene(np.random.default_rng(5), count=8, seen=5)
    result = robust_transform(s.vehicle, s.worker, _true_pairs(2), PARAMS)
    assert isinstance(result, MergeRefusal)
    assert "at least 3" in result.reason


def test_too_few_after_rejection_are_refused() -> None:
    s = scene(np.random.default_rng(6), count=8, seen=5)
    pairs = [(0, 0), (1, 1), (2, 5), (3, 7)]  # two right, two wrong
    result = robust_transform(s.vehicle, s.worker, pairs, PARAMS)
    assert isinstance(result, MergeRefusal)
    assert "agree" in result.reason


def test_many_pairs_are_sampled_with_a_seed_and_give_the_same_fit() -> None:
    s = scene(np.random.default_rng(8), count=40, seen=35)
    pairs = _true_pairs(35)
    pairs[0] = (0, 36)
    params = RobustParams(sampled_hypotheses=200)
    first = _robust(robust_transform(s.vehicle, s.worker, pairs, params))
    second = _robust(robust_transform(s.vehicle, s.worker, pairs, params))
    assert first.hypotheses <= 200
    assert first.fit.vehicle_in_worker == second.fit.vehicle_in_worker
    assert [r.vehicle_index for r in first.rejected] == [0]


@given(
    st.integers(0, 2**16),
    st.lists(st.tuples(st.integers(-1, 9), st.integers(-1, 9)), max_size=12),
    st.integers(1, 4),
)
def test_any_association_set_gives_a_fit_or_a_refusal(
    seed: int, pairs: list[tuple[int, int]], min_inliers: int
) -> None:
    s = scene(np.random.default_rng(seed), count=9, seen=7)
    result = robust_transform(s.vehicle, s.worker, pairs, RobustParams(min_inliers=min_inliers))
    assert isinstance(result, RobustFit | MergeRefusal)
    if isinstance(result, MergeRefusal):
        assert result.reason
    else:
        assert len(result.inliers) + len(result.rejected) == len(pairs)
        assert len({i for i, _ in result.inliers}) == len(result.inliers)
        assert len({j for _, j in result.inliers}) == len(result.inliers)


def test_pallets_stacked_at_one_point_are_refused_not_raised() -> None:
    stacked = PalletMap(tuple(_pallet(1.0, 1.0, 0.0) for _ in range(4)))
    result = robust_transform(stacked, stacked, _true_pairs(4), PARAMS)
    assert isinstance(result, MergeRefusal)


def test_the_floor_marker_rules_out_a_row_shifted_by_one_pallet() -> None:
    # A row of six at 1.5 m: the vehicle sees the first four, the worker the last five
    # (its frame = the vehicle's). Shifted by one, four pairs agree; truly, three.
    row = [_pallet(1.5 * k, 0.0, 0.0) for k in range(6)]
    vehicle, worker = PalletMap(tuple(row[:4])), PalletMap(tuple(row[1:]))
    t0 = Pose2D(0.0, 0.0, 0.0)
    assert candidate_pairs(vehicle, worker, t0, GATE) == [(1, 0), (2, 1), (3, 2)]
    # Pairs from elsewhere (an operator's list, a looser gate): every pallet within 3 m.
    candidates = [
        (i, j)
        for i, v in enumerate(vehicle.pallets)
        for j, w in enumerate(worker.pallets)
        if math.hypot(v.x_m - w.x_m, v.y_m - w.y_m) <= 3.0
    ]
    shifted = _robust(robust_transform(vehicle, worker, candidates, PARAMS))
    assert len(shifted.inliers) == 4
    prior = (t0, np.diag([0.1**2, 0.1**2, math.radians(3.0) ** 2]))
    right = _robust(robust_transform(vehicle, worker, candidates, PARAMS, prior))
    assert sorted(right.inliers) == [(1, 0), (2, 1), (3, 2)]
    assert np.allclose(right.fit.vehicle_in_worker, (0.0, 0.0, 0.0), atol=1e-9)
