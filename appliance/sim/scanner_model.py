"""What a SICK LMS111 mounted on the simulated vehicle measures at one instant.

Angle convention (the device's, so the twin can put these numbers in a telegram as is):
the LMS111 numbers its beams in its own frame from -45° to 225°, counter-clockwise seen
from above, with 90° straight ahead of the scanner (out of its window). The first value
of a scan is at -45°, behind and to the right. ROS drivers convert to the usual
x-forward frame by subtracting 90° (clearpathrobotics/LMS1xx, ``LMS1xx_node.cpp``:
``angle_min = startAngle / 10000 * DEG2RAD - M_PI / 2``; SICKAG/sick_scan_xd issue 322:
the internal coordinates have "an offset of 90 degrees to ros coordinates"). Here the
scanner's own x axis, given by the mount yaw in the vehicle frame, is the 90° beam.

Errors: ``render_scan`` takes a scanner's `ScannerErrors` (``scanner_errors``): the
data sheet's noise and systematic error, the beam footprint that mixes the ranges of a
beam straddling an edge, the remission the device needs at each range, the mount error.
The central ray of every beam is cast as an ideal scanner would; only beams near an edge
(where the central rays' hit shape jumps between neighbours) or on a post are cast again
as a fan of sub-rays across their footprint (``scanner_footprint``), so a scan costs about
twice the thin-ray one rather than seven times. Both casts are `raycast`'s. A
beam with no echo returns exactly 0, as the device does, and never gets noise. Time and
the random generator are arguments, so a test (or a replay) gets the same scan for the
same inputs.
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
    beam_directions,
    inside_any_circle,
    nearer_of,
    nearest_hits_along,
)
from appliance.sim.scanner_errors import TYPICAL_LMS111, ScannerErrors
from appliance.sim.scanner_footprint import (
    JUNCTION_STEP_M,
    echoes,
    footprint_beams,
    footprint_echo,
)
from appliance.sim.site import ShapeArrays, Site
from drivers.geometry import Pose2D

LMS111_START_ANGLE_RAD = math.radians(-45.0)
LMS111_STOP_ANGLE_RAD = math.radians(225.0)
LMS111_STEP_RAD = math.radians(0.25)  # 1081 beams; 0.5° gives 541
LMS111_MAX_RANGE_M = 20.0  # the LMS111's specified scanning range (less on black surfaces)
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
    without, to the last bit (a beam's hit does not depend on what else is cast).
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


__all__ = [
    "DEVICE_FORWARD_RAD",
    "JUNCTION_STEP_M",
    "LMS111_MAX_RANGE_M",
    "LMS111_START_ANGLE_RAD",
    "LMS111_STEP_RAD",
    "LMS111_STOP_ANGLE_RAD",
    "RayCache",
    "beam_angles_rad",
    "footprint_beams",
    "footprint_echo",
    "render_scan",
    "scanner_pose",
]


_EVERY = slice(None)
_NO_SEGMENTS = np.empty((0, 4))
_NO_SEGMENTS.flags.writeable = False


class _Scan:
    """One scan's geometry; the beams' directions are made on first use: a scanner at
    rest, whose static hits are cached, needs them only for a walker or a footprint."""

    def __init__(
        self, pose: Pose2D, shapes: ShapeArrays, angles_rad: NDArray[np.float64], max_range_m: float
    ) -> None:
        self.pose, self.shapes, self.angles_rad = pose, shapes, angles_rad
        self.max_range_m = max_range_m
        self._directions: NDArray[np.float64] | None = None

    def directions(self) -> NDArray[np.float64]:
        if self._directions is None:
            self._directions = beam_directions(self.angles_rad)
        return self._directions

    def cast(
        self, directions: NDArray[np.float64], segments: bool = True, circles: slice = _EVERY
    ) -> RayHits:
        """The nearest hits along ``directions`` of the segments (or none) and ``circles``
        (a run of them, numbered from 0 after the segments cast); the scanner must be
        outside every circle."""
        shapes = self.shapes
        segs = shapes.segments if segments else _NO_SEGMENTS
        pose = self.pose
        return nearest_hits_along(
            pose.x_m, pose.y_m, directions, segs, shapes.circles[circles], self.max_range_m
        )

    def blind(self) -> RayHits:
        """No echo at all: the scanner is inside a circle."""
        beams = self.angles_rad.shape[0]
        return RayHits(np.zeros(beams), np.full(beams, NO_HIT, dtype=np.int64))


def _cast_with_cache(cache: RayCache, site: Site, scan: _Scan, key: tuple[float, ...]) -> RayHits:
    """The scan's nearest hits, with the static shapes' from ``cache`` when it has them
    for ``key``; the walkers are cast along the same beams and the nearer hit is taken
    (a hit does not depend on what else is cast with it: the same as one cast of all)."""
    static = site.static_shapes()
    n_static = static.circles.shape[0]
    walkers = slice(n_static, None)
    pose = scan.pose
    if inside_any_circle(pose.x_m, pose.y_m, scan.shapes.circles[walkers]):
        return scan.blind()
    inside_static = inside_any_circle(pose.x_m, pose.y_m, static.circles)

    def cast_static() -> RayHits:
        if inside_static:
            return scan.blind()
        return scan.cast(scan.directions(), circles=slice(n_static))

    hits = cache.static_hits(static, key, cast_static)
    if scan.shapes.circles.shape[0] > n_static and not inside_static:
        walking = scan.cast(scan.directions(), segments=False, circles=walkers)
        hits = nearer_of(hits, walking, static.segments.shape[0] + n_static)
    return hits


def render_scan(
    site: Site,
    t_s: float,
    vehicle_pose: Pose2D | tuple[float, float, float],
    mount: Pose2D | tuple[float, float, float],
    *,
    rng: np.random.Generator,
    errors: ScannerErrors = TYPICAL_LMS111,
    start_angle_rad: float = LMS111_START_ANGLE_RAD,
    stop_angle_rad: float = LMS111_STOP_ANGLE_RAD,
    step_rad: float = LMS111_STEP_RAD,
    max_range_m: float = LMS111_MAX_RANGE_M,
    cache: RayCache | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """One scan: ranges in metres (0 = no echo) and the remission of what each beam saw.

    ``vehicle_pose`` is (x_m, y_m, yaw_rad) in the site frame; ``mount`` is the
    scanner's configured (x_m, y_m, yaw_rad) in the vehicle frame, and the scan is taken
    from ``errors.true_mount(mount)``. Beams are in device order (see
    ``beam_angles_rad``). Measured ranges are clipped to [0, max_range_m]; the remission
    of a mixed echo is the one a target filling the beam at that range would need to
    give its energy. ``rng`` is drawn from only if ``errors.noise_sigma_m > 0`` (one
    normal per beam per scan). ``cache`` (one per scanner) skips casting the static site
    while nothing moved; the result is the same.
    """
    pose = scanner_pose(vehicle_pose, errors.true_mount(mount))
    shapes = site.shapes_at(t_s)
    device_angles = _fixed_beam_angles_rad(start_angle_rad, stop_angle_rad, step_rad)
    scan = _Scan(pose, shapes, device_angles + (pose.yaw_rad - DEVICE_FORWARD_RAD), max_range_m)
    if cache is not None:
        key = (pose.x_m, pose.y_m, pose.yaw_rad, start_angle_rad, stop_angle_rad, step_rad)
        hits = _cast_with_cache(cache, site, scan, (*key, max_range_m))
    elif inside_any_circle(pose.x_m, pose.y_m, shapes.circles):
        hits = scan.blind()
    else:
        hits = scan.cast(scan.directions())
    # What each shape number's surface remits, the last entry (index -1: none) 0.
    table = np.concatenate([shapes.segment_remission, shapes.circle_remission, _NO_REMISSION])
    ranges, remission = echoes(
        hits,
        table.take(hits.hit_index),
        errors,
        shapes.segments.shape[0],
        scan.cast,
        table,
        scan.angles_rad,
        step_rad,
        max_range_m,
    )
    # Misses stay exactly 0; a hit the errors push below 0 becomes a miss, as it would
    # on the device, and one pushed past the maximum range is reported at the maximum.
    if errors.ideal:
        measured = ranges + 0.0
    else:
        error_m = errors.range_scale * ranges
        error_m += errors.range_offset_m
        if errors.noise_sigma_m > 0.0:
            error_m += rng.normal(0.0, errors.noise_sigma_m, size=ranges.shape)
        measured = ranges + error_m
    np.maximum(measured, 0.0, out=measured)  # np.clip, without its overhead
    np.minimum(measured, max_range_m, out=measured)
    measured = np.where(ranges > 0.0, measured, 0.0)
    return measured, np.where(measured > 0.0, remission, 0.0)


_NO_REMISSION = np.zeros(1)
_NO_REMISSION.flags.writeable = False
