"""The simulated LMS111: angle convention, the launcher seen from the approach, noise.

The error model itself (footprint, remission limit, drawn errors) is tested in
``test_scanner_errors.py``; here the geometry is checked with the ideal scanner.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.sim import (
    LMS111_NOISE_SIGMA_M,
    Circle,
    Pose2D,
    Segment,
    Site,
    beam_angles_rad,
    ideal_scanner,
    load_site,
    render_scan,
    scanner_pose,
    statistical_only,
)

SIGMA_M = LMS111_NOISE_SIGMA_M
IDEAL = ideal_scanner()
AHEAD = 540  # the 90° beam of a 1081-beam scan: straight out of the scanner's window


@pytest.fixture(scope="module")
def launcher() -> Site:
    return load_site("launcher")


def _beam_towards(x_m: float, y_m: float, pose: Pose2D) -> tuple[int, float]:
    """Index of the beam nearest to the bearing of a world point, and the distance to it."""
    bearing = math.atan2(y_m - pose.y_m, x_m - pose.x_m) - pose.yaw_rad
    device_deg = math.degrees(bearing) + 90.0
    return round((device_deg + 45.0) / 0.25), math.hypot(x_m - pose.x_m, y_m - pose.y_m)


def test_lms111_beam_layout() -> None:
    angles = beam_angles_rad()
    assert angles.size == 1081
    assert math.degrees(angles[0]) == pytest.approx(-45.0)
    assert math.degrees(angles[-1]) == pytest.approx(225.0)
    assert math.degrees(angles[AHEAD]) == pytest.approx(90.0)
    assert beam_angles_rad(step_rad=math.radians(0.5)).size == 541
    with pytest.raises(ValueError, match="step_rad"):
        beam_angles_rad(step_rad=0.0)


def test_device_angles_run_counter_clockwise_from_behind_right() -> None:
    """The first beam (-45°) looks back-right, the 180° beam looks left."""
    right_rear = Site((Segment(-3.0, -4.0, -4.0, -3.0, 1.0, "right_rear"),))
    left = Site((Segment(-1.0, 5.0, 1.0, 5.0, 1.0, "left"),))
    rng = np.random.default_rng(0)
    ranges, _ = render_scan(right_rear, 0.0, (0, 0, 0), (0, 0, 0), rng=rng, errors=IDEAL)
    assert ranges[0] == pytest.approx(3.5 * math.sqrt(2.0))
    assert not ranges[AHEAD:].any()
    ranges, _ = render_scan(left, 0.0, (0, 0, 0), (0, 0, 0), rng=rng, errors=IDEAL)
    assert ranges[900] == pytest.approx(5.0)  # (180 + 45) / 0.25
    assert not ranges[:AHEAD].any()


def test_front_board_straight_ahead_at_ten_metres(launcher: Site) -> None:
    rng = np.random.default_rng(1)
    exact, remission = render_scan(
        launcher, 0.0, (-10.0, 0.0, 0.0), (0.0, 0.0, 0.0), rng=rng, errors=IDEAL
    )
    assert exact[AHEAD] == pytest.approx(10.0, abs=1e-9)
    assert remission[AHEAD] == pytest.approx(0.9)
    noisy, _ = render_scan(launcher, 0.0, (-10.0, 0.0, 0.0), (0.0, 0.0, 0.0), rng=rng)
    assert noisy[AHEAD] == pytest.approx(10.0, abs=4 * SIGMA_M)


def test_mount_places_and_turns_the_scanner(launcher: Site) -> None:
    """The mount is composed onto the vehicle pose: offsets turn with the vehicle."""
    # Vehicle facing +y, scanner turned -90° on it: the scanner faces +x, the board.
    assert scanner_pose((-10.0, 0.0, math.pi / 2), (0.0, 0.0, -math.pi / 2)) == pytest.approx(
        Pose2D(-10.0, 0.0, 0.0)
    )
    # Vehicle facing +y, scanner 2 m ahead and 1 m to the left of it: at (-11, 2).
    assert scanner_pose((-10.0, 0.0, math.pi / 2), (2.0, 1.0, 0.0)) == pytest.approx(
        Pose2D(-11.0, 2.0, math.pi / 2)
    )
    ranges, _ = render_scan(
        launcher,
        0.0,
        (-14.0, 0.5, 0.0),
        (4.0, -0.5, 0.0),
        rng=np.random.default_rng(),
        errors=IDEAL,
    )
    assert ranges[AHEAD] == pytest.approx(10.0)


def test_cylinders_at_their_bearings(launcher: Site) -> None:
    pose = Pose2D(-10.0, 0.3, math.radians(3.0))
    ranges, remission = render_scan(
        launcher, 0.0, pose, (0.0, 0.0, 0.0), rng=np.random.default_rng(2)
    )
    for name in ("launcher.cylinder_left", "launcher.cylinder_right"):
        cylinder = launcher.shape(name)
        assert isinstance(cylinder, Circle)
        beam, distance = _beam_towards(cylinder.cx_m, cylinder.cy_m, pose)
        expected = distance - cylinder.radius_m
        # The beam passes within 1/8° of the centre: < 2 mm farther than the near side.
        assert ranges[beam] == pytest.approx(expected, abs=4 * SIGMA_M + 0.002)
        assert remission[beam] == pytest.approx(0.9)
        # Its neighbours two beams out still hit it (0.15 m radius at ~10 m is ~1.7°).
        assert ranges[beam - 2] < distance and ranges[beam + 2] < distance


def test_noise_is_twelve_millimetres_around_the_bias(launcher: Site) -> None:
    rng = np.random.default_rng(3)
    biased = statistical_only(range_offset_m=0.03)
    vehicle, mount = (-10.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    truth, _ = render_scan(launcher, 0.0, vehicle, mount, rng=rng, errors=IDEAL)
    board = slice(AHEAD - 30, AHEAD + 31)  # ±7.5°: all on the front board
    errors = np.array(
        [
            render_scan(launcher, 0.0, vehicle, mount, rng=rng, errors=biased)[0][board]
            - truth[board]
            for _ in range(200)
        ]
    )
    assert errors.mean() == pytest.approx(0.03, abs=0.0005)
    assert errors.std() == pytest.approx(SIGMA_M, rel=0.03)


def test_misses_stay_exactly_zero_and_ranges_are_clipped() -> None:
    at_limit = Site((Segment(19.99, -5.0, 19.99, 5.0, 0.5, "far"),))
    ranges, remission = render_scan(
        at_limit,
        0.0,
        (0, 0, 0),
        (0, 0, 0),
        rng=np.random.default_rng(4),
        errors=statistical_only(noise_sigma_m=0.05),
    )
    assert ranges.max() <= 20.0
    assert (ranges[: AHEAD - 100] == 0.0).all()  # looking away: no echo, no noise
    assert (remission[ranges == 0.0] == 0.0).all()
    assert (ranges[AHEAD - 5 : AHEAD + 6] > 19.7).all()


def test_same_inputs_same_scan(launcher: Site) -> None:
    first = render_scan(launcher, 1.0, (-9, 1, 0.1), (0.5, 0, 0), rng=np.random.default_rng(5))
    again = render_scan(launcher, 1.0, (-9, 1, 0.1), (0.5, 0, 0), rng=np.random.default_rng(5))
    np.testing.assert_array_equal(first[0], again[0])
    np.testing.assert_array_equal(first[1], again[1])


def test_the_walking_person_moves(launcher: Site) -> None:
    person = launcher.movers[0]
    assert person.position_at(0.0) != person.position_at(2.0)
    rng = np.random.default_rng(6)
    pose, mount = (-10.0, 0.0, 0.0), (0.0, 0.0, 0.0)
    before, _ = render_scan(launcher, 0.0, pose, mount, rng=rng, errors=IDEAL)
    after, _ = render_scan(launcher, 2.0, pose, mount, rng=rng, errors=IDEAL)
    changed = np.flatnonzero(np.abs(before - after) > 1e-9)
    assert changed.size > 0
    for t_s in (0.0, 2.0):
        x_m, y_m = person.position_at(t_s)
        beam, distance = _beam_towards(x_m, y_m, Pose2D(*pose))
        seen, _ = render_scan(launcher, t_s, pose, mount, rng=rng, errors=IDEAL)
        assert seen[beam] == pytest.approx(distance - person.radius_m, abs=0.01)
    # The board straight ahead is not disturbed by the person beside the lane.
    assert before[AHEAD] == after[AHEAD]
