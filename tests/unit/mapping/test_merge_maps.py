"""The merged map: the vehicle's pallets as they are, the worker's others where they
belong, their covariance and their reference areas."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.mapping.merge import (
    MergeParams,
    MergeRefusal,
    MergeResult,
    associate,
    merge_maps,
    move_worker_pallet,
)
from appliance.mapping.pallets import PalletMap, inverse_pose
from drivers.geometry import Pose2D

from .merge_scenes import scene

PARAMS = MergeParams()


def _merged(result: MergeResult | MergeRefusal) -> MergeResult:
    assert isinstance(result, MergeResult), result
    return result


def _off(pose: Pose2D, dx_m: float, dy_m: float, dyaw_deg: float) -> Pose2D:
    return Pose2D(pose.x_m + dx_m, pose.y_m + dy_m, pose.yaw_rad + math.radians(dyaw_deg))


def test_noiseless_maps_merge_exactly() -> None:
    s = scene(np.random.default_rng(2), count=10, seen=6, noise=False)
    result = _merged(
        merge_maps(s.vehicle, s.worker, _off(s.worker_in_vehicle, 0.05, -0.03, 2.0), PARAMS)
    )
    assert np.allclose(result.worker_in_vehicle, s.worker_in_vehicle, atol=1e-9)
    assert len(result.pallets) == 10
    assert [p.pallet for p in result.pallets[:6]] == list(s.vehicle.pallets)
    assert [p.worker_index for p in result.added] == [6, 7, 8, 9]
    for added in result.added:
        truth = s.truth[added.worker_index or 0]
        assert added.from_worker and added.vehicle_index is None
        assert (added.pallet.x_m, added.pallet.y_m) == pytest.approx(
            (truth.x_m, truth.y_m), abs=1e-9
        )
        assert math.remainder(added.pallet.yaw_rad - truth.yaw_rad, 2 * math.pi) == pytest.approx(
            0.0, abs=1e-9
        )
        assert added.pallet.kind is truth.kind
    assert result.pallet_map().frame == "vehicle"


def test_a_floor_marker_too_far_off_for_some_pallets_is_made_good_by_the_second_pass() -> None:
    s = scene(np.random.default_rng(4), count=12, seen=10)
    t0 = _off(s.worker_in_vehicle, 0.1, 0.1, 4.0)  # far pallets 1 m or more off: gated out
    result = _merged(merge_maps(s.vehicle, s.worker, t0, PARAMS))
    assert sorted(result.robust.inliers) == [(i, i) for i in range(10)]
    assert [p.worker_index for p in result.added] == [10, 11]


@pytest.mark.parametrize("seed", range(30))
def test_reference_areas_contain_the_true_pallet(seed: int) -> None:
    s = scene(np.random.default_rng(seed), count=10, seen=6)
    result = _merged(
        merge_maps(s.vehicle, s.worker, _off(s.worker_in_vehicle, 0.03, 0.03, 1.0), PARAMS)
    )
    assert len(result.added) == 4
    for added in result.added:
        area = added.reference_area
        assert area is not None
        truth = s.truth[added.worker_index or 0]
        # the whole footprint, not only the centre
        assert all(area.contains(x, y) for x, y in truth.corners_xy_m())


def test_an_added_pallets_covariance_grows_with_the_transforms() -> None:
    s = scene(np.random.default_rng(3), count=10, seen=6)
    result = _merged(merge_maps(s.vehicle, s.worker, s.worker_in_vehicle, PARAMS))
    fit = result.fit
    worker_pallet = s.worker.pallets[8]
    exact = move_worker_pallet(worker_pallet, replace(fit, covariance=np.zeros((3, 3))))
    base = move_worker_pallet(worker_pallet, fit)
    wider = move_worker_pallet(worker_pallet, replace(fit, covariance=4.0 * fit.covariance))
    # Without T's uncertainty it is the worker's covariance rotated; with it, larger.
    assert np.trace(exact.covariance) == pytest.approx(np.trace(worker_pallet.covariance))
    assert np.all(np.linalg.eigvalsh(base.covariance - exact.covariance) >= -1e-15)
    assert np.all(np.linalg.eigvalsh(wider.covariance - base.covariance) >= -1e-15)
    assert np.trace(wider.covariance) > np.trace(base.covariance) > np.trace(exact.covariance)
    added = next(p for p in result.added if p.worker_index == 8)
    assert np.allclose(added.pallet.covariance, base.covariance)


def test_the_added_covariance_is_first_order_right() -> None:
    """Against Monte Carlo over T's covariance: the spread of the moved pallet's position."""
    s = scene(np.random.default_rng(9), count=10, seen=6)
    fit = _merged(merge_maps(s.vehicle, s.worker, s.worker_in_vehicle, PARAMS)).fit
    worker_pallet = s.worker.pallets[9]
    rng = np.random.default_rng(0)
    moved = []
    for x, y, yaw in rng.multivariate_normal(
        np.array(fit.vehicle_in_worker), fit.covariance, 20_000
    ):
        moved.append(inverse_pose(Pose2D(x, y, yaw)).compose(worker_pallet.pose)[:2])
    from_t = (
        move_worker_pallet(worker_pallet, fit).covariance[:2, :2]
        - (
            move_worker_pallet(worker_pallet, replace(fit, covariance=np.zeros((3, 3)))).covariance[
                :2, :2
            ]
        )
    )
    assert np.allclose(np.cov(np.array(moved).T), from_t, rtol=0.1, atol=0.05 * from_t.max())


def test_maps_without_enough_common_pallets_are_refused() -> None:
    s = scene(np.random.default_rng(7), count=8, seen=2)
    result = merge_maps(s.vehicle, s.worker, s.worker_in_vehicle, PARAMS)
    assert isinstance(result, MergeRefusal)
    assert "at least 3" in result.reason
    empty = merge_maps(PalletMap(()), s.worker, s.worker_in_vehicle, PARAMS)
    assert isinstance(empty, MergeRefusal)
    nan = merge_maps(s.vehicle, s.worker, Pose2D(math.nan, 0.0, 0.0), PARAMS)
    assert isinstance(nan, MergeRefusal)


@given(
    st.integers(0, 2**16),
    st.integers(0, 10),
    st.floats(-5.0, 5.0),
    st.floats(-30.0, 30.0),
)
def test_any_two_maps_give_a_merge_or_a_refusal(
    seed: int, seen: int, dx_m: float, dyaw_deg: float
) -> None:
    s = scene(np.random.default_rng(seed), count=10, seen=seen)
    result = merge_maps(s.vehicle, s.worker, _off(s.worker_in_vehicle, dx_m, 0.0, dyaw_deg), PARAMS)
    assert isinstance(result, MergeResult | MergeRefusal)
    if isinstance(result, MergeResult):
        assert len(result.pallets) >= len(s.vehicle)
        assert all(np.isfinite(p.pallet.covariance).all() for p in result.pallets)


def test_a_floor_marker_degrees_off_falls_back_to_every_candidate_pair() -> None:
    s = scene(np.random.default_rng(21), count=10, seen=6)
    t0 = _off(s.worker_in_vehicle, 0.05, -0.05, 6.0)
    assert len(associate(s.vehicle, s.worker, t0, PARAMS.gate)) < 3  # the first pass fails
    result = _merged(merge_maps(s.vehicle, s.worker, t0, PARAMS))
    assert sorted(result.robust.inliers) == [(i, i) for i in range(6)]
    assert np.allclose(result.worker_in_vehicle, s.worker_in_vehicle, atol=0.1)
