"""The target speed along a route: curvature, curves ahead, the route's end, the caps.

The laws are checked against the physics written out here (a circle's curvature, the
distance a constant deceleration needs), the braking curves by driving a point mass
along them, and the whole by the closed loop: profile, pedal controller and the
simulated Husky on a route with a 15 m arc and an end.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.guidance.pedal_speed import PedalSpeedController, PedalSpeedParams
from appliance.guidance.speed_profile import (
    CurveSpeedTable,
    SpeedLimiter,
    SpeedProfileParams,
    SpeedTarget,
    braking_distance_m,
    curvature_preview,
    curve_speed_limit_mps,
    path_curvature,
    route_end_speed_limit_mps,
    target_speed_mps,
    target_with_reason,
)
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.pc104.messages import MotionPattern

PARAMS = SpeedProfileParams()
PLAIN = replace(PARAMS, response_time_s=0.0)  # the textbook braking curve
TEN_MPH = 4.47
NO_CURVES = np.zeros((0, 2))


# -- curvature -----------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    radius_m=st.floats(2.0, 500.0),
    start_rad=st.floats(-math.pi, math.pi),
    steps_rad=st.lists(st.floats(0.01, 0.4), min_size=2, max_size=40),
    left=st.booleans(),
    centre=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)),
    repeats=st.lists(st.integers(0, 39), max_size=5),
)
def test_curvature_on_a_circle_is_one_over_the_radius(
    radius_m: float,
    start_rad: float,
    steps_rad: list[float],
    left: bool,
    centre: tuple[float, float],
    repeats: list[int],
) -> None:
    """Points on a circle, unevenly spaced, either way round, some repeated: 1/R, signed
    positive turning left (counter-clockwise)."""
    angles = start_rad + np.concatenate(([0.0], np.cumsum(steps_rad)))
    angles = angles[angles - start_rad < 1.9 * math.pi]  # less than one full turn
    if not left:
        angles = angles[::-1]
    points = np.column_stack(
        (centre[0] + radius_m * np.cos(angles), centre[1] + radius_m * np.sin(angles))
    )
    for index in sorted({r % len(points) for r in repeats}, reverse=True):
        points = np.insert(points, index, points[index], axis=0)  # a repeated point
    kappa = path_curvature(points)
    expected = (1.0 if left else -1.0) / radius_m
    assert kappa.shape == (len(points),)
    assert np.allclose(kappa, expected, rtol=1e-6, atol=1e-9)


def test_curvature_of_a_straight_line_and_of_too_few_points_is_zero() -> None:
    line = np.column_stack((np.linspace(0.0, 30.0, 16), np.linspace(5.0, -10.0, 16)))
    assert np.allclose(path_curvature(line), 0.0, atol=1e-12)
    assert np.array_equal(path_curvature([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0]]), np.zeros(3))
    assert path_curvature(np.zeros((0, 2))).shape == (0,)


def test_a_path_reversing_on_itself_gets_the_tightest_circle() -> None:
    # Out 2 m and straight back: the circle through the three points has the turn as its
    # diameter, so |κ| = 2 / 2 m.
    kappa = path_curvature([[0.0, 0.0], [2.0, 0.0], [0.0, 0.0]])
    assert np.all(np.isfinite(kappa))
    assert abs(kappa[1]) == pytest.approx(1.0)


@pytest.mark.parametrize(
    "points",
    [
        np.zeros((4, 3)),
        np.zeros(6),
        [[0.0, 0.0], [1.0, math.nan], [2.0, 0.0]],
        [[0, 0], [1, math.inf]],
    ],
)
def test_malformed_points_are_refused(points: object) -> None:
    with pytest.raises(ValueError, match="points_m"):
        path_curvature(points)  # type: ignore[arg-type]


def test_curvature_preview_measures_from_the_vehicle() -> None:
    points = np.column_stack((np.arange(0.0, 100.0, 1.0), np.zeros(100)))
    kappa = np.arange(100.0) / 1000.0  # a label per point, to see which ones came back
    rows = curvature_preview(points, along_m=10.3, preview_m=5.0, curvature_1pm=kappa)
    # The point at 10 m (the segment the vehicle is on) at distance 0, then 11 .. 15 m.
    assert np.allclose(rows[:, 0], [0.0, 0.7, 1.7, 2.7, 3.7, 4.7])
    assert np.allclose(rows[:, 1], kappa[10:16])
    with pytest.raises(ValueError, match="one value per point"):
        curvature_preview(points, 0.0, 5.0, curvature_1pm=kappa[:-1])


# -- the target law ------------------------------------------------------------------------


def _arc_ahead(distance_m: float, radius_m: float = 15.0) -> np.ndarray:
    """Straight road up to ``distance_m``, then an arc, sampled every half metre."""
    d = np.arange(0.0, 60.0, 0.5)
    return np.column_stack((d, np.where(d >= distance_m, -1.0 / radius_m, 0.0)))


@pytest.mark.parametrize("distance_m", [0.0, 1.0, 3.0, 4.0, 5.0, 10.0, 30.0])
def test_a_15_m_arc_ahead_follows_the_textbook_braking_curve(distance_m: float) -> None:
    a_lat, a_dec = PLAIN.lateral_accel_mps2, PLAIN.comfort_decel_mps2
    arc_mps = math.sqrt(a_lat * 15.0)
    assert arc_mps < TEN_MPH  # the arc does limit the Husky at 10 mph
    expected = min(TEN_MPH, math.sqrt(arc_mps**2 + 2.0 * a_dec * distance_m))
    assert target_speed_mps(TEN_MPH, None, _arc_ahead(distance_m), None, PLAIN) == pytest.approx(
        expected
    )


def test_on_the_arc_the_target_is_the_lateral_acceleration_speed() -> None:
    on_arc = _arc_ahead(0.0)
    speed, why = target_with_reason(TEN_MPH, None, on_arc, None, PARAMS)
    assert speed == pytest.approx(math.sqrt(PARAMS.lateral_accel_mps2 * 15.0))
    assert why is SpeedLimiter.CURVE
    # A turn either way is the same turn; a gentle curve does not limit at all.
    mirrored = on_arc * [1.0, -1.0]
    assert target_speed_mps(TEN_MPH, None, mirrored, None, PARAMS) == speed
    gentle = np.column_stack((on_arc[:, 0], np.full(len(on_arc), 1.0 / 200.0)))
    assert target_speed_mps(TEN_MPH, None, gentle, None, PARAMS) == TEN_MPH


def test_slowing_for_the_arc_starts_in_time() -> None:
    """Drive a point mass at the target speed toward the arc; when the target falls, let it
    react for the response time and then brake at the comfortable rate (the assumption the
    curve is built on): it arrives at the arc at the arc's speed, never faster, and it is
    not slowed before it needs to be."""
    arc_at_m, dt_s = 60.0, 0.001
    arc_mps = math.sqrt(PARAMS.lateral_accel_mps2 * 15.0)
    s_m, v_mps, braking_from_s, t_s, first_fall_at_m = 0.0, TEN_MPH, math.inf, 0.0, math.nan
    rows_far = np.array([[0.0, 0.0], [arc_at_m, 1.0 / 15.0]])
    while s_m < arc_at_m:
        rows = rows_far - [s_m, 0.0]
        target = target_speed_mps(TEN_MPH, None, rows[rows[:, 0] >= 0.0], None, PARAMS)
        if target < v_mps - 1e-9 and braking_from_s == math.inf:
            braking_from_s = t_s + PARAMS.response_time_s
            first_fall_at_m = s_m
        if t_s >= braking_from_s:
            v_mps = max(v_mps - PARAMS.comfort_decel_mps2 * dt_s, arc_mps)
        s_m += v_mps * dt_s
        t_s += dt_s
    assert v_mps <= arc_mps + 1e-3
    # It started to slow no earlier than response + braking from 10 mph requires.
    needed_m = TEN_MPH * PARAMS.response_time_s + (TEN_MPH**2 - arc_mps**2) / (
        2 * PARAMS.comfort_decel_mps2
    )
    assert arc_at_m - first_fall_at_m == pytest.approx(needed_m, abs=0.01)


def test_curves_beyond_the_preview_are_not_seen_and_the_preview_is_long_enough() -> None:
    far = np.array([[PARAMS.preview_m + 1.0, 1.0 / 5.0]])
    assert target_speed_mps(TEN_MPH, None, far, None, PARAMS) == TEN_MPH
    assert braking_distance_m(TEN_MPH, PARAMS) < PARAMS.preview_m


@given(st.floats(-5.0, 200.0))
def test_the_route_end_follows_the_braking_curve_to_zero(remaining_m: float) -> None:
    to_stop_m = remaining_m - PLAIN.stop_margin_m
    expected = math.sqrt(2.0 * PLAIN.comfort_decel_mps2 * to_stop_m) if to_stop_m > 0 else 0.0
    assert route_end_speed_limit_mps(remaining_m, PLAIN) == pytest.approx(expected)
    # With the response time it is lower, zero at the margin, and a point mass holding it
    # for t_r then braking at a_dec stops exactly there: v·t_r + v²/(2·a_dec) = d.
    v = route_end_speed_limit_mps(remaining_m, PARAMS)
    assert v <= expected + 1e-12
    if to_stop_m > 0:
        reach = v * PARAMS.response_time_s + v**2 / (2.0 * PARAMS.comfort_decel_mps2)
        assert reach == pytest.approx(to_stop_m)
    else:
        assert v == 0.0


def test_at_the_end_of_the_route_the_target_is_zero() -> None:
    for remaining_m in (0.0, PARAMS.stop_margin_m, -3.0):
        speed, why = target_with_reason(TEN_MPH, None, NO_CURVES, remaining_m, PARAMS)
        assert speed == 0.0
        assert why is SpeedLimiter.ROUTE_END
    assert target_speed_mps(TEN_MPH, None, NO_CURVES, 1000.0, PARAMS) == TEN_MPH


def test_the_speed_limit_and_the_set_speed_cap_and_say_so() -> None:
    assert target_with_reason(TEN_MPH, 3.0, NO_CURVES, None, PARAMS) == (
        3.0,
        SpeedLimiter.SPEED_LIMIT,
    )
    assert target_with_reason(2.0, 3.0, NO_CURVES, None, PARAMS) == (2.0, SpeedLimiter.SET_SPEED)
    assert target_speed_mps(TEN_MPH, None, NO_CURVES, None, PARAMS) == TEN_MPH
    assert target_speed_mps(-1.0, None, NO_CURVES, None, PARAMS) == 0.0  # never reverse


@pytest.mark.parametrize(
    ("set_speed", "limit", "rows", "remaining"),
    [
        (math.nan, None, NO_CURVES, None),
        (math.inf, None, NO_CURVES, None),
        (2.0, math.nan, NO_CURVES, None),
        (2.0, None, np.zeros((3, 3)), None),
        (2.0, None, np.array([[1.0, math.nan]]), None),
        (2.0, None, NO_CURVES, math.nan),
    ],
)
def test_bad_input_is_refused(
    set_speed: float, limit: float | None, rows: np.ndarray, remaining: float | None
) -> None:
    with pytest.raises(ValueError, match=r"\w"):
        target_speed_mps(set_speed, limit, rows, remaining, PARAMS)


@pytest.mark.parametrize(
    "change",
    [{"lateral_accel_mps2": 0.0}, {"comfort_decel_mps2": -1.0}, {"preview_m": math.inf}],
)
def test_bad_parameters_are_refused(change: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="must be finite"):
        replace(PARAMS, **change)


@settings(max_examples=300, deadline=None)
@given(
    steps=st.lists(st.tuples(st.floats(0.05, 8.0), st.floats(-0.6, 0.6)), min_size=1, max_size=120),
    along_m=st.floats(-1.0, 400.0),
    lateral_accel_mps2=st.floats(0.2, 3.0),
    comfort_decel_mps2=st.floats(0.2, 2.0),
    preview_m=st.floats(0.5, 60.0),
    response_time_s=st.floats(0.0, 3.0),
)
def test_the_curve_table_is_the_curve_rule_on_the_preview(
    steps: list[tuple[float, float]],
    along_m: float,
    lateral_accel_mps2: float,
    comfort_decel_mps2: float,
    preview_m: float,
    response_time_s: float,
) -> None:
    """The table (curve speeds made once per path) against the rule on the rows
    curvature_preview cuts for the same place: random curvy paths, straight pieces,
    every place along them and past their ends."""
    params = replace(
        PARAMS,
        lateral_accel_mps2=lateral_accel_mps2,
        comfort_decel_mps2=comfort_decel_mps2,
        preview_m=preview_m,
        response_time_s=response_time_s,
    )
    heading = np.cumsum([turn if turn > -0.3 else 0.0 for _, turn in steps])  # some straight
    lengths = np.array([length for length, _ in steps])
    points = np.vstack(([0.0, 0.0], np.cumsum(
        np.column_stack((lengths * np.cos(heading), lengths * np.sin(heading))), axis=0
    )))  # fmt: skip
    arc = np.concatenate(([0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))))
    kappa = path_curvature(points)
    table = CurveSpeedTable(arc, kappa, params)
    plain = curve_speed_limit_mps(curvature_preview(points, along_m, preview_m, kappa), params)
    fast = table.limit_mps(along_m)
    if math.isinf(plain):
        assert math.isinf(fast)
    else:
        assert fast == pytest.approx(plain, rel=1e-12, abs=1e-12)


def test_the_curve_table_refuses_what_is_no_path() -> None:
    for arc, kappa in (([0.0, 1.0], [0.0]), ([], []), ([0.0, math.nan], [0.0, 0.0])):
        with pytest.raises(ValueError, match=r"\w"):
            CurveSpeedTable(arc, kappa, PARAMS)
    with pytest.raises(ValueError, match="decrease"):
        CurveSpeedTable([0.0, 2.0, 1.0], [0.0, 0.1, 0.0], PARAMS)
    with pytest.raises(ValueError, match="finite"):
        CurveSpeedTable([0.0, 1.0], [0.1, 0.1], PARAMS).limit_mps(math.nan)


# -- the target over time ------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(st.floats(-2.0, 10.0), st.floats(-0.05, 0.3)),  # set speed, time step
        min_size=1,
        max_size=80,
    )
)
def test_the_target_rises_and_falls_no_faster_than_its_limits(
    steps: list[tuple[float, float]],
) -> None:
    target = SpeedTarget(PARAMS)
    now_s, last_s, before = 0.0, None, 0.0
    for set_speed, dt_s in steps:
        now_s += dt_s
        value = target.update(set_speed, None, NO_CURVES, None, now_s)
        elapsed = 0.0 if last_s is None else min(max(now_s - last_s, 0.0), PARAMS.max_step_dt_s)
        last_s = now_s
        assert value - before <= PARAMS.target_rise_mps2 * elapsed + 1e-9
        assert before - value <= PARAMS.target_fall_mps2 * elapsed + 1e-9
        # It moves toward what the law asks, never past it.
        wanted = max(set_speed, 0.0)
        assert min(before, wanted) - 1e-9 <= value <= max(before, wanted) + 1e-9
        before = value


def test_the_target_reaches_the_set_speed_and_starts_from_the_vehicle() -> None:
    target = SpeedTarget(PARAMS)
    target.reset(speed_mps=3.0)
    assert target.update(TEN_MPH, None, NO_CURVES, None, 0.0) == 3.0  # no jump at engagement
    value = 0.0
    for i in range(1, 400):
        value = target.update(TEN_MPH, None, NO_CURVES, None, i * 0.02)
    assert value == pytest.approx(TEN_MPH)
    assert target.limited_by is SpeedLimiter.SET_SPEED


# -- closed loop: profile, pedals and the simulated Husky ----------------------------------


def _route_with_arc_and_end(radius_m: float = 15.0) -> tuple[np.ndarray, float]:
    """80 m straight, a quarter circle of ``radius_m`` to the left, 40 m straight."""
    ds = 0.5
    straight = np.column_stack((np.arange(0.0, 80.0, ds), np.zeros(160)))
    angles = np.arange(0.0, math.pi / 2, ds / radius_m)
    arc = np.column_stack((80.0 + radius_m * np.sin(angles), radius_m * (1 - np.cos(angles))))
    last = np.column_stack((np.full(80, 80.0 + radius_m), radius_m + np.arange(0.0, 40.0, ds)))
    return np.vstack((straight, arc, last)), 80.0


def test_closed_loop_the_husky_slows_for_the_arc_and_stops_before_the_end() -> None:
    config = load_config("husky")
    plant = VehicleParams.from_config(config)
    points, arc_start_m = _route_with_arc_and_end()
    arc_end_m = arc_start_m + 15.0 * math.pi / 2
    kappa = path_curvature(points)
    length_m = float(np.sum(np.linalg.norm(np.diff(points, axis=0), axis=1)))
    target = SpeedTarget(PARAMS)
    pedals = PedalSpeedController(PedalSpeedParams.from_limits(config.limits))
    vehicle, dt_s = VehicleState(), 0.02
    on_arc: list[float] = []
    for i in range(round(60.0 / dt_s)):
        now_s = i * dt_s
        along_m = vehicle.odometer_m  # a straight-line drive: the odometer is the progress
        ahead = curvature_preview(points, along_m, PARAMS.preview_m, kappa)
        wanted = target.update(TEN_MPH, None, ahead, length_m - along_m, now_s)
        cmd = pedals.update(wanted, vehicle.speed_mps, None, now_s)
        wheels = VehicleCommand(
            pattern=MotionPattern.STRAIGHT, throttle_pct=cmd.throttle_pct, brake_pct=cmd.brake_pct
        )
        vehicle = step(vehicle, wheels, dt_s, plant)
        if arc_start_m <= vehicle.odometer_m <= arc_end_m:
            on_arc.append(vehicle.speed_mps)
    arc_mps = math.sqrt(PARAMS.lateral_accel_mps2 * 15.0)
    assert max(on_arc) <= arc_mps * 1.01  # measured: 3.81 m/s in, 3.877 at most
    assert vehicle.speed_mps == 0.0
    stopped_short_m = length_m - vehicle.odometer_m
    assert 0.0 < stopped_short_m <= PARAMS.stop_margin_m + 0.5  # measured: 0.53 m
