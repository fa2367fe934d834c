"""Polar beams to Cartesian points: frames, the range calibration, beams without echo."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.perception.points import scan_points
from drivers.geometry import Pose2D
from drivers.lms111.mounted import MountedScan
from drivers.lms111.scan import scan_from_ranges

from .scenes import LEFT_MOUNT, SENSOR_ANGLES


def test_identity_frame_is_the_sensor_frame() -> None:
    """x out of the window, counter-clockwise: 90° is to the scanner's left."""
    points = scan_points([1.0, 2.0, 3.0], [0.0, math.pi / 2.0, -math.pi / 2.0])
    np.testing.assert_allclose(points.xy_m, [[1.0, 0.0], [0.0, 2.0], [0.0, -3.0]], atol=1e-15)
    assert points.valid.all()
    assert points.origin_xy_m == (0.0, 0.0)


def test_frame_is_the_sensors_pose_in_the_output_frame() -> None:
    frame = Pose2D(2.0, -1.0, math.radians(30.0))
    ranges = np.array([1.5, 4.0, 7.25])
    angles = np.array([-1.0, 0.2, 2.0])
    points = scan_points(ranges, angles, frame)
    for (x, y), r, a in zip(points.xy_m, ranges, angles, strict=True):
        assert (x, y) == pytest.approx(frame.apply(r * math.cos(a), r * math.sin(a)), abs=1e-12)
    assert points.origin_xy_m == (2.0, -1.0)
    np.testing.assert_allclose(
        points.directions,
        np.column_stack([np.cos(angles + frame.yaw_rad), np.sin(angles + frame.yaw_rad)]),
    )


def test_mount_frame_agrees_with_the_drivers_vehicle_points() -> None:
    """The driver's MountedScan converts device angles (−90°) once; we must agree."""
    rng = np.random.default_rng(0)
    ranges = np.where(rng.random(541) < 0.2, 0.0, rng.uniform(0.5, 19.0, 541))
    scan = scan_from_ranges(ranges)  # 0.5°, device angles −45°…225°
    mounted = MountedScan(scan, "left", LEFT_MOUNT, 0.0, 0)
    points = scan_points(scan.ranges_m, scan.angles_rad - math.pi / 2.0, mounted.mount)
    np.testing.assert_allclose(points.valid_xy_m(), mounted.points_vehicle_m(), atol=1e-12)


def test_range_offset_is_subtracted_from_every_echo() -> None:
    points = scan_points([5.0, 0.0, 0.02], [0.0, 0.1, 0.2], range_offset_m=0.03)
    assert points.ranges_m[0] == pytest.approx(4.97)
    assert points.xy_m[0] == pytest.approx([4.97, 0.0])
    # No echo stays no echo, and an echo the offset takes below 0 becomes none.
    assert points.valid.tolist() == [True, False, False]


def test_beams_without_echo_are_invalid_and_never_nan() -> None:
    points = scan_points([0.0, math.nan, math.inf, -1.0, 2.0], [0.0, 0.1, 0.2, math.nan, 0.4])
    assert points.valid.tolist() == [False, False, False, False, True]
    assert np.isfinite(points.xy_m).all()
    assert np.isfinite(points.directions).all()
    assert (points.ranges_m[~points.valid] == 0.0).all()


def test_every_beam_keeps_its_direction_echo_or_not() -> None:
    """A beam without an echo still looks where it looks; one without an angle looks
    along the frame's yaw (a finite placeholder). Scans of one scanner share the
    directions (computed once), so a second frame must not see the first one's."""
    angles = [0.1, 0.2, math.nan, 0.4]
    for yaw in (0.5, -1.0):
        points = scan_points([2.0, 0.0, 3.0, math.inf], angles, Pose2D(1.0, 2.0, yaw))
        expected = [a + yaw if math.isfinite(a) else yaw for a in angles]
        np.testing.assert_array_equal(
            points.directions, np.column_stack([np.cos(expected), np.sin(expected)])
        )
        frame = Pose2D(1.0, 2.0, yaw)
        assert points.xy_m[0] == pytest.approx(
            frame.apply(2.0 * math.cos(0.1), 2.0 * math.sin(0.1))
        )
        assert points.xy_m[1:].tolist() == [[1.0, 2.0]] * 3
        with pytest.raises(ValueError, match="read-only"):
            points.directions[0, 0] = 2.0


def test_mismatched_arrays_are_a_callers_bug() -> None:
    with pytest.raises(ValueError, match="1-D of one length"):
        scan_points([1.0, 2.0], [0.0])
    with pytest.raises(ValueError, match="1-D of one length"):
        scan_points([[1.0]], [[0.0]])


def test_arrays_are_read_only() -> None:
    points = scan_points([1.0], [0.0])
    with pytest.raises(ValueError, match="read-only"):
        points.xy_m[0, 0] = 2.0


@given(
    st.lists(st.floats(allow_nan=True, allow_infinity=True, width=64), min_size=0, max_size=20),
    st.floats(-10.0, 10.0),
)
def test_any_ranges_give_finite_points(ranges: list[float], offset: float) -> None:
    angles = np.linspace(-2.0, 2.0, len(ranges))
    points = scan_points(ranges, angles, Pose2D(1.0, 2.0, 0.5), range_offset_m=offset)
    assert np.isfinite(points.xy_m).all()
    assert (points.ranges_m[points.valid] > 0.0).all()


def _straightforward_points(
    ranges: np.ndarray, angles: np.ndarray, frame: Pose2D, offset: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The conversion as it was first written: every step on every beam, nothing kept."""
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & np.isfinite(angles) & (ranges > 0.0)
        corrected = np.where(valid, ranges - offset, 0.0)
        valid &= corrected > 0.0
        corrected = np.where(valid, corrected, 0.0)
        world = np.where(np.isfinite(angles), angles, 0.0) + frame.yaw_rad
    xy = np.column_stack((corrected * np.cos(world), corrected * np.sin(world)))
    return xy + np.array([frame.x_m, frame.y_m]), corrected, valid


@pytest.mark.parametrize("offset", [0.0, 0.02, -0.01])
def test_points_are_the_straightforward_conversions_to_the_last_bit(offset: float) -> None:
    """The kept beam directions, and the shortcut without a range offset, change nothing:
    two scanners' frames over the same angles, scan after scan, with odd beams."""
    rng = np.random.default_rng(5)
    angles = SENSOR_ANGLES.copy()
    angles[7] = math.nan
    for scan in range(6):
        ranges = rng.uniform(0.0, 30.0, angles.shape)
        ranges[rng.integers(0, len(ranges), 20)] = rng.choice([0.0, math.inf, math.nan, 0.01])
        frame = (LEFT_MOUNT, Pose2D(5.8, -1.5, math.radians(-45.0)))[scan % 2]
        points = scan_points(ranges, angles, frame, range_offset_m=offset)
        xy, corrected, valid = _straightforward_points(ranges, angles, frame, offset)
        assert points.xy_m.tobytes() == xy.tobytes()
        assert points.ranges_m.tobytes() == corrected.tobytes()
        assert (points.valid == valid).all()
