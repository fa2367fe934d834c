"""The feasibility check: the vehicle's turning radius against a hand computation and the
simulated vehicle, tight turns refused where they are, self-overlaps, gaps and repeats."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.localization.local_frame import LocalFrame
from appliance.routes.check import (
    CheckParams,
    ProblemKind,
    Severity,
    check_route,
    min_turn_radius_m,
    turn_radius_at_centre_m,
)
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.pc104.messages import MotionPattern
from tests.unit.routes.courses import ArcCourse

HUSKY = load_config("husky")


def _centre_radius_by_instant_centre(wheelbase_m: float, k: float, steer_deg: float) -> float:
    """Where the perpendiculars to the front and rear wheels meet (the instant centre of
    rotation), and its distance from the geometric centre: axles at x = ±L/2, the front
    wheel at +φ, the rear counter-steered at -kφ."""
    phi = math.radians(steer_deg)
    front = np.array([wheelbase_m / 2, 0.0])
    rear = np.array([-wheelbase_m / 2, 0.0])
    front_normal = np.array([-math.sin(phi), math.cos(phi)])
    rear_normal = np.array([-math.sin(-k * phi), math.cos(-k * phi)])
    # front + a * front_normal = rear + b * rear_normal
    a, _b = np.linalg.solve(np.column_stack((front_normal, -rear_normal)), rear - front)
    centre_of_turn = front + a * front_normal
    return float(np.hypot(*centre_of_turn))


def test_husky_turning_radius_by_hand() -> None:
    """L 3.6 m, k 0.63, 32°: tan 32° = 0.624869, tan 20.16° = 0.367136, so the axis
    point's radius is 3.6 / 0.992005 = 3.6290 m (the brief's L / (tan φ + tan kφ)), and the
    centre's 3.6290 * sqrt(1 + 0.128867²) = 3.6590 m."""
    assert 3.6 / (math.tan(math.radians(32)) + math.tan(math.radians(0.63 * 32))) == (
        pytest.approx(3.6290, abs=1e-4)
    )
    assert min_turn_radius_m(HUSKY) == pytest.approx(3.6590, abs=1e-4)
    assert min_turn_radius_m(HUSKY) == pytest.approx(
        _centre_radius_by_instant_centre(3.6, 0.63, 32.0), rel=1e-12
    )


@given(
    st.floats(1.0, 20.0),
    st.floats(0.0, 1.5),
    st.floats(5.0, 40.0),
)
def test_turning_radius_is_the_instant_centres_distance(
    wheelbase_m: float, k: float, steer_deg: float
) -> None:
    assert turn_radius_at_centre_m(wheelbase_m, k, math.radians(steer_deg)) == pytest.approx(
        _centre_radius_by_instant_centre(wheelbase_m, k, steer_deg), rel=1e-9
    )


def test_with_equal_counter_steer_the_radius_is_half_the_wheelbase_over_tan() -> None:
    assert turn_radius_at_centre_m(4.0, 1.0, math.radians(30)) == pytest.approx(
        4.0 / (2 * math.tan(math.radians(30))), rel=1e-12
    )


def test_the_simulated_husky_drives_the_circle_at_full_steer() -> None:
    """The simulated vehicle at full counter-steer and a crawl (G_ss ≈ 1) draws a circle of
    the check's radius: fitted by least squares to its centre's track."""
    params = VehicleParams.from_config(HUSKY)
    phi = params.max_steer_angle_rad
    state = VehicleState(
        speed_mps=0.2, front_steer_rad=phi, rear_steer_rad=params.counter_steer_ratio_k * phi
    )
    command = VehicleCommand(
        pattern=MotionPattern.COUNTER_STEER, front_steer_rad=phi, throttle_pct=1.0, brake_pct=0.0
    )
    track = []
    for _ in range(2500):
        state = step(state, command, 0.05, params)
        track.append((state.x_m, state.y_m))
    x, y = np.array(track).T
    # x² + y² = 2 a x + 2 b y + c: linear in a, b, c; r² = c + a² + b².
    (a, b, c), *_ = np.linalg.lstsq(np.column_stack((2 * x, 2 * y, np.ones_like(x))), x**2 + y**2)
    gain = 1.0 / (1.0 + (state.speed_mps / params.characteristic_speed_mps) ** 2)
    assert math.sqrt(c + a**2 + b**2) * gain == pytest.approx(min_turn_radius_m(HUSKY), rel=1e-3)


def test_a_3_m_arc_is_refused_for_the_husky_at_the_arc() -> None:
    """The Husky turns down to 3.66 m: a 3 m arc is refused, its place is on the arc."""
    course = ArcCourse(radius_m=3.0)
    frame = LocalFrame(52.0, 9.0, 80.0)
    report = check_route(course.points(0.25), min_turn_radius_m(HUSKY), frame=frame)
    assert report.refused
    (turn,) = [p for p in report.problems if p.kind is ProblemKind.TIGHT_TURN]
    place = turn.place
    assert place is not None
    assert course.lead_m < place.distance_m < course.lead_m + course.arc_m
    assert math.dist((place.east_m, place.north_m), course.centre_m) == pytest.approx(3.0, abs=0.01)
    assert place.index == round(
        place.distance_m / (course.length_m / (len(course.points(0.25)) - 1))
    )
    assert turn.radius_m == pytest.approx(3.0, abs=0.03)
    lat, lon, _ = frame.to_geodetic(place.east_m, place.north_m)
    assert (place.lat_deg, place.lon_deg) == pytest.approx((lat, lon), abs=1e-9)
    assert f"point {place.index}, {place.distance_m:.1f} m from the start" in turn.message
    assert "radius 3.0" in turn.message and "3.66 m" in turn.message


@pytest.mark.parametrize("radius_m", [4.0, 10.0, 20.0])
def test_arcs_the_husky_can_turn_pass_cleanly(radius_m: float) -> None:
    report = check_route(ArcCourse(radius_m=radius_m).points(0.5), min_turn_radius_m(HUSKY))
    assert not report.refused
    assert report.problems == ()
    assert report.min_radius_found_m == pytest.approx(radius_m, rel=0.02)


def test_a_kink_is_refused_at_its_corner() -> None:
    points = np.array(
        [(float(x), 0.0) for x in range(11)] + [(10.0, float(y)) for y in range(1, 11)]
    )
    report = check_route(points, min_turn_radius_m(HUSKY))
    (turn,) = report.problems
    assert turn.kind is ProblemKind.TIGHT_TURN and turn.place is not None
    assert (turn.place.index, turn.place.east_m, turn.place.north_m) == (10, 10.0, 0.0)
    # The circle through the corner and the route's own points 1 m either side (1 and 2 m
    # are equally near 1.5 m: the nearer wins): radius √2 / 2.
    assert turn.radius_m == pytest.approx(math.sqrt(2) / 2, rel=1e-9)


def test_point_noise_does_not_fake_tight_turns() -> None:
    """1 cm of noise on every point 0.5 m apart, a kilometre straight: nothing refused."""
    rng = np.random.default_rng(7)
    points = np.column_stack((np.arange(0.0, 1000.0, 0.5), np.zeros(2000)))
    report = check_route(points + rng.normal(0.0, 0.01, points.shape), min_turn_radius_m(HUSKY))
    assert not report.refused
    assert report.min_radius_found_m > 10.0


def _figure_eight(count: int = 600) -> np.ndarray:
    """x = 20 sin t, y = 10 sin 2t from t = π/4 (away from the crossing at t = 0, π)
    for 0.95 of a turn: it crosses itself once, at the origin (t = π)."""
    t = np.linspace(math.pi / 4, math.pi / 4 + 0.95 * math.tau, count)
    return np.column_stack((20 * np.sin(t), 10 * np.sin(2 * t)))


def test_a_figure_eight_is_flagged_at_its_crossing_with_both_places() -> None:
    points = _figure_eight()
    report = check_route(points, min_turn_radius_m(HUSKY))
    assert not report.refused
    (overlap,) = [p for p in report.problems if p.kind is ProblemKind.SELF_OVERLAP]
    assert overlap.severity is Severity.WARN
    assert overlap.place is not None and overlap.other is not None
    steps = np.hypot(*np.diff(points, axis=0).T)
    s_m = np.concatenate(([0.0], np.cumsum(steps)))
    # t = π is index (π - π/4) / (0.95 τ) * (count - 1) along the line; the first pass
    # through the origin is there, the second at t = 2π.
    first_index = (math.pi - math.pi / 4) / (0.95 * math.tau) * 599
    second_index = (2 * math.pi - math.pi / 4) / (0.95 * math.tau) * 599
    crossing_s = [float(np.interp(i, np.arange(600), s_m)) for i in (first_index, second_index)]
    assert "crosses itself" in overlap.message
    for place, expected_s in zip((overlap.place, overlap.other), crossing_s, strict=True):
        assert math.hypot(place.east_m, place.north_m) < 0.5
        assert place.distance_m == pytest.approx(expected_s, abs=0.5)


def test_a_return_leg_beside_the_outward_one_is_flagged() -> None:
    """Out 30 m east, a wide loop (radius 6 m), back west 1.5 m north of the way out, for
    about 20 m (so the end is not near the start)."""
    out = [(x, 0.0) for x in np.arange(0.0, 30.0, 0.5)]
    theta = np.linspace(-math.pi / 2, math.pi / 2 + math.asin(4.5 / 6), 60)[1:]
    loop = [(30.0 + 6 * math.cos(a), 6.0 + 6 * math.sin(a)) for a in theta]
    end_x = loop[-1][0]
    back = [(x, 1.5) for x in np.arange(end_x - 0.5, 10.0, -0.5)]
    points = np.array(out + loop + [(end_x, 1.5)] + back)
    report = check_route(points, min_turn_radius_m(HUSKY))
    overlaps = [p for p in report.problems if p.kind is ProblemKind.SELF_OVERLAP]
    assert overlaps and all("beside itself" in p.message for p in overlaps)
    first = overlaps[0]
    assert first.place is not None and first.other is not None
    assert first.place.north_m == pytest.approx(0.0, abs=1e-9)
    assert first.other.north_m == pytest.approx(1.5, abs=0.02)


def test_a_closed_loop_is_named_as_one() -> None:
    angle = np.linspace(0.0, math.tau, 200)
    points = np.column_stack((10 * np.cos(angle), 10 * np.sin(angle)))
    (overlap,) = check_route(points, min_turn_radius_m(HUSKY)).problems
    assert "ends 0.00 m from where it starts (a loop)" in overlap.message


def test_a_u_turn_the_vehicle_can_make_is_not_an_overlap() -> None:
    report = check_route(ArcCourse(radius_m=4.0, turn_deg=180.0).points(0.25), 3.66)
    assert report.problems == ()


def test_gaps_and_repeats_are_flagged_where_they_are() -> None:
    points = np.array([(0.0, 0.0), (1.0, 0.0), (1.0, 0.0), (1.004, 0.0), (2.0, 0.0), (40.0, 0.0)])
    report = check_route(points, 3.66)
    assert not report.refused
    by_kind = {p.kind: p for p in report.problems}
    assert "2 point(s) repeat the one before" in by_kind[ProblemKind.DUPLICATE].message
    assert "the first is point 2" in by_kind[ProblemKind.DUPLICATE].message
    gap = by_kind[ProblemKind.GAP]
    assert gap.place is not None and gap.other is not None
    assert (gap.place.index, gap.other.index) == (4, 5)
    assert gap.message.startswith("38.0 m between point 4, 2.0 m from the start")


def test_unusable_routes_are_refused() -> None:
    same = check_route(np.array([(1.0, 1.0), (1.0, 1.0), (1.0, 1.0)]), 3.66)
    assert same.refused and "fewer than 2 distinct points" in same.problems[0].message
    far = check_route(np.array([(0.0, 0.0), (150_000.0, 0.0)]), 3.66)
    assert far.refused and "150.0 km long" in far.problems[0].message
    with pytest.raises(ValueError, match="finite"):
        check_route(np.array([(0.0, 0.0), (math.nan, 1.0)]), 3.66)


@given(st.floats(-math.pi, math.pi), st.floats(-5000, 5000), st.floats(-5000, 5000))
@settings(max_examples=30)
def test_the_check_does_not_depend_on_where_the_route_lies(
    angle_rad: float, east_m: float, north_m: float
) -> None:
    """Rotated and moved, a route's findings are the same at the same distances."""
    kink = [(float(x), 0.0) for x in range(11)] + [(10.0, float(y)) for y in range(1, 21)]
    points = np.vstack((kink, _figure_eight(300) + np.array([10.0, 41.0])))
    rotation = np.array(
        [[math.cos(angle_rad), -math.sin(angle_rad)], [math.sin(angle_rad), math.cos(angle_rad)]]
    )
    moved = points @ rotation.T + (east_m, north_m)
    here, there = check_route(points, 3.66), check_route(moved, 3.66)
    assert [p.kind for p in here.problems] == [p.kind for p in there.problems]
    for a, b in zip(here.problems, there.problems, strict=True):
        assert a.place is not None and b.place is not None
        # Within one densified step (0.5 m): a near-tie for the closest pair may flip.
        assert abs(b.place.index - a.place.index) <= 1
        assert b.place.distance_m == pytest.approx(a.place.distance_m, abs=0.6)
    assert there.min_radius_found_m == pytest.approx(here.min_radius_found_m, rel=1e-6)


def test_the_figure_eights_tightest_turn_is_found() -> None:
    """Its curvature |x'y'' - y'x''| / |v|³ written out: tightest 4.175 m at t = 2.24; the
    3 m span reads it 3 % wider (the tight stretch is short), so 4.0 passes, 4.5 refuses."""
    t = np.linspace(0.0, math.tau, 200_001)
    dx, dy, ddx, ddy = 20 * np.cos(t), 20 * np.cos(2 * t), -20 * np.sin(t), -40 * np.sin(2 * t)
    tightest_m = 1.0 / float(np.max(np.abs(dx * ddy - dy * ddx) / (dx**2 + dy**2) ** 1.5))
    assert tightest_m == pytest.approx(4.175, abs=1e-3)
    points = _figure_eight()
    assert check_route(points, 3.66).min_radius_found_m == pytest.approx(tightest_m, rel=0.04)
    assert not check_route(points, 4.0).refused
    refused = check_route(points, 4.5)
    assert refused.refused
    assert {p.kind for p in refused.problems} == {ProblemKind.TIGHT_TURN, ProblemKind.SELF_OVERLAP}


def test_the_overlap_distance_is_a_parameter() -> None:
    """The return leg 1.5 m beside the outward one: flagged at 2 m, not at 1 m."""
    out = np.column_stack((np.arange(0.0, 30.0, 0.5), np.zeros(60)))
    back = np.column_stack((np.arange(30.0, 0.0, -0.5), np.full(60, 1.5)))
    points = np.vstack((out, back))
    kinds = {p.kind for p in check_route(points, 0.5).problems}
    assert ProblemKind.SELF_OVERLAP in kinds
    params = CheckParams(overlap_distance_m=1.0)
    assert ProblemKind.SELF_OVERLAP not in {
        p.kind for p in check_route(points, 0.5, params).problems
    }


coordinates = st.floats(-200.0, 200.0, allow_nan=False).map(lambda v: round(v, 1))


@given(st.lists(st.tuples(coordinates, coordinates), min_size=0, max_size=80))
@settings(max_examples=60)
def test_any_points_give_a_report_with_places_on_the_route(
    points: list[tuple[float, float]],
) -> None:
    """Duplicates, zig-zags, a single point, collinear reversals: always a report, and every
    place it names is a point of the route at its distance along it."""
    array = np.array(points, dtype=np.float64).reshape(-1, 2)
    report = check_route(array, 3.66)
    steps = np.hypot(*np.diff(array, axis=0).T) if len(array) > 1 else np.zeros(0)
    s_m = np.concatenate(([0.0], np.cumsum(steps)))
    for problem in report.problems:
        for place in (problem.place, problem.other):
            if place is None:
                continue
            assert 0 <= place.index < len(array)
            assert -1e-6 <= place.distance_m <= s_m[-1] + 1e-6
            if problem.kind is not ProblemKind.SELF_OVERLAP:  # overlaps lie between points
                assert (place.east_m, place.north_m) == tuple(array[place.index])
                assert place.distance_m == pytest.approx(s_m[place.index], abs=1e-6)
