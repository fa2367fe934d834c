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
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from appliance.sim.raycast import (
    NO_HIT,
    RayHits,
    cast_rays,
    inside_any_circle,
    nearer_of,
    nearest_hits,
    remission_of,
)
from appliance.sim.site import ShapeArrays, Site
from drivers.geometry import Pose2D

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


class RayCache:
    """The static site's hits of the last scan, for a scanner that has not moved.

    Why: a vehicle at rest (READY, e-stop, a fault) sees the same walls and posts scan
    after scan, and casting 541-1081 rays against them is most of the simulated
    vehicle's CPU. Only the static shapes are kept (keyed on the exact scanner pose and
    beam layout): walkers are cast for every scan and the nearer hit taken per beam,
    and noise is drawn for every scan as before, so a scan with the cache equals one
    without (to the last bits of floating point, which a differently sized product may
    round differently).
    """

    def __init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self._key: tuple[float, ...] | None = None
        self._shapes: object = None  # the static shapes the hits are of (held, not copied)
        self._hits: RayHits | None = None
        self.hits = 0
        self.misses = 0

    def static_hits(
        self, shapes: object, key: tuple[float, ...], cast: Callable[[], RayHits]
    ) -> RayHits:
        if self._hits is not None and shapes is self._shapes and key == self._key:
            self.hits += 1
            return self._hits
        self.misses += 1
        hits = cast()
        for array in hits:
            array.flags.writeable = False  # shared by every scan that hits
        self._key, self._shapes, self._hits = key, shapes, hits
        return hits


def _cast_with_cache(
    cache: RayCache,
    site: Site,
    shapes: ShapeArrays,
    pose: Pose2D,
    world_angles: Callable[[], NDArray[np.float64]],
    layout: tuple[float, float, float],
    max_range_m: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``cast_rays`` over ``shapes`` with the static ones from ``cache``; ``world_angles``
    is only called (and should be cached by the caller) when something must be cast."""
    static = site.static_shapes()
    n_static = static.segments.shape[0] + static.circles.shape[0]
    movers = shapes.circles[static.circles.shape[0] :]
    key = (pose.x_m, pose.y_m, pose.yaw_rad, *layout, max_range_m)
    if inside_any_circle(pose.x_m, pose.y_m, movers):
        beams = len(world_angles())  # blinded by a walker: no echo at all
        hits = RayHits(np.zeros(beams), np.full(beams, NO_HIT, dtype=np.int64))
    else:
        hits = cache.static_hits(
            static,
            key,
            lambda: nearest_hits(
                pose.x_m, pose.y_m, world_angles(), static.segments, static.circles, max_range_m
            ),
        )
        if movers.shape[0] and not inside_any_circle(pose.x_m, pose.y_m, static.circles):
            moving = nearest_hits(pose.x_m, pose.y_m, world_angles(), None, movers, max_range_m)
            hits = nearer_of(hits, moving, n_static)
    n_segments, n_circles = shapes.segments.shape[0], shapes.circles.shape[0]
    remission = remission_of(
        hits, n_segments, n_circles, shapes.segment_remission, shapes.circle_remission
    )
    return hits.ranges_m, remission


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
    cache: RayCache | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One scan: ranges in metres (0 = no echo) and the remission of what each beam hit.

    ``vehicle_pose`` is (x_m, y_m, yaw_rad) in the site frame; ``mount`` is the
    scanner's (x_m, y_m, yaw_rad) in the vehicle frame. Beams are in device order
    (see ``beam_angles_rad``). Noisy ranges are clipped to [0, max_range_m];
    ``noise_sigma_m=0`` gives exact geometry plus the bias, and leaves ``rng`` untouched.
    ``cache`` (one per scanner) skips the ray casting while nothing moved; the result is
    the same.
    """
    pose = scanner_pose(vehicle_pose, mount)
    shapes = site.shapes_at(t_s)

    def world_angles() -> NDArray[np.float64]:
        device_angles = _fixed_beam_angles_rad(start_angle_rad, stop_angle_rad, step_rad)
        angles: NDArray[np.float64] = device_angles + (pose.yaw_rad - DEVICE_FORWARD_RAD)
        return angles

    if cache is not None:
        layout = (start_angle_rad, stop_angle_rad, step_rad)
        ranges, remission = _cast_with_cache(
            cache, site, shapes, pose, functools.cache(world_angles), layout, max_range_m
        )
    else:
        ranges, remission = cast_rays(
            pose.x_m,
            pose.y_m,
            world_angles(),
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
