"""Scans for the perception tests: exact ones computed here, realistic ones from the sim.

The exact scans (a line, a circle, seen from an origin) are computed in closed form
without the ray caster, so the fits can be checked against geometry known exactly and
the noise is exactly the model the fits assume: white, along the beam, σ per beam.
The realistic scans come from ``appliance.sim.render_scan`` with its default LMS111
errors (noise, beam footprint, remission limit), from the flat-bed's two scanners.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from appliance.sim import Site, beam_angles_rad, render_scan
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]

# The flat-bed profile's scanners (appliance/config/profiles/flatbed.toml).
FLATBED_FRONT_M = 5.8
LEFT_MOUNT = Pose2D(FLATBED_FRONT_M, 1.5, math.radians(45.0))
RIGHT_MOUNT = Pose2D(FLATBED_FRONT_M, -1.5, math.radians(-45.0))
MOUNTS = {"left": LEFT_MOUNT, "right": RIGHT_MOUNT}
# Sensor-frame beam angles (device angle − 90°): 1081 beams at 0.25°, −135° to 135°.
SENSOR_ANGLES = beam_angles_rad() - math.pi / 2.0
SIGMA_M = 0.012


def vehicle_before_board(distance_m: float, y_m: float = 0.0, yaw_deg: float = 0.0) -> Pose2D:
    """The vehicle (rear axle) whose front end is ``distance_m`` before the launcher's
    front board (the launcher frame's x = 0), heading into it."""
    return Pose2D(-distance_m - FLATBED_FRONT_M, y_m, math.radians(yaw_deg))


def render(site: Site, vehicle: Pose2D, mount: Pose2D, seed: int, t_s: float = 0.0) -> FloatArray:
    """A realistic scan (ranges, 0 = no echo) from the simulator."""
    ranges, _ = render_scan(site, t_s, vehicle, mount, rng=np.random.default_rng(seed))
    return ranges


def to_frame(pose: Pose2D, x_m: float, y_m: float) -> tuple[float, float]:
    """A point of the parent frame expressed in ``pose``'s frame (inverse of apply)."""
    dx, dy = x_m - pose.x_m, y_m - pose.y_m
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    return c * dx + s * dy, -s * dx + c * dy


def hessian_in_frame(r_m: float, alpha_rad: float, pose: Pose2D) -> tuple[float, float]:
    """A line given in the parent frame, in Hessian form (r >= 0) in ``pose``'s frame."""
    alpha = alpha_rad - pose.yaw_rad
    r = r_m - (pose.x_m * math.cos(alpha_rad) + pose.y_m * math.sin(alpha_rad))
    if r < 0.0:
        r, alpha = -r, alpha + math.pi
    return r, math.atan2(math.sin(alpha), math.cos(alpha))


def angle_difference(a_rad: float, b_rad: float) -> float:
    return math.atan2(math.sin(a_rad - b_rad), math.cos(a_rad - b_rad))


def line_ranges(r_m: float, alpha_rad: float, angles_rad: FloatArray) -> FloatArray:
    """Exact ranges from the origin to the line x cos α + y sin α = r (0 = misses)."""
    facing = np.cos(angles_rad - alpha_rad)
    with np.errstate(divide="ignore"):
        ranges = np.where(facing > 1e-9, r_m / facing, 0.0)
    return ranges


def circle_ranges(cx_m: float, cy_m: float, radius_m: float, angles_rad: FloatArray) -> FloatArray:
    """Exact ranges from the origin to a circle's near side (0 = misses)."""
    along = cx_m * np.cos(angles_rad) + cy_m * np.sin(angles_rad)
    miss_sq = cx_m * cx_m + cy_m * cy_m - along * along
    inside = radius_m * radius_m - miss_sq
    with np.errstate(invalid="ignore"):
        ranges = np.where(inside > 0.0, along - np.sqrt(inside), 0.0)
    return np.where(ranges > 0.0, ranges, 0.0)


def with_noise(
    ranges: FloatArray, rng: np.random.Generator, sigma_m: float = SIGMA_M
) -> FloatArray:
    """White range noise on the beams with an echo (the fits' own noise model)."""
    noisy = ranges + rng.normal(0.0, sigma_m, ranges.shape)
    return np.where(ranges > 0.0, noisy, 0.0)
