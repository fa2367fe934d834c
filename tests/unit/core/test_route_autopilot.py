"""The `route` source on the autopilot seam: selection, refusals, epochs taken once, and
the routes near the vehicle for `dbw status`."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core.autopilot import make_source
from appliance.core.route_autopilot import RouteAutopilot
from appliance.core.wish import AutopilotWish, Observation
from appliance.localization.gnss_pose import GnssPose, HeadingSource, SigmaSource
from appliance.localization.local_frame import LocalFrame
from appliance.routes import Route, RouteStore
from drivers.gnss.sentences import FixQuality
from drivers.pc104.messages import MotionPattern

ORIGIN = {"lat_deg": 42.4591, "lon_deg": -71.2674, "alt_m": 100.0}


def route_config(routes: Path, selected: str | None = None) -> VehicleConfig:
    data = load_config("husky").model_dump(mode="json")
    data["engagement"]["autopilot_source"] = "route"
    data["devices"]["gnss"] = {"port": "/dev/null", "receiver_latency_s": 0.05}
    data["positioning"]["origin"] = ORIGIN
    data["route"]["routes_dir"] = str(routes)
    data["route"]["selected"] = selected
    return VehicleConfig.model_validate(data)


def store_with(routes: Path, name: str, points: np.ndarray) -> None:
    frame = LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_m"])
    RouteStore(routes).save(Route.from_enu(name, points, frame))


def straight(length_m: float = 200.0, north_m: float = 0.0) -> np.ndarray:
    n = int(length_m / 0.5) + 1
    return np.column_stack((np.linspace(0.0, length_m, n), np.full(n, north_m)))


def epoch(t_s: float, east_m: float, north_m: float) -> GnssPose:
    return GnssPose(
        measurement_time_s=t_s,
        utc_time_of_day_s=100.0 + t_s,
        east_m=east_m,
        north_m=north_m,
        up_m=0.0,
        quality=FixQuality.RTK_FIXED,
        satellites=15,
        hdop=0.6,
        yaw_rad=0.0,
        heading_source=HeadingSource.TRUE_HEADING,
        course_yaw_rad=None,
        speed_mps=0.0,
        yaw_rate_rad_per_s=0.0,
        sigma_east_m=0.02,
        sigma_north_m=0.02,
        sigma_worst_m=0.02,
        sigma_source=SigmaSource.GST,
    )


def drive_cycles(
    source: RouteAutopilot,
    east_m: float,
    north_m: float,
    engaged: bool = False,
    start_s: float = 0.0,
) -> AutopilotWish:
    wish = None
    for k in range(30):  # 0.6 s at 50 Hz, an epoch every 0.1 s
        t = start_s + 0.02 * k
        seq = round(start_s * 10) + k // 5
        observation = Observation(
            t, 0.0, 0.0, {}, engaged, gnss=epoch(0.1 * seq, east_m, north_m), gnss_seq=seq
        )
        wish = source.update(observation)
    assert wish is not None
    return wish


def test_the_vehicle_file_picks_the_route_source(tmp_path: Path) -> None:
    store_with(tmp_path, "yard", straight())
    source = make_source(route_config(tmp_path, selected="yard"))
    assert isinstance(source, RouteAutopilot)
    assert source.route is not None and source.route.name == "yard"


def test_without_a_route_it_refuses_saying_so(tmp_path: Path) -> None:
    source = RouteAutopilot(route_config(tmp_path))
    wish = drive_cycles(source, 10.0, 0.0)
    assert not wish.ready and wish.reason == "no route selected"


def test_a_missing_or_undrivable_route_is_not_selected_and_the_old_one_stays(
    tmp_path: Path,
) -> None:
    store_with(tmp_path, "yard", straight())
    zigzag = np.array([[0.0, 0.0], [10.0, 0.0], [11.0, 1.5], [11.0, 12.0]])
    store_with(tmp_path, "zigzag", zigzag)
    source = RouteAutopilot(route_config(tmp_path, selected="yard"))
    ok, message = source.select("nowhere")
    assert not ok and "nowhere" in message
    ok, message = source.select("zigzag")
    assert not ok and "radius" in message and "the vehicle needs at least" in message
    assert source.route is not None and source.route.name == "yard"


def test_on_the_route_it_is_ready_and_engaged_it_steers_in_counter_steer(tmp_path: Path) -> None:
    store_with(tmp_path, "yard", straight())
    source = RouteAutopilot(route_config(tmp_path, selected="yard"))
    wish = drive_cycles(source, 20.0, 1.0)
    assert wish.ready, wish.reason
    assert wish.max_speed_mps is None  # not engaged: the speed is the operator's
    source.reset()
    wish = drive_cycles(source, 20.0, 1.0, engaged=True, start_s=1.0)
    assert wish.ready, wish.reason
    assert wish.pattern is MotionPattern.COUNTER_STEER
    assert wish.steer_tyre_rad < 0.0  # 1 m left of the route: back to the right
    assert wish.max_speed_mps is not None
    follow = wish.status["follow"]
    assert isinstance(follow, dict) and abs(follow["cross_track_m"] - 1.0) < 0.05


def test_far_from_the_route_the_refusal_gives_the_distance(tmp_path: Path) -> None:
    store_with(tmp_path, "yard", straight())
    source = RouteAutopilot(route_config(tmp_path, selected="yard"))
    wish = drive_cycles(source, 50.0, 12.4)
    assert not wish.ready and wish.reason == "12.4 m from route, limit 10 m"


def test_each_epoch_is_taken_once_whatever_the_control_rate(tmp_path: Path) -> None:
    store_with(tmp_path, "yard", straight())
    source = RouteAutopilot(route_config(tmp_path, selected="yard"))
    taken: list[float] = []
    assert source.follower is not None
    original = source.follower.update_fix

    def spy(fix: object, now_s: float) -> None:
        taken.append(now_s)
        original(fix, now_s)  # type: ignore[arg-type]

    source.follower.update_fix = spy  # type: ignore[method-assign]
    drive_cycles(source, 20.0, 0.0)
    assert len(taken) == 6  # 30 cycles, 6 epochs


def test_nearby_routes_are_listed_nearest_first_with_the_engagement_verdict(tmp_path: Path) -> None:
    store_with(tmp_path, "near", straight())
    store_with(tmp_path, "far", straight(north_m=30.0))
    store_with(
        tmp_path, "across", np.column_stack((np.full(401, 100.0), np.linspace(-100, 100, 401)))
    )
    source = RouteAutopilot(route_config(tmp_path, selected="near"))
    drive_cycles(source, 60.0, 2.0)
    nearby = source.nearby()
    assert [r["name"] for r in nearby] == ["near", "far", "across"]
    assert nearby[0]["engage_allowed"] and math.isclose(float(nearby[0]["distance_m"]), 2.0)
    assert not nearby[1]["engage_allowed"]  # 28 m away
    assert not nearby[2]["engage_allowed"] and nearby[2]["heading_error_deg"] == 90.0


def test_nearby_parses_a_route_file_once_until_it_changes(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The status asks for the routes nearby on the event loop: unchanged files are not
    read again; a new, replaced or removed route is seen at the next call."""
    store_with(tmp_path, "near", straight())
    store_with(tmp_path, "far", straight(north_m=30.0))
    source = RouteAutopilot(route_config(tmp_path, selected="near"))
    drive_cycles(source, 60.0, 2.0)
    loads: list[str] = []
    real_load = source.store.load
    monkeypatch.setattr(source.store, "load", lambda name: loads.append(name) or real_load(name))
    assert [r["name"] for r in source.nearby()] == ["near", "far"]
    assert sorted(loads) == ["far", "near"]
    for _ in range(5):
        source.nearby()
    assert sorted(loads) == ["far", "near"]  # nothing read again
    RouteStore(tmp_path).save(
        Route.from_enu(
            "far",
            straight(north_m=1.0),
            LocalFrame(ORIGIN["lat_deg"], ORIGIN["lon_deg"], ORIGIN["alt_m"]),
        ),
        overwrite=True,
    )
    store_with(tmp_path, "new", straight(north_m=10.0))
    (tmp_path / "near.geojson").unlink()
    nearby = source.nearby()
    assert [r["name"] for r in nearby] == ["far", "new"]
    assert math.isclose(float(nearby[0]["distance_m"]), 1.0)
    assert sorted(loads) == ["far", "far", "near", "new"]


def test_the_route_window_holds_the_selected_routes_points_near_the_vehicle(
    tmp_path: Path,
) -> None:
    """For the operator page's route view: the points within the radius of the pose the
    source last estimated, by an independent distance check; none before a pose."""
    store_with(tmp_path, "near", straight())
    source = RouteAutopilot(route_config(tmp_path, selected="near"))
    assert source.route_window() == {"points_m": [], "radius_m": 30.0}
    drive_cycles(source, 60.0, 2.0)
    pose = source._last_pose
    assert pose is not None
    window = source.route_window(radius_m=20.0)
    points = np.asarray(window["points_m"])
    assert len(points) > 10 and np.all(np.abs(points[:, 1]) < 1e-6)  # on the route (north 0)
    distances = np.hypot(points[:, 0] - pose.x_m, points[:, 1] - pose.y_m)
    assert distances.max() <= 20.0 + 1e-9
    # The route's ends nearest the window: nothing within 20 m was left out.
    assert points[:, 0].min() <= pose.x_m - 19.0 and points[:, 0].max() >= pose.x_m + 19.0
    assert len(source.route_window(radius_m=1000.0)["points_m"]) <= 400
