"""The way to a pallet's view pose: on the `pallets` site, boxed in, and fuzzed.

The plans are checked with their own geometry written out again here (points of the
outline inside the obstacles' polygons, curvature from the points), not with the
planner's separating-axis test.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from appliance.guidance.pallet_geometry import (
    Obstacle,
    VehicleShape,
    entry_face,
    entry_face_indices,
    face_in_view,
    wall_obstacle,
)
from appliance.guidance.pallet_plan import (
    PalletPlan,
    PalletPlanParams,
    PalletTarget,
    PlanRefusal,
    map_obstacles,
    plan_pallet_approach,
)
from appliance.guidance.pallet_search import SearchParams
from appliance.mapping.pallets import Pallet, PalletKind
from drivers.geometry import Pose2D
from tests.unit.guidance.pallet_scene import (
    ROW_B,
    START,
    plan_params,
    site_plan,
    static_obstacles,
    true_pallet,
    true_pallets,
    vehicle_shape,
    worker_map,
)

SURE = np.diag([1e-4, 1e-4, 1e-4])


def _plan(name: str) -> PalletPlan:
    plan = site_plan(name)
    assert isinstance(plan, PalletPlan), plan
    return plan


def _inside_convex(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """Which points are strictly inside the convex polygon (either winding)."""
    left = np.ones(points.shape[:-1], dtype=bool)
    right = np.ones(points.shape[:-1], dtype=bool)
    for i in range(len(corners)):
        a, b = corners[i], corners[(i + 1) % len(corners)]
        cross = (b[0] - a[0]) * (points[..., 1] - a[1]) - (b[1] - a[1]) * (points[..., 0] - a[0])
        left &= cross > 0.0
        right &= cross < 0.0
    return left | right


def _outline_points(shape: VehicleShape, guide_poses: np.ndarray, spacing_m: float) -> np.ndarray:
    """Points over every box of the outline (edges and inside), (N, P, 2)."""
    local = []
    for rear, front, right, left in shape.parts_local_m():
        xs = np.linspace(rear, front, math.ceil((front - rear) / spacing_m) + 1)
        ys = np.linspace(right, left, math.ceil((left - right) / spacing_m) + 1)
        px, py = np.meshgrid(xs, ys)
        local.append(np.column_stack([px.ravel(), py.ravel()]))
    pts = np.concatenate(local)
    c, s = np.cos(guide_poses[:, 2:3]), np.sin(guide_poses[:, 2:3])
    x = guide_poses[:, 0:1] + c * pts[None, :, 0] - s * pts[None, :, 1]
    y = guide_poses[:, 1:2] + s * pts[None, :, 0] + c * pts[None, :, 1]
    return np.stack([x, y], axis=-1)


def _outline_hits(plan: PalletPlan, obstacles: tuple[Obstacle, ...]) -> list[str]:
    """The obstacles some point of the outline (2.5 cm apart) is inside of, at some
    point of the path (5 cm apart)."""
    shape = vehicle_shape()
    poses = plan.guide_poses()
    reach = max(abs(v) for box in shape.parts_local_m() for v in box) + shape.width_m
    hits = []
    for obstacle in obstacles:
        corners = obstacle.corners_xy_m
        centre = corners.mean(axis=0)
        radius = float(np.hypot(*(corners - centre).T).max())
        near = np.hypot(*(poses[:, :2] - centre).T) < radius + reach
        if not near.any():
            continue
        points = _outline_points(shape, poses[near], 0.025)
        if _inside_convex(points, corners).any():
            hits.append(obstacle.name)
    return hits


@pytest.mark.parametrize("name", ROW_B)
def test_the_blind_row_is_reached_around_the_front_row_by_its_free_face(name: str) -> None:
    plan = _plan(name)
    pallet = true_pallet(name)
    # Row b's faces toward row a have no room for the vehicle: the far (+x) face is it.
    assert plan.face.index == 0
    assert math.cos(plan.face.entry_yaw_rad) < -0.99  # driving in toward -x
    refused = {v.face.index: v.refused for v in plan.faces}
    assert "corridor is blocked by row_a" in refused[2]
    # The route goes round row a (its far end is at y = -4.55) and not through it.
    assert plan.guide_xy_m[:, 1].min() < -4.55 - 0.6
    assert np.hypot(plan.guide_xy_m[0, 0] - 0.8 + 2.0, plan.guide_xy_m[0, 1] + 1.5) < 1e-9
    # The view pose: square to the face, the tips the standoff before its centre.
    tips = plan.view_pose.compose(Pose2D(vehicle_shape().tips_forward_m, 0.0, 0.0))
    face = entry_face(pallet, 0)
    assert math.hypot(tips.x_m - face.centre_x_m, tips.y_m - face.centre_y_m) == pytest.approx(
        plan_params().approach_standoff_m, abs=1e-9
    )
    assert face_in_view(vehicle_shape(), plan.view_pose, face) == ""


@pytest.mark.parametrize("name", ROW_B)
def test_the_whole_outline_stays_clear_along_the_path(name: str) -> None:
    plan = _plan(name)
    target, pallets = worker_map(name, (0.0, 0.0, 0.0))
    grown = map_obstacles(target.pallet, pallets, plan_params(), static_obstacles())
    assert _outline_hits(plan, grown) == []
    # And a fortiori the pallets themselves, by a margin.
    bare = tuple(
        Obstacle(p.name, np.array(p.corners_xy_m())) for p in true_pallets() if p.name != name
    )
    assert _outline_hits(plan, bare) == []
    # The check is not vacuous: a post on the path is found.
    x, y = plan.guide_xy_m[len(plan.guide_xy_m) // 2]
    post = Obstacle("post", np.array([[x, y], [x + 0.05, y], [x + 0.05, y + 0.05]]))
    assert _outline_hits(plan, (post,)) == ["post"]


@pytest.mark.parametrize("name", ROW_B)
def test_the_path_is_one_the_vehicle_can_drive(name: str) -> None:
    plan = _plan(name)
    shape = vehicle_shape()
    limit = plan_params().curvature_fraction / shape.min_turning_radius_m
    xy = plan.guide_xy_m
    # Curvature from the points alone (Menger, over three samples 5 cm apart).
    a, b, c = xy[:-2], xy[1:-1], xy[2:]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    sides = np.hypot(*(b - a).T) * np.hypot(*(c - b).T) * np.hypot(*(c - a).T)
    menger = 2.0 * np.abs(cross) / sides
    assert menger.max() <= limit * 1.001
    assert np.abs(plan.curvature_per_m).max() <= limit * 1.001
    # The headings are the points' tangents: forward driving, no cusp.
    steps = np.diff(xy, axis=0)
    along = steps[:, 0] * np.cos(plan.headings_rad[1:]) + steps[:, 1] * np.sin(
        plan.headings_rad[1:]
    )
    assert (along > 0.0).all()
    # It ends with the final straight along the entry direction into the view pose.
    straight = plan.arc_m >= plan.straight_start_m
    assert plan.arc_m[-1] - plan.straight_start_m >= 1.5
    off = np.remainder(plan.headings_rad[straight] - plan.face.entry_yaw_rad + math.pi, math.tau)
    assert np.abs(off - math.pi).max() < 1e-6
    end = shape.centre_of(Pose2D(float(xy[-1, 0]), float(xy[-1, 1]), float(plan.headings_rad[-1])))
    assert math.hypot(end.x_m - plan.view_pose.x_m, end.y_m - plan.view_pose.y_m) < 1e-6
    assert plan.length_m == pytest.approx(np.hypot(*np.diff(xy, axis=0).T).sum(), rel=1e-3)


def test_the_front_row_is_entered_from_the_aisle() -> None:
    plan = _plan("row_a.r0c1")
    assert plan.face.index == 2  # its -x side, toward the start
    refused = {v.face.index: v.refused for v in plan.faces}
    assert set(refused) == {0, 1, 2, 3}  # a JIS pallet offers all four
    assert all("blocked" in refused[i] for i in (0, 1, 3))


def test_a_lone_jis_pallet_offers_four_faces_and_the_nearest_is_taken() -> None:
    lone = Pallet(12.0, 0.0, 0.3, SURE, PalletKind.JIS, "lone")
    assert entry_face_indices(PalletKind.JIS) == (0, 1, 2, 3)
    assert entry_face_indices(PalletKind.EUR) == (0, 2)
    plan = plan_pallet_approach(
        Pose2D(0.0, 0.0, 0.0), PalletTarget(lone), [lone], vehicle_shape(), PalletPlanParams()
    )
    assert isinstance(plan, PalletPlan), plan
    assert len(plan.faces) == 4
    assert not any("blocked" in v.refused for v in plan.faces)
    # Straight ahead of the start: the face looking back at it (yaw 0.3 + π).
    assert plan.face.index == 2
    assert plan.length_m < 9.0


def test_a_pallet_boxed_in_by_others_is_refused_with_each_face_s_reason() -> None:
    target = Pallet(5.0, 0.0, 0.0, SURE, PalletKind.EUR, "boxed")
    ends = [
        Pallet(5.0 + side * 1.4, 0.0, 0.0, SURE, PalletKind.JIS, f"n{side}") for side in (-1, 1)
    ]
    result = plan_pallet_approach(
        Pose2D(0.0, 3.0, 0.0),
        PalletTarget(target),
        [target, *ends],
        vehicle_shape(),
        PalletPlanParams(),
    )
    assert isinstance(result, PlanRefusal)
    assert result.reason.startswith("no entry face is free")
    assert "face 0: its corridor is blocked by n1" in result.reason
    assert "face 2: its corridor is blocked by n-1" in result.reason


def test_a_start_walled_in_is_refused_not_searched_forever() -> None:
    target = Pallet(8.0, 0.0, 0.0, SURE, PalletKind.JIS, "out")
    box = [
        wall_obstacle(-3.0, -3.0, 3.0, -3.0, 0.1, "south"),
        wall_obstacle(3.0, -3.0, 3.0, 3.0, 0.1, "east"),
        wall_obstacle(3.0, 3.0, -3.0, 3.0, 0.1, "north"),
        wall_obstacle(-3.0, 3.0, -3.0, -3.0, 0.1, "west"),
    ]
    result = plan_pallet_approach(
        Pose2D(0.0, 0.0, 0.0),
        PalletTarget(target),
        [target],
        vehicle_shape(),
        PalletPlanParams(),
        box,
    )
    assert isinstance(result, PlanRefusal)
    assert result.reason.startswith("no path to any free entry face")
    assert "wide enough" in result.reason or "blocked" in result.reason


def test_a_dead_end_is_refused_when_the_search_runs_out_of_ways() -> None:
    """Only a forward path counts: in a corridor too narrow to turn, facing its closed
    end, the vehicle has no way back out to a pallet behind it (though a point would)."""
    target = Pallet(-8.0, 6.0, 0.0, SURE, PalletKind.JIS, "behind")
    corridor = [
        wall_obstacle(-6.0, 0.9, 4.0, 0.9, 0.1, "left"),
        wall_obstacle(-6.0, -0.9, 4.0, -0.9, 0.1, "right"),
        wall_obstacle(4.0, -0.9, 4.0, 0.9, 0.1, "end"),
    ]
    result = plan_pallet_approach(
        Pose2D(0.0, 0.0, 0.0),
        PalletTarget(target),
        [target],
        vehicle_shape(),
        PalletPlanParams(),
        corridor,
    )
    assert isinstance(result, PlanRefusal)
    assert "every way is blocked" in result.reason


def test_a_start_inside_an_obstacle_is_refused() -> None:
    target = Pallet(8.0, 0.0, 0.0, SURE, PalletKind.JIS, "t")
    on_it = Pallet(0.5, 0.0, 0.0, SURE, PalletKind.JIS, "under the forks")
    result = plan_pallet_approach(
        Pose2D(0.0, 0.0, 0.0),
        PalletTarget(target),
        [target, on_it],
        vehicle_shape(),
        PalletPlanParams(),
    )
    assert isinstance(result, PlanRefusal)
    assert "at its start overlaps" in result.reason


def test_a_worker_pallet_off_in_the_map_moves_the_view_pose_with_it() -> None:
    """The plan goes by the map (the pallet is re-detected at the view pose)."""
    error = (0.08, -0.06, math.radians(2.0))
    plan = site_plan("row_b.r0c1", error)
    assert isinstance(plan, PalletPlan), plan
    target, _ = worker_map("row_b.r0c1", error)
    face = entry_face(target.pallet, plan.face.index)
    tips = plan.view_pose.compose(Pose2D(vehicle_shape().tips_forward_m, 0.0, 0.0))
    assert math.hypot(tips.x_m - face.centre_x_m, tips.y_m - face.centre_y_m) == pytest.approx(1.5)
    assert plan.reference_area == target.reference_area


def test_bad_input_is_a_refusal() -> None:
    target = PalletTarget(Pallet(5.0, 0.0, 0.0, SURE))
    shape = vehicle_shape()
    nan_start = plan_pallet_approach(
        Pose2D(math.nan, 0.0, 0.0), target, [], shape, PalletPlanParams()
    )
    assert isinstance(nan_start, PlanRefusal)
    assert "not finite" in nan_start.reason
    flat = VehicleShape(3.3, 1.2, 2.0, 1.6, 0.0, 2.0)
    assert isinstance(
        plan_pallet_approach(START, target, [], flat, PalletPlanParams()), PlanRefusal
    )


_FUZZ_PARAMS = PalletPlanParams(
    region_margin_m=3.0, search=SearchParams(max_expansions=300, max_shortcut_tries=50)
)


@settings(
    max_examples=15,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
    derandomize=True,
)
@given(
    start=st.tuples(st.floats(-4, 4), st.floats(-4, 4), st.floats(-4, 4)),
    target=st.tuples(
        st.floats(-5, 5), st.floats(-5, 5), st.floats(-4, 4), st.sampled_from(list(PalletKind))
    ),
    others=st.lists(st.tuples(st.floats(-6, 6), st.floats(-6, 6), st.floats(-4, 4)), max_size=6),
    sigma=st.floats(0.0, 0.5),
)
def test_the_planner_never_raises(
    start: tuple[float, float, float],
    target: tuple[float, float, float, PalletKind],
    others: list[tuple[float, float, float]],
    sigma: float,
) -> None:
    covariance = np.diag([sigma**2, sigma**2, 0.01])
    pallet = Pallet(target[0], target[1], target[2], covariance, target[3], "target")
    pallets = [
        Pallet(x, y, yaw, SURE, PalletKind.JIS, f"p{i}") for i, (x, y, yaw) in enumerate(others)
    ]
    result = plan_pallet_approach(
        Pose2D(*start), PalletTarget(pallet), [pallet, *pallets], vehicle_shape(), _FUZZ_PARAMS
    )
    assert isinstance(result, PalletPlan | PlanRefusal)
    if isinstance(result, PalletPlan):
        assert np.isfinite(result.guide_xy_m).all()
        assert result.arc_m[-1] - result.straight_start_m >= 1.5 - 1e-9
    else:
        assert result.reason
