"""Qian et al.'s launcher seen by the flat-bed's two LMS111 (simulated, with the data
sheet's noise and beam footprint), from about 10 m and 2 m in front of it.

The fixed seeds keep the tests deterministic. The bounds are a few σ of what one scanner
can do: at 10 m the board's α is known to ~0.1° (σ) and a cylinder's centre to ~5-7 mm,
at 2 m to ~0.03° and ~3 mm; the centre keeps a bias of 3-4 mm away from the scanner at
10 m (the footprint averages the arc's receding sides), inside its σ.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.perception.features import (
    DiscRoi,
    FeatureParams,
    LineRoi,
    extract_features,
    extract_mounted_features,
)
from appliance.perception.types import CircleFeature, LineFeature, ScanFeatures
from appliance.sim import Circle, Site, beam_angles_rad, load_site, render_scan
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan
from drivers.lms111.scan import scan_from_ranges

from .scenes import (
    MOUNTS,
    SENSOR_ANGLES,
    angle_difference,
    hessian_in_frame,
    render,
    to_frame,
    vehicle_before_board,
)

CYLINDERS = ((-0.5, 2.5), (-0.5, -2.5))  # launcher frame (launcher.toml)
POST_THIN = (-6.0, -4.5)  # radius 0.1 m: not the landmark
POST_LIKE = (-13.0, 4.0)  # radius 0.15 m: indistinguishable from the landmark
# (distance to the board, lateral offset, yaw): straight on and a little off.
APPROACHES = [(10.0, 0.0, 0.0), (10.0, 0.4, 3.0), (2.0, 0.0, 0.0), (2.0, 0.2, -2.0)]


@pytest.fixture(scope="module")
def launcher() -> Site:
    return load_site("launcher")


def _features(
    site: Site, vehicle: Pose2D, sensor: str, seed: int, t_s: float = 0.0
) -> ScanFeatures:
    mount = MOUNTS[sensor]
    return extract_features(render(site, vehicle, mount, seed, t_s), SENSOR_ANGLES, mount)


def _board(vehicle: Pose2D) -> tuple[float, float]:
    """The front board (x = 0 in the launcher frame) in the vehicle frame."""
    return hessian_in_frame(0.0, math.pi, vehicle)


def _board_lines(features: ScanFeatures, vehicle: Pose2D) -> list[LineFeature]:
    r, alpha = _board(vehicle)
    return [
        line
        for line in features.lines
        if abs(angle_difference(line.alpha_rad, alpha)) < math.radians(10.0)
        and abs(line.r_m - r) < 0.3
    ]


def _near(
    circles: tuple[CircleFeature, ...], vehicle: Pose2D, x_m: float, y_m: float
) -> list[CircleFeature]:
    tx, ty = to_frame(vehicle, x_m, y_m)
    return [c for c in circles if math.hypot(c.cx_m - tx, c.cy_m - ty) < 0.5]


@pytest.mark.parametrize(("distance_m", "y_m", "yaw_deg"), APPROACHES)
@pytest.mark.parametrize("sensor", ["left", "right"])
def test_the_front_board_is_one_line_in_the_right_place(
    launcher: Site, distance_m: float, y_m: float, yaw_deg: float, sensor: str
) -> None:
    vehicle = vehicle_before_board(distance_m, y_m, yaw_deg)
    r, alpha = _board(vehicle)
    near = distance_m < 5.0
    for seed in range(3):
        (board,) = _board_lines(_features(launcher, vehicle, sensor, seed), vehicle)
        assert board.r_m == pytest.approx(r, abs=0.003 if near else 0.005)
        assert abs(math.degrees(angle_difference(board.alpha_rad, alpha))) < (
            0.15 if near else 0.35
        )
        error = np.array([board.r_m - r, angle_difference(board.alpha_rad, alpha)])
        assert float(error @ np.linalg.solve(board.covariance, error)) < 16.0  # 4σ in 2-D
        assert board.length_m == pytest.approx(3.0, abs=0.25)  # clipped to the data
        assert not board.start_occluded and not board.end_occluded  # corners: true ends


@pytest.mark.parametrize(("distance_m", "y_m", "yaw_deg"), APPROACHES)
@pytest.mark.parametrize("sensor", ["left", "right"])
def test_both_cylinders_are_found_where_they_are(
    launcher: Site, distance_m: float, y_m: float, yaw_deg: float, sensor: str
) -> None:
    vehicle = vehicle_before_board(distance_m, y_m, yaw_deg)
    bound_m = 0.015 if distance_m < 5.0 else 0.03
    for seed in range(3):
        features = _features(launcher, vehicle, sensor, seed)
        for x_m, y_m_ in CYLINDERS:
            (found,) = _near(features.circles, vehicle, x_m, y_m_)
            tx, ty = to_frame(vehicle, x_m, y_m_)
            error = np.array([found.cx_m - tx, found.cy_m - ty])
            assert math.hypot(*error) < bound_m
            assert float(error @ np.linalg.solve(found.covariance, error)) < 16.0
            assert found.radius_m == 0.15


def test_posts_are_landmarks_only_when_their_radius_matches(launcher: Site) -> None:
    vehicle = vehicle_before_board(10.0)
    for seed in range(3):
        left = _features(launcher, vehicle, "left", seed)
        right = _features(launcher, vehicle, "right", seed)
        for features in (left, right):
            assert _near(features.circles, vehicle, *POST_THIN) == []
        assert len(_near(left.circles, vehicle, *POST_LIKE)) == 1  # 0.15 m: the estimator gates
        assert right.rejections.get("circle.too_narrow", 0) >= 1  # the thin post, 5 m away


def test_the_walking_person_is_not_a_cylinder(launcher: Site) -> None:
    vehicle = vehicle_before_board(10.0)
    person = launcher.movers[0]
    for t_s in (0.0, 3.0, 6.0):
        for sensor in MOUNTS:
            features = _features(launcher, vehicle, sensor, 0, t_s)
            assert _near(features.circles, vehicle, *person.position_at(t_s)) == []


@pytest.mark.parametrize("distance_m", [10.0, 2.0])
@pytest.mark.parametrize("gap_m", [0.0, 0.05, 0.3])
def test_a_person_next_to_a_cylinder_does_not_pull_it_off(
    launcher: Site, distance_m: float, gap_m: float
) -> None:
    """Standing beside the left cylinder, on its outer side: the cylinder is either found
    where it is, or not at all (too wide with the person, or not isolated)."""
    cx, cy = CYLINDERS[0]
    person = Circle(cx, cy + 0.15 + 0.25 + gap_m, 0.25, 0.3, "person")
    site = launcher.merged(Site((), (person,)))
    vehicle = vehicle_before_board(distance_m)
    for sensor in MOUNTS:
        for seed in range(3):
            features = _features(site, vehicle, sensor, seed)
            tx, ty = to_frame(vehicle, cx, cy)
            for circle in _near(features.circles, vehicle, cx, cy):
                assert math.hypot(circle.cx_m - tx, circle.cy_m - ty) < 0.03


@pytest.mark.parametrize(("distance_m", "yaw_deg"), [(10.0, 0.0), (2.0, -2.0)])
@pytest.mark.parametrize("sensor", ["left", "right"])
def test_regions_of_interest_give_the_same_landmarks(
    launcher: Site, distance_m: float, yaw_deg: float, sensor: str
) -> None:
    """Discs around the cylinders and a band along the board, where a prior pose puts
    them: the cylinders come out exactly as from the whole scan; the board within a
    fraction of its σ (the band keeps a stub of each side board, so the corner's split
    may fall a point or two differently); and nothing else."""
    vehicle = vehicle_before_board(distance_m, 0.1, yaw_deg)
    mount = MOUNTS[sensor]
    ranges = render(launcher, vehicle, mount, 4)
    rois = [DiscRoi(*to_frame(vehicle, x, y), 0.5) for x, y in CYLINDERS]
    rois.append(LineRoi(*to_frame(vehicle, 0.0, -1.5), *to_frame(vehicle, 0.0, 1.5), 0.25))
    full = extract_features(ranges, SENSOR_ANGLES, mount)
    focused = extract_features(ranges, SENSOR_ANGLES, mount, rois=rois)
    assert len(focused.circles) == 2
    for circle in focused.circles:
        (twin,) = [c for c in full.circles if c.first_index == circle.first_index]
        assert (circle.cx_m, circle.cy_m, circle.n_points) == (twin.cx_m, twin.cy_m, twin.n_points)
        np.testing.assert_array_equal(circle.covariance, twin.covariance)
    (board,) = _board_lines(focused, vehicle)
    (twin_board,) = _board_lines(full, vehicle)
    difference = np.array(
        [board.r_m - twin_board.r_m, angle_difference(board.alpha_rad, twin_board.alpha_rad)]
    )
    assert float(difference @ np.linalg.solve(twin_board.covariance, difference)) < 1.0
    assert abs(board.n_points - twin_board.n_points) <= 6
    assert len(focused.lines) == 1  # no walls, no side boards: only the band's board
    # Fewer beams reach the fits: that is what makes it faster (benchmarks/bench_features.py).
    kept = lambda f: sum(stop - start for start, stop in f.segments)  # noqa: E731
    assert kept(focused) < 0.6 * kept(full)


def test_an_empty_set_of_regions_processes_nothing(launcher: Site) -> None:
    vehicle = vehicle_before_board(10.0)
    features = extract_features(
        render(launcher, vehicle, MOUNTS["left"], 0), SENSOR_ANGLES, MOUNTS["left"], rois=[]
    )
    assert features.segments == () and features.lines == () and features.circles == ()


def test_half_degree_scans_work_too(launcher: Site) -> None:
    """541 beams at 0.5° (the 50 Hz mode): the board and, at 5 m, both cylinders."""
    step = math.radians(0.5)
    angles = beam_angles_rad(step_rad=step) - math.pi / 2.0
    vehicle = vehicle_before_board(5.0)
    for sensor, mount in MOUNTS.items():
        ranges, _ = render_scan(
            launcher, 0.0, vehicle, mount, rng=np.random.default_rng(1), step_rad=step
        )
        features = extract_features(ranges, angles, mount)
        assert len(_board_lines(features, vehicle)) == 1, sensor
        for x_m, y_m in CYLINDERS:
            assert len(_near(features.circles, vehicle, x_m, y_m)) == 1, sensor


def test_a_drivers_mounted_scan_gives_the_same_features(launcher: Site) -> None:
    vehicle = vehicle_before_board(6.0)
    ranges = render(launcher, vehicle, MOUNTS["left"], 2)
    scan = scan_from_ranges(ranges, angular_step_deg=0.25)  # millimetres, as the device sends
    mounted = MountedScan(scan, "left", MOUNTS["left"], 0.0, 0)
    via_driver = extract_mounted_features(mounted, FeatureParams())
    direct = extract_features(scan.ranges_m, SENSOR_ANGLES, MOUNTS["left"])
    assert via_driver.segments == direct.segments
    assert [c.cx_m for c in via_driver.circles] == pytest.approx(
        [c.cx_m for c in direct.circles], abs=1e-12
    )
    assert [line.r_m for line in via_driver.lines] == pytest.approx(
        [line.r_m for line in direct.lines], abs=1e-12
    )


def test_a_person_in_front_of_the_board_occludes_its_ends(launcher: Site) -> None:
    """The board's pieces beside the person end at them: occluded ends; the corners with
    the side boards stay true ends; a region cutting the board leaves occluded ends."""
    site = launcher.merged(Site((), (Circle(-3.0, 0.3, 0.25, 0.3, "person"),)))
    vehicle = vehicle_before_board(8.0)
    mount = MOUNTS["right"]
    for seed in range(3):
        (board,) = _board_lines(_features(site, vehicle, "right", seed), vehicle)
        assert (board.start_occluded, board.end_occluded) == (False, True)  # corner, person
        assert board.length_m < 2.5
    band = LineRoi(*to_frame(vehicle, 0.0, -1.0), *to_frame(vehicle, 0.0, 1.0), 0.25)
    ranges = render(site, vehicle, mount, 0)
    (cut,) = extract_features(ranges, SENSOR_ANGLES, mount, rois=[band]).lines
    assert cut.start_occluded and cut.end_occluded
