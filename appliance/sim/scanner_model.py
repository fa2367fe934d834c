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
as a fan of sub-rays across their footprint (``footprint_beams``), so a scan costs about
twice the thin-ray one rather than seven times. A
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
    nearest_hits,
    nearest_hits_along,
    remission_of,
)
from appliance.sim.scanner_errors import (
    TYPICAL_LMS111,
    BeamFootprint,
    RemissionLimit,
    ScannerErrors,
    echo_energy,
    first_strong_echo,
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


_NO_SEGMENTS = np.empty((0, 4))
_NO_SEGMENTS.flags.writeable = False


def _cast_with_cache(
    cache: RayCache,
    site: Site,
    shapes: ShapeArrays,
    pose: Pose2D,
    world_angles: Callable[[], NDArray[np.float64]],
    directions: Callable[[], NDArray[np.float64]],
    layout: tuple[float, float, float],
    max_range_m: float,
) -> tuple[RayHits, NDArray[np.float64]]:
    """``nearest_hits`` over ``shapes`` with the static ones from ``cache``; ``world_angles``
    and their ``directions`` are only called (and should be cached by the caller) when
    something must be cast: the static site and the walkers are cast along the same ones."""
    static = site.static_shapes()
    n_static = static.segments.shape[0] + static.circles.shape[0]
    movers = shapes.circles[static.circles.shape[0] :]
    key = (pose.x_m, pose.y_m, pose.yaw_rad, *layout, max_range_m)
    if inside_any_circle(pose.x_m, pose.y_m, movers):
        beams = len(world_angles())  # blinded by a walker: no echo at all
        hits = RayHits(np.zeros(beams), np.full(beams, NO_HIT, dtype=np.int64))
    else:
        inside_static = inside_any_circle(pose.x_m, pose.y_m, static.circles)

        def cast_static() -> RayHits:
            if inside_static:
                return nearest_hits(
                    pose.x_m, pose.y_m, world_angles(), static.segments, static.circles, max_range_m
                )  # blinded
            return nearest_hits_along(
                pose.x_m, pose.y_m, directions(), static.segments, static.circles, max_range_m
            )

        hits = cache.static_hits(static, key, cast_static)
        if movers.shape[0] and not inside_static:
            moving = nearest_hits_along(
                pose.x_m, pose.y_m, directions(), _NO_SEGMENTS, movers, max_range_m
            )
            hits = nearer_of(hits, moving, n_static)
    n_segments, n_circles = shapes.segments.shape[0], shapes.circles.shape[0]
    remission = remission_of(
        hits, n_segments, n_circles, shapes.segment_remission, shapes.circle_remission
    )
    return hits, remission


# Neighbouring central rays on different shapes whose ranges differ by less than this
# meet at a corner (a board and its side board, two walls): the footprint there averages
# ranges a few millimetres apart, so such a junction is not cast again.
JUNCTION_STEP_M = 0.02


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

    @functools.cache
    def world_angles() -> NDArray[np.float64]:
        device_angles = _fixed_beam_angles_rad(start_angle_rad, stop_angle_rad, step_rad)
        angles: NDArray[np.float64] = device_angles + (pose.yaw_rad - DEVICE_FORWARD_RAD)
        return angles

    @functools.cache
    def directions() -> NDArray[np.float64]:
        return beam_directions(world_angles())

    if cache is not None:
        layout = (start_angle_rad, stop_angle_rad, step_rad)
        hits, remission = _cast_with_cache(
            cache, site, shapes, pose, world_angles, directions, layout, max_range_m
        )
    else:
        hits = nearest_hits(
            pose.x_m, pose.y_m, world_angles(), shapes.segments, shapes.circles, max_range_m
        )
        remission = remission_of(
            hits,
            shapes.segments.shape[0],
            shapes.circles.shape[0],
            shapes.segment_remission,
            shapes.circle_remission,
        )
    ranges, remission = _echoes(
        hits, remission, errors, pose, shapes, world_angles, step_rad, max_range_m
    )
    if errors.ideal:
        error_m: NDArray[np.float64] | float = 0.0
    else:
        error_m = errors.range_offset_m + errors.range_scale * ranges
        if errors.noise_sigma_m > 0.0:
            error_m = error_m + rng.normal(0.0, errors.noise_sigma_m, size=ranges.shape)
    # Misses stay exactly 0; a hit the errors push below 0 becomes a miss, as it would
    # on the device, and one pushed past the maximum range is reported at the maximum.
    measured = np.where(ranges > 0.0, np.clip(ranges + error_m, 0.0, max_range_m), 0.0)
    return measured, np.where(measured > 0.0, remission, 0.0)


def _echoes(
    hits: RayHits,
    remission: NDArray[np.float64],
    errors: ScannerErrors,
    pose: Pose2D,
    shapes: ShapeArrays,
    world_angles: Callable[[], NDArray[np.float64]],
    step_rad: float,
    max_range_m: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True ranges and remissions of the echoes the device detects (0 = none): the
    central rays', the weak ones dropped, and the footprint's mix near edges."""
    ranges, cast_remission = hits.ranges_m, remission
    limit, footprint = errors.remission_limit, errors.footprint
    if limit is not None:
        weak = echo_energy(ranges, remission) < limit.min_energy
        ranges = np.where(weak, 0.0, ranges)
        remission = np.where(weak, 0.0, remission)
    if footprint is None:
        return ranges, remission
    beams = footprint_beams(hits, shapes.segments.shape[0], footprint, step_rad, max_range_m)
    if beams.size == 0:
        return ranges, remission
    ranges = np.array(ranges)  # the cast's arrays may be the cache's (read-only)
    remission = np.array(remission)
    central_m = hits.ranges_m[beams]
    sub_m, sub_remission = _cast_footprints(
        central_m, world_angles()[beams], pose, shapes, footprint, max_range_m
    )
    ranges[beams], remission[beams] = footprint_echo(
        _with_centre(sub_m, central_m),
        _with_centre(sub_remission, cast_remission[beams]),
        footprint,
        limit,
    )
    return ranges, remission


def footprint_beams(
    hits: RayHits, n_segments: int, footprint: BeamFootprint, step_rad: float, max_range_m: float
) -> NDArray[np.intp]:
    """The beams whose central ray does not stand for their footprint: cast them again.

    Those that may reach across an edge: where neighbouring central rays hit different
    shapes (or one misses) at ranges more than ``JUNCTION_STEP_M`` apart. A beam k beams
    away from the edge reaches it if the footprint's half-angle at the nearer of the
    edge's two ranges exceeds k beam steps; the farthest such reach over the scan is used
    for every edge. And those on a circle (shapes from ``n_segments`` on): across a
    post's curve the footprint's ranges differ by millimetres to centimetres.
    """
    ranges, index = hits.ranges_m, hits.hit_index
    count = ranges.shape[0]
    near = index >= n_segments
    edges = np.flatnonzero(
        (index[1:] != index[:-1]) & (np.abs(ranges[1:] - ranges[:-1]) > JUNCTION_STEP_M)
    )
    if edges.size == 0:
        return np.flatnonzero(near)
    before = np.where(ranges[edges] > 0.0, ranges[edges], max_range_m)
    after = np.where(ranges[edges + 1] > 0.0, ranges[edges + 1], max_range_m)
    reach = int(footprint.half_angle_rad(np.minimum(before, after)).max() // step_rad)
    for k in range(min(reach, count) + 1):
        near[np.maximum(edges - k, 0)] = True
        near[np.minimum(edges + 1 + k, count - 1)] = True
    return np.flatnonzero(near)


def _cast_footprints(
    central_m: NDArray[np.float64],
    angles_rad: NDArray[np.float64],
    pose: Pose2D,
    shapes: ShapeArrays,
    footprint: BeamFootprint,
    max_range_m: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ranges and remissions of every sub-ray but the central one, (beams, sub_rays - 1).

    The fan's half-angle is the footprint's at the central ray's range (at the maximum
    range for a beam whose central ray has no hit)."""
    side = footprint.side_offsets
    half = footprint.half_angle_rad(np.where(central_m > 0.0, central_m, max_range_m))
    fan = (angles_rad[:, None] + half[:, None] * side[None, :]).ravel()
    sub = nearest_hits(pose.x_m, pose.y_m, fan, shapes.segments, shapes.circles, max_range_m)
    sub_remission = remission_of(
        sub,
        shapes.segments.shape[0],
        shapes.circles.shape[0],
        shapes.segment_remission,
        shapes.circle_remission,
    )
    shape = (central_m.size, side.size)
    return sub.ranges_m.reshape(shape), sub_remission.reshape(shape)


def _with_centre(sides: NDArray[np.float64], centre: NDArray[np.float64]) -> NDArray[np.float64]:
    """(beams, k - 1) side sub-rays and (beams,) central rays as (beams, k), centre between."""
    beams, side_count = sides.shape
    half = side_count // 2
    full = np.empty((beams, side_count + 1))
    full[:, :half] = sides[:, :half]
    full[:, half] = centre
    full[:, half + 1 :] = sides[:, half:]
    return full


def footprint_echo(
    ranges_m: NDArray[np.float64],
    remission: NDArray[np.float64],
    footprint: BeamFootprint,
    limit: RemissionLimit | None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The echo of each beam from its sub-rays' (beams, sub_rays) hits: range and remission.

    Each sub-ray carries its profile weight of the beam's energy; the returned remission
    is the one a target filling the beam at the echo's range would need for the echo's
    energy (a beam half on a board reports about half its remission). Without a
    remission limit every hit counts, even of a black (0) surface.
    """
    _, weights = footprint.profile
    if limit is None:
        remission = np.maximum(remission, 1e-9)
    energy = weights * echo_energy(ranges_m, remission)
    min_energy = 0.0 if limit is None else limit.min_energy
    echo_m, echo_energy_ = first_strong_echo(ranges_m, energy, footprint.pulse_merge_m, min_energy)
    return echo_m, echo_energy_ * echo_m * echo_m
