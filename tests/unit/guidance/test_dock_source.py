"""The `dock` autopilot source through the core's seam: refusals with reasons, a plan only
while engaged, and a status for `dbw status`."""

from __future__ import annotations

import math

import numpy as np

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core.autopilot import AutopilotWish, DockAutopilot, Observation, make_source
from appliance.sim.scanner_model import render_scan
from appliance.sim.site import Site
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan, mount_pose
from drivers.lms111.scan import scan_from_ranges
from drivers.pc104.messages import MotionPattern, PoseState

SITE = load_site("launcher")


def _config() -> VehicleConfig:
    config = load_config("flatbed")
    return config.model_copy(
        update={"engagement": config.engagement.model_copy(update={"autopilot_source": "dock"})}
    )


def _centre(gap_m: float, y_m: float = 0.0, heading_deg: float = 0.0) -> Pose2D:
    front = Pose2D(-gap_m, y_m, math.radians(heading_deg))
    return front.compose(Pose2D(-6.0, 0.0, 0.0))


def _scans(
    config: VehicleConfig, centre: Pose2D, t_s: float, site: Site = SITE
) -> dict[str, MountedScan]:
    mounts = {
        "left": mount_pose(config.geometry.scanner_left_mount),
        "right": mount_pose(config.geometry.scanner_right_mount),
    }
    scans = {}
    for name, mount in mounts.items():
        # the data sheet's noise and footprint, no drawn systematic error
        rng = np.random.default_rng(int(t_s * 1000) + len(scans))
        ranges, _ = render_scan(site, t_s, centre, mount, rng=rng)
        scan = scan_from_ranges(ranges, angular_step_deg=0.25)
        scans[name] = MountedScan(scan, name, mount, t_s, 0)
    return scans


def _run(
    source: DockAutopilot, config: VehicleConfig, centre: Pose2D, engaged: bool, cycles: int = 10
) -> AutopilotWish:
    wish = AutopilotWish(ready=False)
    for k in range(cycles):
        t_s = k * 0.04
        wish = source.update(Observation(t_s, 0.0, 0.0, _scans(config, centre, t_s), engaged))
    return wish


def test_the_dock_source_is_made_from_the_vehicle_file() -> None:
    source = make_source(_config())
    assert isinstance(source, DockAutopilot) and source.name == "dock"


def test_in_the_zone_it_is_ready_and_says_where_the_vehicle_is() -> None:
    config = _config()
    source = make_source(config)
    assert isinstance(source, DockAutopilot)
    wish = _run(source, config, _centre(9.0, 0.3, 2.0), engaged=False)
    assert wish.ready, wish.reason
    assert wish.max_speed_mps == 0.0  # not engaged: no motion asked for
    pose = wish.status["localization"]["pose"]  # type: ignore[index]
    assert abs(pose["y_m"] - _centre(9.0, 0.3, 2.0).y_m) < 0.02
    docking = wish.status["docking"]
    assert abs(docking["gap_m"] - 9.0) < 0.02  # type: ignore[index]


def test_engaged_it_plans_the_papers_first_step() -> None:
    config = _config()
    source = make_source(config)
    assert isinstance(source, DockAutopilot)
    wish = _run(source, config, _centre(9.0, 0.3, 2.0), engaged=True)
    assert wish.ready
    assert wish.pattern is MotionPattern.REAR_STEER
    assert wish.rear_steer_rad > 0.0 and wish.max_speed_mps > 0.0 and not wish.reverse
    assert wish.status["docking"]["phase"] == "heading"  # type: ignore[index]
    # The pose and the plan, for a PC104 that closes the loop itself: the geometric
    # centre's estimate, and where the centre is when the front end is at the board.
    truth = _centre(9.0, 0.3, 2.0)
    assert wish.pose is not None and wish.pose_state is PoseState.OK
    assert abs(wish.pose.x_m - truth.x_m) < 0.02 and abs(wish.pose.y_m - truth.y_m) < 0.02
    docked = _centre(0.0)
    assert wish.expected_pose == Pose2D(docked.x_m, 0.0, 0.0)
    idle = _run(source, config, truth, engaged=False)
    assert idle.pose is not None and idle.expected_pose is None  # no plan unless engaged


def test_outside_the_zone_it_refuses_with_the_reason() -> None:
    config = _config()
    source = make_source(config)
    assert isinstance(source, DockAutopilot)
    wish = _run(source, config, _centre(6.0, 1.9, 0.0), engaged=False)
    assert not wish.ready
    assert "outside the automatic zone" in wish.reason and "off the axis" in wish.reason


def test_without_a_launcher_it_refuses_with_the_reason() -> None:
    config = _config()
    source = make_source(config)
    assert isinstance(source, DockAutopilot)
    empty = Site((), ())
    wish = AutopilotWish(ready=True)
    for k in range(5):
        scans = _scans(config, _centre(9.0), k * 0.04, site=empty)
        wish = source.update(Observation(k * 0.04, 0.0, 0.0, scans, False))
    assert not wish.ready
    assert wish.reason.startswith("launcher not in view")


def test_scans_that_stop_coming_refuse_within_the_staleness_limit() -> None:
    config = _config()
    source = make_source(config)
    assert isinstance(source, DockAutopilot)
    scans = _scans(config, _centre(8.0), 0.0)
    for k in range(10):
        wish = source.update(
            Observation(k * 0.04, 0.0, 0.0, _scans(config, _centre(8.0), k * 0.04), True)
        )
    assert wish.ready
    # the same scans, seen again and again: nothing new arrives
    late = source.update(Observation(1.5, 0.0, 0.0, scans, True))
    assert not late.ready
    assert "localization" in late.reason
