"""The route planner: its projection against brute force, Fig. 5's direction, the crossing."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.guidance.route_planner import (
    PlannerOutput,
    PlannerParams,
    PlannerRefusal,
    RoutePlanner,
    TravelDirection,
    clean_route,
    engagement_check,
)

STRAIGHT = np.array([[0.0, 0.0], [25.0, 0.0], [50.0, 0.0], [100.0, 0.0]])


def _ok(result: PlannerOutput | PlannerRefusal) -> PlannerOutput:
    assert isinstance(result, PlannerOutput), result
    return result


def _nearest_brute_force(route: np.ndarray, point: np.ndarray) -> tuple[float, float]:
    """(distance, arc length) of the nearest point over every segment, written out."""
    a, d = route[:-1], np.diff(route, axis=0)
    lengths = np.hypot(d[:, 0], d[:, 1])
    t = np.clip(np.einsum("ij,ij->i", point - a, d) / lengths**2, 0.0, 1.0)
    distances = np.hypot(*(a + t[:, None] * d - point).T)
    i = int(np.argmin(distances))
    return float(distances[i]), float(np.sum(lengths[:i]) + t[i] * lengths[i])


def _point_at(route: np.ndarray, s: float) -> np.ndarray:
    lengths = np.hypot(*np.diff(route, axis=0).T)
    for a, b, length in zip(route[:-1], route[1:], lengths, strict=True):
        if s <= length:
            return np.asarray(a + (b - a) * (s / length))
        s -= length
    return np.asarray(route[-1])


def _wave(n: int = 400, spacing_m: float = 0.5) -> np.ndarray:
    x = np.arange(n) * spacing_m
    return np.column_stack([x, 8.0 * np.sin(x / 15.0)])


# -- the route -----------------------------------------------------------------------------


def test_consecutive_duplicates_are_removed_and_non_routes_refused() -> None:
    route = [[0, 0], [0, 0], [1, 0], [1, 0], [1, 0], [1, 1], [0, 0]]
    assert clean_route(route).tolist() == [[0, 0], [1, 0], [1, 1], [0, 0]]
    cases: list[tuple[object, str]] = [
        ([[0, 0]], "two distinct"),
        ([[1, 1], [1, 1]], "two distinct"),
        ([[0, 0, 0], [1, 1, 1]], "shape"),
        ([[0, 0], [math.nan, 1]], "finite"),
        (np.zeros((0, 2)), "none"),
    ]
    for bad, why in cases:
        with pytest.raises(ValueError, match=why):
            RoutePlanner(bad)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="allowed"):
        RoutePlanner(STRAIGHT, allowed="sideways")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="coarse_stride"):
        PlannerParams(coarse_stride=0)
    with pytest.raises(ValueError, match="behind_m"):
        PlannerParams(behind_m=0.0)


# -- the projection ------------------------------------------------------------------------


@settings(max_examples=60)
@given(
    st.lists(st.tuples(st.floats(0.3, 3.0), st.floats(-math.pi, math.pi)), min_size=2, max_size=60),
    st.floats(-40.0, 40.0),
    st.floats(-40.0, 40.0),
)
def test_first_projection_is_the_nearest_point_on_any_polyline(
    steps: list[tuple[float, float]], px: float, py: float
) -> None:
    """The coarse pass bounds what each group of segments can hold, so it misses none."""
    route = np.vstack(
        [[0.0, 0.0], np.cumsum([[r * math.cos(a), r * math.sin(a)] for r, a in steps], axis=0)]
    )
    out = _ok(RoutePlanner(route).update((px, py), 0.0, 0.0))
    distance, _ = _nearest_brute_force(route, np.array([px, py]))
    assert out.distance_to_route_m == pytest.approx(distance, abs=1e-9)
    assert math.hypot(out.point_m[0] - px, out.point_m[1] - py) == pytest.approx(distance, abs=1e-9)


@given(st.floats(0.0, 199.0), st.floats(-3.0, 3.0))
def test_reduced_density_search_is_exact_on_a_smooth_route(x: float, offset: float) -> None:
    route = _wave()
    point = np.array([x, 8.0 * math.sin(x / 15.0) + offset])
    out = _ok(RoutePlanner(route).update(point, 0.0, 0.0))
    distance, s = _nearest_brute_force(route, point)
    assert out.distance_to_route_m == pytest.approx(distance, abs=1e-9)
    assert out.arc_length_m == pytest.approx(s, abs=1e-6)


def test_tracking_stays_exact_while_driving() -> None:
    route = _wave()
    planner = RoutePlanner(route)
    for k in range(0, 1900):
        x = 0.1 * k
        point = np.array([x, 8.0 * math.sin(x / 15.0) + 1.5 * math.sin(k / 50.0)])
        out = _ok(planner.update(point, 0.3, 0.02 * k))
        assert out.distance_to_route_m == pytest.approx(
            _nearest_brute_force(route, point)[0], abs=1e-9
        )
    assert planner.jumps_refused == 0


def test_a_straight_route_forward_and_backward() -> None:
    forward = _ok(RoutePlanner(STRAIGHT).update((30.0, 2.0), 0.1, 0.0))
    assert forward.direction is TravelDirection.FORWARD
    assert forward.segment_index == 1
    assert forward.fraction == pytest.approx(0.2)
    assert forward.point_m == pytest.approx((30.0, 0.0))
    assert forward.arc_length_m == pytest.approx(30.0)
    assert forward.progress_m == pytest.approx(30.0)
    assert forward.progress_fraction == pytest.approx(0.3)
    assert forward.remaining_m == pytest.approx(70.0)
    assert forward.cross_track_m == pytest.approx(2.0)  # left of travel
    assert forward.path_heading_rad == pytest.approx(0.0)
    assert forward.heading_error_rad == pytest.approx(0.1)
    assert forward.distance_to_route_m == pytest.approx(2.0)

    backward = _ok(RoutePlanner(STRAIGHT).update((30.0, 2.0), math.pi - 0.1, 0.0))
    assert backward.direction is TravelDirection.REVERSE
    assert backward.arc_length_m == pytest.approx(30.0)  # route order is route order
    assert backward.progress_m == pytest.approx(70.0)
    assert backward.remaining_m == pytest.approx(30.0)
    assert backward.cross_track_m == pytest.approx(-2.0)  # driving −x, +y is on the right
    assert abs(backward.path_heading_rad) == pytest.approx(math.pi)
    assert backward.heading_error_rad == pytest.approx(-0.1)


@given(st.floats(0.0, 90.0), st.booleans(), st.floats(0.5, 5.0), st.floats(1.0, 40.0))
def test_local_path_is_in_travel_order_around_the_projection(
    s: float, reverse: bool, behind: float, ahead: float
) -> None:
    route = np.array([[0.0, 0.0], [20.0, 0.0], [20.0, 30.0], [50.0, 30.0], [50.0, 40.0]])
    total = 90.0
    planner = RoutePlanner(route, PlannerParams(behind_m=behind, ahead_m=ahead))
    point = _point_at(route, s)
    heading = math.atan2(
        *(_point_at(route, min(s + 0.01, total)) - _point_at(route, max(s - 0.01, 0.0)))[::-1]
    )
    out = _ok(planner.update(point, heading + (math.pi if reverse else 0.0), 0.0))
    path = out.local_path_m
    # from behind to ahead of the projection in the travel direction, clipped at the ends
    sign = -1.0 if reverse else 1.0
    start_s = min(max(s - sign * behind, 0.0), total)
    end_s = min(max(s + sign * ahead, 0.0), total)
    assert path[0] == pytest.approx(_point_at(route, start_s), abs=1e-9)
    assert path[-1] == pytest.approx(_point_at(route, end_s), abs=1e-9)
    assert float(np.sum(np.hypot(*np.diff(path, axis=0).T))) == pytest.approx(abs(end_s - start_s))
    assert np.all(np.hypot(*np.diff(path, axis=0).T) > 1e-9)  # no zero-length segments
    k, f = out.local_segment_index, out.local_fraction
    assert path[k] + f * (path[k + 1] - path[k]) == pytest.approx(np.array(out.point_m), abs=1e-9)
    assert out.progress_m + out.remaining_m == pytest.approx(total)
    assert 0.0 <= out.progress_fraction <= 1.0
    assert not path.flags.writeable


# -- Fig. 5: the direction -----------------------------------------------------------------


@given(st.floats(-math.pi, math.pi))
def test_direction_comes_from_the_side_of_the_normal_the_heading_is_on(heading: float) -> None:
    out = _ok(RoutePlanner(STRAIGHT).update((40.0, 1.0), heading, 0.0))
    expected = TravelDirection.FORWARD if math.cos(heading) > 0 else TravelDirection.REVERSE
    assert out.direction is expected
    assert abs(out.heading_error_rad) <= math.pi / 2 + 1e-12


def test_direction_is_latched_until_reset() -> None:
    planner = RoutePlanner(STRAIGHT)
    assert _ok(planner.update((10.0, 0.0), 0.0, 0.0)).direction is TravelDirection.FORWARD
    wobble = _ok(planner.update((10.1, 0.0), math.radians(100.0), 0.02))
    assert wobble.direction is TravelDirection.FORWARD
    assert wobble.heading_error_rad == pytest.approx(math.radians(100.0))
    planner.reset()
    assert _ok(planner.update((10.1, 0.0), math.pi, 0.04)).direction is TravelDirection.REVERSE


def test_a_one_way_route_refuses_the_other_way() -> None:
    planner = RoutePlanner(STRAIGHT, allowed="forward")
    refusal = planner.update((10.0, 0.0), math.radians(170.0), 0.0)
    assert refusal == PlannerRefusal("heading 170° from the route (it may be driven forward only)")
    assert _ok(planner.update((10.0, 0.0), 0.0, 0.1)).direction is TravelDirection.FORWARD
    reverse_only = RoutePlanner(STRAIGHT, allowed="reverse")
    assert isinstance(reverse_only.update((10.0, 0.0), 0.2, 0.0), PlannerRefusal)
    assert _ok(reverse_only.update((10.0, 0.0), math.pi, 0.1)).direction is TravelDirection.REVERSE


# -- the position-change threshold ---------------------------------------------------------


def _figure_eight(a_m: float, n: int) -> np.ndarray:
    """Gerono's lemniscate: x = a sin t, y = a sin t cos t, crossing itself at the origin."""
    t = np.linspace(0.5 * math.pi, 2.5 * math.pi, n, endpoint=False)  # from a lobe's tip
    return np.column_stack([a_m * np.sin(t), a_m * np.sin(t) * np.cos(t)])


def _drive_through_the_crossing(planner: RoutePlanner, route: np.ndarray) -> list[PlannerOutput]:
    """4.5 m/s along the first branch, 0.3 m to its left: at the crossing the other branch
    (at right angles) runs through the anchor, nearer than the branch being driven."""
    lengths = np.hypot(*np.diff(route, axis=0).T)
    cum = np.concatenate(([0.0], np.cumsum(lengths)))
    outputs = []
    for k in range(int(cum[-1] / (4.5 * 0.02)) - 1):
        s = 4.5 * 0.02 * k
        i = min(int(np.searchsorted(cum, s, side="right")) - 1, len(lengths) - 1)
        tangent = (route[i + 1] - route[i]) / lengths[i]
        anchor = _point_at(route, s) + 0.3 * np.array([-tangent[1], tangent[0]])
        outputs.append(_ok(planner.update(anchor, math.atan2(tangent[1], tangent[0]), 0.02 * k)))
    return outputs


def test_driving_through_a_crossing_stays_on_the_branch() -> None:
    route = _figure_eight(8.0, 500)  # ~49 m long: the other branch is inside the window
    planner = RoutePlanner(route)
    outputs = _drive_through_the_crossing(planner, route)
    arcs = np.array([o.arc_length_m for o in outputs])
    assert np.all(np.diff(arcs) > 0.0)
    assert np.all(np.diff(arcs) < 4.5 * 0.02 * 1.5)
    assert all(o.cross_track_m == pytest.approx(0.3, abs=0.01) for o in outputs)
    assert planner.jumps_refused > 0
    assert sum(o.jump_refused for o in outputs) == planner.jumps_refused
    # without the threshold the same drive jumps to the other branch: the test can fail
    loose = RoutePlanner(route, PlannerParams(max_speed_mps=1e4))
    arcs = np.array([o.arc_length_m for o in _drive_through_the_crossing(loose, route)])
    assert np.max(np.abs(np.diff(arcs))) > 5.0


def test_a_large_figure_eight_needs_no_refusal() -> None:
    route = _figure_eight(40.0, 2000)  # the other branch is far outside the window
    planner = RoutePlanner(route)
    outputs = _drive_through_the_crossing(planner, route)
    assert np.all(np.diff([o.arc_length_m for o in outputs]) > 0.0)
    assert planner.jumps_refused == 0


def test_after_a_pause_the_reach_grows_with_the_time() -> None:
    planner = RoutePlanner(STRAIGHT)
    _ok(planner.update((10.0, 0.0), 0.0, 0.0))
    near = _ok(planner.update((40.0, 0.0), 0.0, 0.1))  # 30 m in 0.1 s: not possible
    assert near.jump_refused and near.arc_length_m == pytest.approx(10.0 + 10.0 * 0.1 + 1.0)
    far = _ok(planner.update((40.0, 0.0), 0.0, 5.0))  # 5 s later it is
    assert not far.jump_refused and far.arc_length_m == pytest.approx(40.0)


def test_bad_updates_are_refused() -> None:
    planner = RoutePlanner(STRAIGHT)
    assert planner.update((math.nan, 0.0), 0.0, 0.0) == PlannerRefusal("anchor position not finite")
    assert isinstance(planner.update((0.0, 0.0), math.inf, 0.0), PlannerRefusal)
    _ok(planner.update((1.0, 0.0), 0.0, 1.0))
    assert planner.update((1.0, 0.0), 0.0, 0.5) == PlannerRefusal("time went backwards")
    with pytest.raises(ValueError, match="anchor point"):
        planner.update((1.0, 2.0, 3.0), 0.0, 2.0)


# -- engagement ----------------------------------------------------------------------------


def test_engagement_reasons_are_stated() -> None:
    assert engagement_check(_ok(RoutePlanner(STRAIGHT).update((30.0, 2.0), 0.0, 0.0))) == ()
    far = _ok(RoutePlanner(STRAIGHT).update((30.0, 12.4), 0.0, 0.0))
    assert engagement_check(far) == ("12.4 m from route, limit 10 m",)
    planner = RoutePlanner(STRAIGHT)
    planner.update((30.0, 0.0), 0.0, 0.0)
    turned = _ok(planner.update((30.0, 0.0), math.radians(104.0), 0.1))
    assert engagement_check(turned) == ("heading 104° from the route",)
    assert engagement_check(turned, max_heading_error_rad=math.radians(110.0)) == ()
    assert engagement_check(PlannerRefusal("time went backwards")) == ("time went backwards",)
