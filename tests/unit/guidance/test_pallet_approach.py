"""The approach controller: closed loop on the simulated forklift to each pallet of the
blind row, its refusals, and its wishes' limits under any input.

Measured (truth, at the stop; the worker's map 8 cm, 6 cm and 2° off; detections with
3 mm and 0.1° of noise): the fork tips within 1.5 mm of the pallet's axis, the heading
within 0.08°, the tips within 1.5 mm of the face, with an exact estimate and with one
4-5 cm and 0.5° off. Run with ``-s`` to see each run's figures.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.guidance.pallet_approach import (
    PalletApproach,
    PalletApproachParams,
    PalletPhase,
)
from appliance.guidance.pallet_geometry import Obstacle, overlaps
from appliance.guidance.pallet_plan import (
    PalletPlan,
    PalletPlanParams,
    PalletTarget,
    plan_pallet_approach,
)
from appliance.mapping.pallets import Pallet, PalletKind
from drivers.geometry import Pose2D
from tests.unit.guidance.pallet_scene import (
    ROW_B,
    START,
    approach_params,
    closed_loop,
    outline_polygons,
    site_plan,
    static_obstacles,
    true_pallets,
    vehicle_shape,
)

WORKER_ERROR = (0.08, -0.06, math.radians(2.0))
ESTIMATE_ERRORS = {
    "exact": (0.0, 0.0, 0.0),
    "off": (0.04, -0.03, math.radians(0.5)),
    "off_other_way": (-0.05, 0.04, math.radians(-0.5)),
}
SURE = np.diag([1e-4, 1e-4, 1e-6])
COVARIANCE = np.diag([0.01**2, 0.01**2, 1e-4])


@pytest.mark.parametrize("estimate", list(ESTIMATE_ERRORS))
@pytest.mark.parametrize("name", ROW_B)
def test_closed_loop_to_each_blind_pallet_ends_aligned_at_its_openings(
    name: str, estimate: str
) -> None:
    error = ESTIMATE_ERRORS[estimate]
    believed_start = Pose2D(START.x_m + error[0], START.y_m + error[1], START.yaw_rad + error[2])
    plan = site_plan(name, WORKER_ERROR, believed_start)
    assert isinstance(plan, PalletPlan), plan
    result = closed_loop(plan, name, error, seed=len(name) + len(estimate))
    print(
        f"\n{name} estimate {estimate}: {result.order.phase} after {result.sim_time_s:.0f} s;"
        f" tips {1000 * result.tips_lateral_m:+.2f} mm off the axis,"
        f" heading {math.degrees(result.heading_rad):+.3f}°,"
        f" tips {1000 * result.tips_past_face_m:+.2f} mm past the face;"
        f" off the path by {result.max_path_deviation_m:.3f} m at most"
    )
    assert result.order.phase is PalletPhase.DONE, result.order.refused
    # The goal is 10 mm and 0.3°; what it does is well inside.
    assert abs(result.tips_lateral_m) < 0.004
    assert abs(result.heading_rad) < math.radians(0.15)
    assert abs(result.tips_past_face_m) < 0.003
    assert result.max_path_deviation_m < plan_clearance()
    # The vehicle's true outline never touched a pallet on the way (the target's face
    # only at the end, by the tips' last millimetres) nor a wall.
    for polygons in outline_polygons(vehicle_shape(), list(result.truth)):
        for pallet in true_pallets():
            stop = len(polygons) - 50 if pallet.name == name else len(polygons)
            bare = Obstacle(pallet.name, np.array(pallet.corners_xy_m()))
            assert not overlaps(polygons[:stop], bare).any(), pallet.name
        for wall in static_obstacles():
            assert not overlaps(polygons, wall).any(), wall.name


def plan_clearance() -> float:
    return PalletPlanParams().clearance_m


# -- the phases by hand: a lone pallet straight ahead ---------------------------------


def _short_plan(kind: PalletKind = PalletKind.EUR) -> PalletPlan:
    """A lone pallet at (10, 0), the vehicle 2 m before the view pose of its -x face:
    the plan is the final straight alone."""
    pallet = Pallet(10.0, 0.0, 0.0, SURE, kind, "lone")
    shape = vehicle_shape()
    face_x = 10.0 - kind.length_m / 2.0
    start = Pose2D(face_x - 1.5 - shape.tips_forward_m - 2.0, 0.0, 0.0)
    plan = plan_pallet_approach(start, PalletTarget(pallet), [pallet], shape, PalletPlanParams())
    assert isinstance(plan, PalletPlan), plan
    assert plan.length_m == pytest.approx(2.0, abs=0.05)
    return plan


def _plan_start(plan: PalletPlan) -> Pose2D:
    x, y = plan.guide_xy_m[0]
    return vehicle_shape().centre_of(Pose2D(float(x), float(y), 0.0))


def _at_view_pose(plan: PalletPlan, params: PalletApproachParams | None = None) -> PalletApproach:
    controller = PalletApproach(plan, params or approach_params())
    order = controller.update(plan.view_pose, COVARIANCE, 0.0, 0.0)
    assert order.phase is PalletPhase.REDETECT
    return controller


def _detection(
    x: float = 10.0, y: float = 0.0, yaw: float = 0.0, kind: PalletKind = PalletKind.EUR
) -> Pallet:
    return Pallet(x, y, yaw, SURE, kind, "seen")


def test_standing_at_the_view_pose_it_waits_for_the_pallet_then_goes_in() -> None:
    plan = _short_plan()
    controller = _at_view_pose(plan)
    for i in range(4):
        order = controller.update(plan.view_pose, COVARIANCE, 0.0, 0.1 * (i + 1), _detection())
        assert order.phase is PalletPhase.REDETECT
        assert order.speed_mps == 0.0
        assert order.waiting
    order = controller.update(plan.view_pose, COVARIANCE, 0.0, 0.5, _detection(yaw=math.pi))
    assert order.phase is PalletPhase.FINAL
    assert order.speed_mps > 0.0
    assert order.distance_m == pytest.approx(1.5, abs=1e-6)  # the standoff


@pytest.mark.parametrize(
    ("seen", "why"),
    [
        (_detection(kind=PalletKind.JIS), "a 1100x1100 pallet, not 1200x800"),
        (_detection(x=10.7), "0.70 m from where the map puts the target"),
        (None, "not detected again within 10 s"),
    ],
)
def test_no_fitting_detection_within_the_timeout_is_refused(seen: Pallet | None, why: str) -> None:
    plan = _short_plan()
    controller = _at_view_pose(plan)
    order = controller.update(plan.view_pose, COVARIANCE, 0.0, 1.0, seen)
    for t in np.arange(1.0, 10.0, 0.5):
        order = controller.update(plan.view_pose, COVARIANCE, 0.0, float(t), seen)
        assert order.phase is PalletPhase.REDETECT
    order = controller.update(plan.view_pose, COVARIANCE, 0.0, 10.5, seen)
    assert order.phase is PalletPhase.REFUSED
    assert why in order.refused
    assert order.speed_mps == 0.0


def test_a_pallet_too_far_off_to_line_up_is_refused_with_the_detection_kept() -> None:
    plan = _short_plan()
    controller = _at_view_pose(plan)
    off = _detection(y=0.35, yaw=math.radians(4.0))
    for i in range(5):
        order = controller.update(plan.view_pose, COVARIANCE, 0.0, 0.1 * i, off)
    assert order.phase is PalletPhase.REFUSED
    assert "plan again from the detection" in order.refused
    kept = controller.detected_pallet
    assert kept is not None
    assert (kept.x_m, kept.y_m) == pytest.approx((10.0, 0.35))


def _in_final(plan: PalletPlan, params: PalletApproachParams | None = None) -> PalletApproach:
    controller = _at_view_pose(plan, params)
    for i in range(5):
        order = controller.update(plan.view_pose, COVARIANCE, 0.0, 0.1 * i, _detection())
    assert order.phase is PalletPhase.FINAL
    return controller


def test_stopped_misaligned_at_the_pallet_is_refused_not_pushed_in() -> None:
    plan = _short_plan()
    controller = _in_final(plan)
    # The tips at the face, 2 cm to the side (as if the vehicle had been shoved).
    at_face = Pose2D(9.4 - vehicle_shape().tips_forward_m, 0.02, 0.0)
    order = controller.update(at_face, COVARIANCE, 0.0, 1.0)
    assert order.phase is PalletPhase.REFUSED
    assert "stopped misaligned" in order.refused
    assert "+20.0 mm" in order.refused
    aligned = _in_final(plan)
    order = aligned.update(at_face._replace(y_m=0.004), COVARIANCE, 0.0, 1.0)
    assert order.phase is PalletPhase.DONE
    assert order.lateral_error_m == pytest.approx(0.004)


def test_a_lost_pose_stops_at_once_and_is_refused_when_it_lasts() -> None:
    plan = _short_plan()
    controller = PalletApproach(plan, approach_params())
    start = _plan_start(plan)
    assert controller.update(start, COVARIANCE, 0.0, 0.0).speed_mps > 0.0
    order = controller.update(None, None, 0.5, 0.1)
    assert (order.phase, order.speed_mps, order.waiting) == (
        PalletPhase.TO_VIEW,
        0.0,
        "the pose estimate is lost",
    )
    unsure = np.diag([1.0, 1.0, 0.1])  # a metre of σ: as good as lost
    assert controller.update(start, unsure, 0.5, 0.3).speed_mps == 0.0
    assert controller.update(start, COVARIANCE, 0.4, 0.4).speed_mps > 0.0  # back
    controller.update(None, None, 0.4, 1.0)
    order = controller.update(None, None, 0.2, 1.6)
    assert order.phase is PalletPhase.REFUSED
    assert "lost" in order.refused


def test_straying_from_the_path_is_refused() -> None:
    plan = _short_plan()
    controller = PalletApproach(plan, approach_params())
    start = _plan_start(plan)
    order = controller.update(start._replace(y_m=0.5), COVARIANCE, 0.3, 0.0)
    assert order.phase is PalletPhase.REFUSED
    assert "off the planned path" in order.refused


finite = st.floats(-1e6, 1e6)
pose = st.builds(Pose2D, finite, finite, finite)
pallet = st.builds(
    Pallet,
    st.floats(-100, 100),
    st.floats(-100, 100),
    st.floats(-10, 10),
    st.just(SURE),
    st.sampled_from(list(PalletKind)),
)
covariance = st.one_of(
    st.none(),
    st.just(COVARIANCE),
    st.lists(st.floats(-1e3, 1e3), min_size=9, max_size=9).map(lambda v: np.array(v).reshape(3, 3)),
)
cycle = st.tuples(
    st.one_of(
        st.none(), pose, pose.map(lambda p: Pose2D(p.x_m % 12.0, p.y_m % 0.3, p.yaw_rad % 0.1))
    ),
    covariance,
    st.floats(-5, 5),
    st.floats(0, 1e4),
    st.one_of(st.none(), pallet, st.just(_detection()), st.just(_detection(0.0, 0.01, 0.01))),
)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(st.sampled_from(["to_view", "redetect", "final"]), st.lists(cycle, max_size=25))
def test_the_wish_is_finite_and_within_the_limits_whatever_comes_in(
    phase: str, cycles: list[tuple[Pose2D | None, np.ndarray | None, float, float, Pallet | None]]
) -> None:
    plan = _short_plan()
    params = approach_params()
    if phase == "to_view":
        controller = PalletApproach(plan, params)
    elif phase == "redetect":
        controller = _at_view_pose(plan, params)
    else:
        controller = _in_final(plan, params)
    for estimate, cov, speed, t, detection in cycles:
        order = controller.update(estimate, cov, speed, t, detection)
        assert math.isfinite(order.speed_mps)
        assert math.isfinite(order.steer_rad)
        assert 0.0 <= order.speed_mps <= params.cruise_speed_mps
        assert abs(order.steer_rad) <= params.max_steer_rad
        if order.phase in (PalletPhase.DONE, PalletPhase.REFUSED, PalletPhase.REDETECT):
            assert order.speed_mps == 0.0
        if order.phase is PalletPhase.REFUSED:
            assert order.refused
