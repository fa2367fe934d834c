"""RouteFollower: the refusals an operator reads, and the chain's wiring on exact input."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.guidance.path_geometry import PathProjection
from appliance.guidance.pure_pursuit import PurePursuitTracker, PursuitParams
from appliance.guidance.route_follow import RouteFollower, RouteFollowParams
from appliance.guidance.route_planner import PlannerOutput, RoutePlanner
from appliance.localization.gnss_pose import GnssNoFix, GnssPose, HeadingSource, SigmaSource
from drivers.geometry import Pose2D
from drivers.gnss.sentences import FixQuality

HUSKY = load_config("husky")
ROUTE = np.column_stack((np.linspace(0.0, 200.0, 401), np.zeros(401)))


def follower() -> RouteFollower:
    return RouteFollower(RouteFollowParams(PursuitParams.from_config(HUSKY)), ROUTE)


def fix(t_s: float, east_m: float, north_m: float, yaw_rad: float, **kw: object) -> GnssPose:
    values: dict[str, object] = {
        "measurement_time_s": t_s,
        "utc_time_of_day_s": 1000.0 + t_s,
        "east_m": east_m,
        "north_m": north_m,
        "up_m": 0.0,
        "quality": FixQuality.RTK_FIXED,
        "satellites": 14,
        "hdop": 0.7,
        "yaw_rad": yaw_rad,
        "heading_source": HeadingSource.TRUE_HEADING,
        "course_yaw_rad": yaw_rad,
        "speed_mps": 0.0,
        "yaw_rate_rad_per_s": 0.0,
        "sigma_east_m": 0.02,
        "sigma_north_m": 0.02,
        "sigma_worst_m": 0.02,
        "sigma_source": SigmaSource.GST,
    }
    return GnssPose(**(values | kw))  # type: ignore[arg-type]


def standing(f: RouteFollower, east_m: float, north_m: float, yaw_rad: float, **kw: object) -> None:
    """A few fixes of a vehicle standing still, each followed by a cycle."""
    for k in range(5):
        t = 0.1 * k
        f.update_fix(fix(t, east_m, north_m, yaw_rad, **kw), t)
        f.update(t + 0.01, 0.0, 2.0, engaged=False)


def test_nothing_is_ready_without_a_fix() -> None:
    f = follower()
    wish = f.update(0.0, 0.0, 2.0, engaged=False)
    assert not wish.ready and wish.reason == "no fix"


def test_the_receiver_saying_no_fix_is_stated() -> None:
    f = follower()
    f.update_fix(GnssNoFix(0.0, "GGA quality 0"), 0.0)
    assert f.update(0.01, 0.0, 2.0, engaged=False).reason == "no fix"


def test_on_the_route_and_aligned_engagement_is_allowed() -> None:
    f = follower()
    standing(f, 20.0, 0.5, 0.05)
    wish = f.update(0.5, 0.0, 2.0, engaged=False)
    assert wish.ready, wish.reason
    # the cross-track is the anchor's, 3 m ahead of the centre (the antenna, here)
    anchor_left_m = 0.5 + math.sin(0.05) * HUSKY.geometry.anchor_point_forward_m
    assert abs(wish.status["cross_track_m"] - anchor_left_m) < 0.01


def test_too_far_from_the_route_is_refused_with_the_distance() -> None:
    f = follower()
    standing(f, 50.0, 12.4, 0.0)
    wish = f.update(0.5, 0.0, 2.0, engaged=False)
    assert not wish.ready
    assert wish.reason == "12.4 m from route, limit 10 m"


def test_facing_away_from_the_route_is_refused_with_the_angle() -> None:
    f = follower()
    standing(f, 50.0, 1.0, math.radians(60.0))
    wish = f.update(0.5, 0.0, 2.0, engaged=False)
    assert not wish.ready
    assert wish.reason == "heading 60° from the route"
    # past 90° the route is driven the other way (Fig. 5): 104° is 76° off that way
    g = follower()
    standing(g, 50.0, 1.0, math.radians(104.0))
    assert g.update(0.5, 0.0, 2.0, engaged=False).reason == "heading 76° from the route"


def test_a_degraded_fix_is_refused_with_its_sigma() -> None:
    f = follower()
    standing(f, 50.0, 0.0, 0.0, sigma_east_m=0.8, sigma_north_m=0.8, sigma_worst_m=0.8)
    wish = f.update(0.5, 0.0, 2.0, engaged=False)
    assert not wish.ready
    assert wish.reason.startswith("fix degraded: σ 0.80 m"), wish.reason


def test_a_lost_fix_while_engaged_is_refused_once_it_is_too_old() -> None:
    f = follower()
    standing(f, 20.0, 0.0, 0.0)
    f.reset(0.0)
    assert f.update(0.5, 0.0, 2.0, engaged=True).ready
    assert f.update(0.4 + 0.5 - 1e-3, 0.0, 2.0, engaged=True).ready  # last fix at 0.4 s
    wish = f.update(0.4 + 0.5 + 0.02, 0.0, 2.0, engaged=True)
    assert not wish.ready and wish.reason.startswith("fix lost"), wish.reason


def test_engaged_on_the_route_it_steers_back_towards_it() -> None:
    f = follower()
    standing(f, 20.0, 1.0, 0.0)  # 1 m left of the route, parallel to it
    f.reset(0.0)
    assert f.update(0.5, 0.0, 2.0, engaged=True).ready
    wish = f.update(0.52, 0.0, 2.0, engaged=True)  # one period on: the rate limit allows a step
    assert wish.ready
    assert wish.front_steer_rad < 0.0  # to the right
    assert math.isclose(
        wish.rear_steer_rad, HUSKY.geometry.counter_steer_ratio_k * wish.front_steer_rad
    )
    assert wish.status["direction"] == "forward"


# -- what is made once per route, against what it replaced ---------------------------------

WAVE = np.column_stack(
    (np.arange(0.0, 150.0, 0.5), 6.0 * np.sin(np.arange(0.0, 150.0, 0.5) / 12.0))
)


@settings(max_examples=150, deadline=None)
@given(
    s_m=st.floats(0.0, 149.0),
    left_m=st.floats(-1.5, 1.5),
    heading_error_rad=st.floats(-0.3, 0.3),
    reverse=st.booleans(),
    speed_mps=st.floats(0.0, 5.0),
    previous_rad=st.floats(-0.3, 0.3),
)
def test_the_tracker_on_the_travel_path_is_the_tracker_on_the_local_window(
    s_m: float,
    left_m: float,
    heading_error_rad: float,
    reverse: bool,
    speed_mps: float,
    previous_rad: float,
) -> None:
    """The whole route in travel order (made once) and the planner's projection on it
    give what the local window cut around the projection each cycle gave."""
    planner = RoutePlanner(WAVE)
    i = min(int(s_m / 0.5), len(WAVE) - 2)
    (x0, y0), (x1, y1) = WAVE[i], WAVE[i + 1]
    yaw = math.atan2(y1 - y0, x1 - x0)
    anchor = Pose2D(
        x0 - left_m * math.sin(yaw),
        y0 + left_m * math.cos(yaw),
        yaw + heading_error_rad + (math.pi if reverse else 0.0),
    )
    planned = planner.update((anchor.x_m, anchor.y_m), anchor.yaw_rad, 0.0)
    assert isinstance(planned, PlannerOutput)
    params = PursuitParams.from_config(HUSKY)
    outputs = []
    for path, projection in (
        (planner.paths.path(planned.direction), planned.travel_projection),
        (
            planned.local_path_m,
            PathProjection(planned.local_segment_index, planned.local_fraction),
        ),
    ):
        tracker = PurePursuitTracker(params)
        tracker.reset(previous_rad)
        outputs.append(tracker.update(anchor, speed_mps, path, projection, 0.02))
    fast, plain = outputs
    for name in (
        "front_steer_rad",
        "unclamped_front_steer_rad",
        "goal_x_m",
        "goal_y_m",
        "eta_rad",
        "cross_track_m",
        "path_curvature_per_m",
    ):
        assert getattr(fast, name) == pytest.approx(getattr(plain, name), abs=1e-9), name
    assert fast.goal_beyond_end == plain.goal_beyond_end


def _wanted_speed(f: RouteFollower, t_s: float) -> float:
    """The speed the profile asks for (before its rise limit) standing at (10, 0)."""
    f.update_fix(fix(t_s, 10.0, 0.0, 0.0), t_s)
    wish = f.update(t_s + 0.01, 0.0, 4.47, engaged=True)
    assert wish.ready, wish.reason
    return f.speed.unlimited_mps


def test_a_new_route_or_new_profile_parameters_are_used_at_once() -> None:
    """What is made once per route and parameters is made again when either changes."""
    turn = np.arange(0.0, 1.5, 0.04)
    curve = np.vstack((
        np.column_stack((np.arange(0.0, 15.0, 0.5), np.zeros(30))),
        np.column_stack((15.0 + 12.0 * np.sin(turn), 12.0 * (1.0 - np.cos(turn)))),
    ))  # fmt: skip
    f = follower()
    standing(f, 10.0, 0.0, 0.0)
    f.reset(0.0)
    assert _wanted_speed(f, 0.5) == pytest.approx(4.47)  # the straight: the set speed
    f.planner.set_route(curve)
    on_curve = _wanted_speed(f, 0.6)
    fresh = RouteFollower(RouteFollowParams(PursuitParams.from_config(HUSKY)), curve)
    standing(fresh, 10.0, 0.0, 0.0)
    fresh.reset(0.0)
    assert on_curve < 4.0  # the 12 m arc 5 m ahead
    assert on_curve == pytest.approx(_wanted_speed(fresh, 0.6), abs=1e-9)
    gentler = replace(f.speed.params, lateral_accel_mps2=0.5)
    f.speed.params = gentler
    fresh_gentle = RouteFollower(
        RouteFollowParams(PursuitParams.from_config(HUSKY), profile=gentler), curve
    )
    standing(fresh_gentle, 10.0, 0.0, 0.0)
    fresh_gentle.reset(0.0)
    slower = _wanted_speed(f, 0.7)
    assert slower < on_curve
    assert slower == pytest.approx(_wanted_speed(fresh_gentle, 0.7), abs=1e-9)
