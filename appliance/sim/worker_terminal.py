"""The worker's terminal: a consumer 3D LiDAR carried through the site, and what it gets wrong.

Kinouchi et al. (Sections 2.1, 2.2(4), 3.1): a worker first photographs a marker on the
floor, whose position the vehicle knows, then walks the storage area scanning it with a
tablet; the terminal's map ("the worker's terminal map", a 3D point cloud) has its origin
where the terminal saw the marker, so the vehicle takes T0 (its first guess of the map
transform) from the marker's surveyed pose. The terminal is "not for industrial use": its
map is off by a few centimetres and a small heading, and in the paper's trial n = 2 it was
notably worse. This module renders such a map from a `Site`, errors and all, with every
truth the tests and reports need beside it.

Frames: the *site* frame is the simulation's; the *worker* frame W is the terminal's map
frame. The marker's surveyed pose ``marker`` is exact (the marker is where it was
surveyed); the terminal's estimate of it is not, so W's true pose in the site is

    t0_true = marker ∘ marker_error

(``Pose2D.compose``: the error is expressed in the marker's own frame), while the vehicle,
like the terminal, believes W is the marker: its T0 is ``marker``. Heights are not in
error: AR terminals align their map's z with gravity, so the floor stays at z = 0.

The error model and its presets are `terminal_errors`'s; each viewpoint's points are
placed in W through the terminal's believed pose of that viewpoint, so its cloud is
moved rigidly by ``believed ∘ true⁻¹`` (`WorkerSurvey.cloud_motions`). The draws come
from the caller's generator: the walk's first (see `terminal_errors.draw_walk`), then
the range noise per point, or the fit noise per object of `survey_objects`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from appliance.mapping.object_file import DEFAULT_SIGMA_XY_M, DEFAULT_SIGMA_YAW_DEG
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap, inverse_pose
from appliance.sim.raycast3d import (
    DEFAULT_WORLD,
    NO_HIT,
    FloatArray,
    World3D,
    WorldParams,
    cast_rays_3d,
    grid_directions,
    site_world,
    with_walkers,
)
from appliance.sim.site import WALKING_SPEED_MPS, Site
from appliance.sim.terminal_errors import (
    CONSUMER,
    IDEAL,
    WORSE,
    TerminalErrors,
    draw_walk,
    wrap_rad,
    wrapped,
)
from appliance.sim.worker_route import walk_around
from drivers.geometry import Pose2D

TERMINAL_HEIGHT_M = 1.2  # a tablet held at chest height
_FULL_TURN_RAD = 2.0 * math.pi


@dataclass(frozen=True)
class TerminalScanParams:
    """What one viewpoint's scan covers. A tablet's LiDAR (e.g. the iPad Pro's) reaches
    about 5 m; a worker turning on the spot while scanning covers the full circle, so the
    default field is 360 deg (set a narrower ``horizontal_fov_rad`` for a device held
    still, centred on the viewpoint's heading). Steps of 0.75 deg: ~51k rays a viewpoint.
    """

    horizontal_fov_rad: float = _FULL_TURN_RAD
    azimuth_step_rad: float = math.radians(0.75)
    elevation_min_rad: float = math.radians(-60.0)
    elevation_max_rad: float = math.radians(20.0)
    elevation_step_rad: float = math.radians(0.75)
    max_range_m: float = 5.0
    range_sigma_m: float = 0.01  # consumer time-of-flight depth: about a centimetre

    def __post_init__(self) -> None:
        if not 0.0 < self.horizontal_fov_rad <= _FULL_TURN_RAD:
            raise ValueError("horizontal_fov_rad must be in (0, 2 pi]")
        if not (self.azimuth_step_rad > 0.0 and self.elevation_step_rad > 0.0):
            raise ValueError("angular steps must be > 0")
        if not -math.pi / 2 <= self.elevation_min_rad <= self.elevation_max_rad <= math.pi / 2:
            raise ValueError("elevations must satisfy -pi/2 <= min <= max <= pi/2")
        if not (self.max_range_m > 0.0 and self.range_sigma_m >= 0.0):
            raise ValueError("max_range_m must be > 0 and range_sigma_m >= 0")


def scan_directions(heading_rad: float, params: TerminalScanParams) -> FloatArray:
    """(rays, 3) unit directions in the site frame of a scan with the device heading
    ``heading_rad``: a full turn starts at the heading, a narrower field is centred on it."""
    if params.horizontal_fov_rad >= _FULL_TURN_RAD - 1e-9:
        count = max(1, round(_FULL_TURN_RAD / params.azimuth_step_rad))
        azimuths = heading_rad + np.arange(count) * (_FULL_TURN_RAD / count)
    else:
        count = math.floor(params.horizontal_fov_rad / params.azimuth_step_rad + 1e-9) + 1
        half = (count - 1) * params.azimuth_step_rad / 2.0
        azimuths = heading_rad + np.linspace(-half, half, count)
    span = params.elevation_max_rad - params.elevation_min_rad
    rows = math.floor(span / params.elevation_step_rad + 1e-9) + 1
    elevations = params.elevation_min_rad + np.arange(rows) * params.elevation_step_rad
    return grid_directions(
        np.asarray(azimuths, dtype=np.float64), np.asarray(elevations, dtype=np.float64)
    )


class TerminalScan(NamedTuple):
    """One viewpoint's returns in the site frame, and what each one hit."""

    xyz_m: FloatArray  # (N, 3)
    surface_index: NDArray[np.int64]  # (N,) into the world's names


def scan_viewpoint(
    world: World3D,
    viewpoint: Pose2D,
    height_m: float,
    params: TerminalScanParams,
    rng: np.random.Generator,
) -> TerminalScan:
    """The points the terminal at ``viewpoint`` (site frame), ``height_m`` above the
    floor, measures: the nearest hit of each ray within range, its range perturbed by
    Gaussian noise along the ray (the range limit applies to the true range); rays
    without a hit are dropped. Draws one normal per point from ``rng`` if sigma > 0."""
    origin = np.array([viewpoint.x_m, viewpoint.y_m, height_m])
    directions = scan_directions(viewpoint.yaw_rad, params)
    hits = cast_rays_3d(world, origin, directions, params.max_range_m)
    seen = hits.surface_index != NO_HIT
    range_m = hits.range_m[seen]
    if params.range_sigma_m > 0.0:
        range_m = range_m + params.range_sigma_m * rng.standard_normal(range_m.shape[0])
    xyz = origin + range_m[:, None] * directions[seen]
    return TerminalScan(xyz, hits.surface_index[seen])


def transform_points(pose: Pose2D, xyz_m: FloatArray) -> FloatArray:
    """Points (N, 3) given in ``pose``'s frame, in the parent frame (z unchanged)."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    moved = np.array(xyz_m, dtype=np.float64).reshape(-1, 3)
    x, y = moved[:, 0].copy(), moved[:, 1].copy()
    moved[:, 0] = pose.x_m + c * x - s * y
    moved[:, 1] = pose.y_m + s * x + c * y
    return moved


@dataclass(frozen=True, eq=False)
class WorkerSurvey:
    """A worker's terminal map (``xyz_m``, in W) and the truth about it.

    ``marker`` is what the vehicle takes as T0 (W's pose in the site, believed);
    ``t0_true`` is W's true pose in the site: ``marker ∘ marker_error``. A point p in
    ``xyz_m`` lies in truth at ``t0_true ∘ cloud_motions[k]⁻¹ ∘ p`` in the site, k its
    viewpoint; the site point seen from viewpoint k appears at ``cloud_motions[k] ∘
    t0_true⁻¹`` of it. The vehicle, taking T0 = ``marker``, puts p at ``marker ∘ p``.
    """

    xyz_m: FloatArray  # (N, 3) in W
    viewpoint_index: NDArray[np.int64]  # (N,): which viewpoint saw each point
    surface_index: NDArray[np.int64]  # (N,): what it is (into surface_names), for scoring
    surface_names: tuple[str, ...]  # the world's: floor, boxes, walls, posts, walkers
    origins_m: FloatArray  # (K, 3): the believed viewpoint positions in W, z = height
    marker: Pose2D
    t0_true: Pose2D
    marker_error: Pose2D
    true_viewpoints: tuple[Pose2D, ...]  # in W
    believed_viewpoints: tuple[Pose2D, ...]  # in W
    walked_m: FloatArray  # (K,): distance walked from the marker to each viewpoint

    @property
    def pose_errors(self) -> tuple[Pose2D, ...]:
        """Per viewpoint: believed minus true position (in W) and heading, wrapped."""
        return tuple(
            Pose2D(b.x_m - t.x_m, b.y_m - t.y_m, wrap_rad(b.yaw_rad - t.yaw_rad))
            for b, t in zip(self.believed_viewpoints, self.true_viewpoints, strict=True)
        )

    @property
    def cloud_motions(self) -> tuple[Pose2D, ...]:
        """Per viewpoint: the rigid motion (in W) its ideal points were moved by."""
        return tuple(
            wrapped(b.compose(inverse_pose(t)))
            for b, t in zip(self.believed_viewpoints, self.true_viewpoints, strict=True)
        )

    def points_of(self, viewpoint: int) -> FloatArray:
        result: FloatArray = self.xyz_m[self.viewpoint_index == viewpoint]
        return result


def survey(
    site: Site,
    marker: Pose2D,
    viewpoints: Sequence[Pose2D],
    *,
    rng: np.random.Generator,
    height_m: float = TERMINAL_HEIGHT_M,
    errors: TerminalErrors = CONSUMER,
    params: TerminalScanParams = TerminalScanParams(),
    world: WorldParams = DEFAULT_WORLD,
    start_s: float = 0.0,
) -> WorkerSurvey:
    """The worker's terminal map of ``site`` from a walk through ``viewpoints`` (site
    frame; each one's yaw is the device's heading), after photographing ``marker``.

    Walkers are where they are when the worker reaches each viewpoint, walking at
    `WALKING_SPEED_MPS` from the marker from ``start_s``. A viewpoint inside a solid sees
    nothing (see `raycast3d`). Raises ValueError only for a non-finite viewpoint or
    marker or a height that is not > 0.
    """
    _check_poses(marker, viewpoints)
    if not (math.isfinite(height_m) and height_m > 0.0):
        raise ValueError(f"height_m must be finite and > 0, got {height_m}")
    walk = draw_walk(marker, viewpoints, errors, rng)
    static = site_world(site, world)
    clouds: list[FloatArray] = []
    surfaces: list[NDArray[np.int64]] = []
    owners: list[NDArray[np.int64]] = []
    for k, (viewpoint, believed) in enumerate(zip(viewpoints, walk.believed_w, strict=True)):
        now = with_walkers(
            static, site, start_s + float(walk.walked_m[k]) / WALKING_SPEED_MPS, world
        )
        scan = scan_viewpoint(now, viewpoint, height_m, params, rng)
        site_to_w = believed.compose(inverse_pose(viewpoint))
        clouds.append(transform_points(site_to_w, scan.xyz_m))
        surfaces.append(scan.surface_index)
        owners.append(np.full(scan.surface_index.shape[0], k, dtype=np.int64))
    origins = np.array([(b.x_m, b.y_m, height_m) for b in walk.believed_w]).reshape(-1, 3)
    return WorkerSurvey(
        np.concatenate(clouds) if clouds else np.empty((0, 3)),
        np.concatenate(owners) if owners else np.empty(0, dtype=np.int64),
        np.concatenate(surfaces) if surfaces else np.empty(0, dtype=np.int64),
        with_walkers(static, site, start_s, world).names,  # walkers' names: the same at any time
        origins,
        marker,
        walk.t0_true,
        walk.marker_error,
        walk.true_w,
        walk.believed_w,
        walk.walked_m,
    )


def _check_poses(marker: Pose2D, viewpoints: Sequence[Pose2D]) -> None:
    for pose in (marker, *viewpoints):
        if not all(math.isfinite(v) for v in pose):
            raise ValueError(f"poses must be finite, got {pose}")


class WorkerObject(NamedTuple):
    """One object of a worker map's object-list form, in W (its pose's yaw: the length)."""

    name: str
    x_m: float
    y_m: float
    yaw_rad: float
    length_m: float
    width_m: float


@dataclass(frozen=True)
class WorkerObjectSurvey:
    """The object-list form of a worker map and the truth needed to score it (as in
    `WorkerSurvey`: the vehicle's T0 is ``marker``, W's true pose ``t0_true``)."""

    objects: tuple[WorkerObject, ...]
    marker: Pose2D
    t0_true: Pose2D
    marker_error: Pose2D
    measured_from: tuple[int, ...]  # per object, the viewpoint whose pose placed it


def survey_objects(
    site: Site,
    marker: Pose2D,
    errors: TerminalErrors,
    rng: np.random.Generator,
    *,
    viewpoints: Sequence[Pose2D] | None = None,
) -> WorkerObjectSurvey:
    """Every pallet of ``site`` as the terminal would list it in W (no cloud): its pose
    through the believed pose of the nearest viewpoint of the walk (default
    `worker_route.walk_around` of the site, all pallets), then the terminal's own fit
    error (``object_*_sigma``). With the same seed and walk, the marker error and drift
    are those of `survey`."""
    if viewpoints is None:
        viewpoints = walk_around(site)
    _check_poses(marker, viewpoints)
    walk = draw_walk(marker, viewpoints, errors, rng)
    unit = rng.standard_normal(3 * len(site.pallets))
    objects: list[WorkerObject] = []
    measured_from: list[int] = []
    positions = np.array([(v.x_m, v.y_m) for v in viewpoints]).reshape(-1, 2)
    for i, pallet in enumerate(site.pallets):
        fit = Pose2D(
            errors.object_xy_sigma_m * float(unit[3 * i]),
            errors.object_xy_sigma_m * float(unit[3 * i + 1]),
            errors.object_yaw_sigma_rad * float(unit[3 * i + 2]),
        )
        if positions.shape[0]:
            gaps_m = np.hypot(positions[:, 0] - pallet.pose.x_m, positions[:, 1] - pallet.pose.y_m)
            k = int(np.argmin(gaps_m))
            site_to_w = walk.believed_w[k].compose(inverse_pose(viewpoints[k]))
        else:  # no walk: placed from where the marker was photographed, without drift
            k, site_to_w = -1, inverse_pose(walk.t0_true)
        placed = wrapped(site_to_w.compose(pallet.pose).compose(fit))
        objects.append(WorkerObject(pallet.name, *placed, pallet.length_m, pallet.width_m))
        measured_from.append(k)
    return WorkerObjectSurvey(
        tuple(objects), marker, walk.t0_true, walk.marker_error, tuple(measured_from)
    )


__all__ = [  # the error presets re-exported: a survey's callers need both
    "CONSUMER",
    "IDEAL",
    "TERMINAL_HEIGHT_M",
    "WORSE",
    "TerminalErrors",
    "TerminalScan",
    "TerminalScanParams",
    "WorkerObject",
    "WorkerObjectSurvey",
    "WorkerSurvey",
    "scan_directions",
    "scan_viewpoint",
    "survey",
    "survey_objects",
    "transform_points",
]


def object_pallet_map(objects: Sequence[WorkerObject]) -> PalletMap:
    """The terminal's object list as a pallet map: each standard pallet (others are not
    listed by the terminal) with the sigmas a consumer terminal claims (the object
    file's defaults), whatever this simulated one actually got wrong."""
    sigma_yaw = math.radians(DEFAULT_SIGMA_YAW_DEG)
    covariance = np.diag([DEFAULT_SIGMA_XY_M**2, DEFAULT_SIGMA_XY_M**2, sigma_yaw**2])
    pallets = []
    for item in objects:
        kind = PalletKind.of_size(item.length_m, item.width_m)
        if kind is not None:
            pallets.append(Pallet(item.x_m, item.y_m, item.yaw_rad, covariance, kind, item.name))
    return PalletMap(tuple(pallets), "worker")
