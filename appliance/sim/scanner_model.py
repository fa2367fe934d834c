"""What a SICK LMS111 mounted on the simulated vehicle measures at one instant.

Angle convention (the device's, so the twin can put these numbers in a telegram as is):
the LMS111 numbers its beams in its own frame from -45° to 225°, counter-clockwise seen
from above, with 90° straight ahead of the scanner (out of its window). The first value
of a scan is at -45°, behind and to the right. ROS drivers convert to the usual
x-forward frame by subtracting 90° (clearpathrobotics/LMS1xx, ``LMS1xx_node.cpp``:
``angle_min = startAngle / 10000 * DEG2RAD - M_PI / 2``; SICKAG/sick_scan_xd issue 322:
the internal coordinates have "an offset of 90 degrees to ros coordinates"). Here the
scanner's own x axis, given by the mount yaw in the vehicle frame, is the 90° beam.

Noise model: each beam's range gets a fixed per-scanner bias (the data sheet's
systematic error, up to a few centimetres, which the estimator must tolerate) plus
white Gaussian noise of 12 mm, the statistical error. A beam with no echo returns
exactly 0, as the device does, and never gets noise. Time and the random generator are
arguments, so a test (or a replay) gets the same scan for the same inputs.
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numpy.typing import NDArray

from appliance.sim.raycast import cast_rays
from appliance.sim.site import Pose2D, Site

LMS111_START_ANGLE_RAD = math.radians(-45.0)
LMS111_STOP_ANGLE_RAD = math.radians(225.0)
LMS111_STEP_RAD = math.radians(0.25)  # 1081 beams; 0.5° gives 541
LMS111_MAX_RANGE_M = 20.0  # the LMS111's specified scanning range (less on black surfaces)
LMS111_NOISE_SIGMA_M = 0.012  # the data sheet's statistical error, taken as 1 sigma
DEVICE_FORWARD_RAD = math.pi / 2.0  # the device angle that points along the scanner's x


def beam_angles_rad(
    start_angle_rad: float = LMS111_START_ANGLE_RAD,
    stop_angle_rad: float = LMS111_STOP_ANGLE_RAD,
    step_rad: float = LMS111_STEP_RAD,
) -> NDArray[np.float64]:
    """Device-frame angles of every beam, first to last, both ends included.

    The count is rounded so that (-45°, 225°, 0.25°) gives exactly 1081 beams despite
    floating-point radians.
    """
    if not step_rad > 0.0:
        raise ValueError(f"step_rad must be > 0, got {step_rad}")
    if stop_angle_rad < start_angle_rad:
        raise ValueError("stop_angle_rad must not be below start_angle_rad")
    count = math.floor((stop_angle_rad - start_angle_rad) / step_rad + 1e-6) + 1
    angles: NDArray[np.float64] = start_angle_rad + step_rad * np.arange(count, dtype=np.float64)
    return angles


@functools.lru_cache(maxsize=16)
def _fixed_beam_angles_rad(
    start_angle_rad: float, stop_angle_rad: float, step_rad: float
) -> NDArray[np.float64]:
    """`beam_angles_rad`, computed once per layout (every scan of a twin has the same)."""
    angles = beam_angles_rad(start_angle_rad, stop_angle_rad, step_rad)
    angles.flags.writeable = False
    return angles


def scanner_pose(
    vehicle_pose: Pose2D | tuple[float, float, float], mount: Pose2D | tuple[float, float, float]
) -> Pose2D:
    """The scanner's pose in the world from the vehicle's pose and the mount on it."""
    return Pose2D(*vehicle_pose).compose(Pose2D(*mount))


def render_scan(
    site: Site,
    t_s: float,
    vehicle_pose: Pose2D | tuple[float, float, float],
    mount: Pose2D | tuple[float, float, float],
    *,
    rng: np.random.Generator,
    start_angle_rad: float = LMS111_START_ANGLE_RAD,
    stop_angle_rad: float = LMS111_STOP_ANGLE_RAD,
    step_rad: float = LMS111_STEP_RAD,
    max_range_m: float = LMS111_MAX_RANGE_M,
    noise_sigma_m: float = LMS111_NOISE_SIGMA_M,
    range_bias_m: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One scan: ranges in metres (0 = no echo) and the remission of what each beam hit.

    ``vehicle_pose`` is (x_m, y_m, yaw_rad) in the site frame; ``mount`` is the
    scanner's (x_m, y_m, yaw_rad) in the vehicle frame. Beams are in device order
    (see ``beam_angles_rad``). Noisy ranges are clipped to [0, max_range_m];
    ``noise_sigma_m=0`` gives exact geometry plus the bias, and leaves ``rng`` untouched.
    """
    pose = scanner_pose(vehicle_pose, mount)
    device_angles = _fixed_beam_angles_rad(start_angle_rad, stop_angle_rad, step_rad)
    world_angles = device_angles + (pose.yaw_rad - DEVICE_FORWARD_RAD)
    shapes = site.shapes_at(t_s)
    ranges, remission = cast_rays(
        pose.x_m,
        pose.y_m,
        world_angles,
        shapes.segments,
        shapes.circles,
        max_range_m,
        shapes.segment_remission,
        shapes.circle_remission,
    )
    if noise_sigma_m > 0.0:
        error_m = rng.normal(range_bias_m, noise_sigma_m, size=ranges.shape)
    else:
        error_m = np.full(ranges.shape, range_bias_m)
    # Misses stay exactly 0; a hit the noise pushes below 0 becomes a miss, as it would
    # on the device, and one pushed past the maximum range is reported at the maximum.
    measured = np.where(ranges > 0.0, np.clip(ranges + error_m, 0.0, max_range_m), 0.0)
    return measured, np.where(measured > 0.0, remission, 0.0)
