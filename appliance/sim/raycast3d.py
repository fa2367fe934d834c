"""The site in 3D, and nearest-hit ray casting against it, for the worker's 3D terminal.

The vehicle's scanners see a slice of the site (``raycast``); the worker's handheld
LiDAR terminal (Kinouchi et al., Section 2.1) sees it whole: the floor, the pallets'
tops and the cargo on them, which the scan plane never shows. So a `Site` is lifted
into a few kinds of upright solids, each a row of an array the caster takes at once:

- the floor, the plane z = 0 (unbounded: the yard's walls stop the rays);
- boxes that may turn about z: each `SitePallet` as a plain solid box of its footprint
  and height (or, with ``WorldParams.pallet_runners``, a 22 mm top deck on three
  100 mm runners along its length, the fork pockets open), its cargo as a box of the
  same footprint from the pallet's top up by ``cargo_height_m`` when that is > 0;
- walls: every static segment that is not a pallet's side (its name does not start with
  a pallet's name and a dot) as a vertical rectangle of no thickness from the floor up;
- vertical cylinders: the posts (static circles) and, at a given instant, the walkers.

Each ray gets the nearest hit over all of them: one (rays x solids) array computation
per kind, chunked over rays so that a scan of 100k rays never holds more than a few MB
of temporaries, and solids farther than the maximum range culled first (a 30 m yard
has most of its walls out of a 5 m terminal's reach).

Conventions (as ``raycast``'s, for the same reasons): a ray that meets nothing within
the maximum range has no hit; a ray grazing a wall edge-on does not hit it; an origin
inside (or on) a solid, or at or below the floor, is blinded: no ray hits anything,
since a device inside an object sees nothing of the site.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from appliance.sim.site import Site, SitePallet

FloatArray = NDArray[np.float64]

NO_HIT = -1
FLOOR_INDEX = 0  # what ``surface_index`` says for the floor; the solids follow
FLOOR_NAME = "floor"
PALLET_DECK_M = 0.022  # ISO 6780 block pallets: 22 mm top deck boards
PALLET_RUNNER_WIDTH_M = 0.100  # a runner (or a row of blocks) 100 mm wide
_CHUNK_ELEMENTS = 1 << 17  # rays x solids per chunk: 1 MB per temporary array
_PARALLEL_EPS = 1e-12  # |d x e| below which a ray counts as parallel to a wall
_MIN_RANGE_M = 1e-9  # a hit at the origin itself is no echo


@dataclass(frozen=True)
class WorldParams:
    """What a site's 2D shapes become in 3D. None of it is in the paper: plausible
    heights of a storage area's walls, posts and people."""

    wall_height_m: float = 2.5
    post_height_m: float = 2.0
    walker_height_m: float = 1.7
    # A pallet as deck on runners rather than a solid block; the 2D sites ignore the fork
    # pockets, and a plain box is what the vehicle's scan plane sees as the outline.
    pallet_runners: bool = False

    def __post_init__(self) -> None:
        if not (self.wall_height_m > 0 and self.post_height_m > 0 and self.walker_height_m > 0):
            raise ValueError("wall, post and walker heights must be > 0")


DEFAULT_WORLD = WorldParams()


@dataclass(frozen=True, eq=False)
class World3D:
    """A site as upright solids, in the array form the caster takes (metres, radians).

    ``surface_index`` values of a cast point into ``names``: 0 the floor, then the
    boxes, the walls and the cylinders in their rows' order. Walkers are appended to the
    cylinders (`with_walkers`), so the floor's, boxes' and walls' indices never change
    with time.
    """

    boxes: FloatArray  # (B, 7): centre x, centre y, yaw, half length, half width, z0, z1
    walls: FloatArray  # (W, 6): x0, y0, x1, y1, z0, z1
    cylinders: FloatArray  # (C, 5): centre x, centre y, radius, z0, z1
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        expected = 1 + len(self.boxes) + len(self.walls) + len(self.cylinders)
        if len(self.names) != expected:
            raise ValueError(f"{len(self.names)} names for {expected} surfaces")
        for rows in (self.boxes, self.walls, self.cylinders):
            rows.flags.writeable = False  # shared between the worlds of several instants

    @property
    def first_wall(self) -> int:
        return 1 + int(self.boxes.shape[0])

    @property
    def first_cylinder(self) -> int:
        return self.first_wall + int(self.walls.shape[0])


def pallet_boxes(pallet: SitePallet, runners: bool = False) -> list[tuple[str, list[float]]]:
    """The boxes a pallet and its cargo are made of: (name, box row) pairs."""
    x, y, yaw = pallet.pose
    hl, hw = pallet.length_m / 2.0, pallet.width_m / 2.0
    top_m = pallet.height_m
    boxes: list[tuple[str, list[float]]] = []
    if runners and pallet.height_m > PALLET_DECK_M and pallet.width_m > 3 * PALLET_RUNNER_WIDTH_M:
        deck_m = top_m - PALLET_DECK_M
        boxes.append((f"{pallet.name}.deck", [x, y, yaw, hl, hw, deck_m, top_m]))
        half_runner = PALLET_RUNNER_WIDTH_M / 2.0
        c, s = np.cos(yaw), np.sin(yaw)
        for i, lateral in enumerate((hw - half_runner, 0.0, -(hw - half_runner))):
            cx, cy = x - s * lateral, y + c * lateral
            boxes.append((f"{pallet.name}.runner{i}", [cx, cy, yaw, hl, half_runner, 0.0, deck_m]))
    else:
        boxes.append((pallet.name, [x, y, yaw, hl, hw, 0.0, top_m]))
    if pallet.cargo_height_m > 0.0:
        cargo = [x, y, yaw, hl, hw, top_m, top_m + pallet.cargo_height_m]
        boxes.append((f"{pallet.name}.cargo", cargo))
    return boxes


def site_world(site: Site, params: WorldParams = DEFAULT_WORLD) -> World3D:
    """The static part of ``site`` in 3D (no walkers: add them with `with_walkers`)."""
    boxes = [box for pallet in site.pallets for box in pallet_boxes(pallet, params.pallet_runners)]
    prefixes = tuple(f"{pallet.name}." for pallet in site.pallets)
    walls = [s for s in site.segments if not (prefixes and s.name.startswith(prefixes))]
    return World3D(
        np.array([row for _, row in boxes], dtype=np.float64).reshape(-1, 7),
        np.array(
            [(s.x0_m, s.y0_m, s.x1_m, s.y1_m, 0.0, params.wall_height_m) for s in walls],
            dtype=np.float64,
        ).reshape(-1, 6),
        np.array(
            [(c.cx_m, c.cy_m, c.radius_m, 0.0, params.post_height_m) for c in site.circles],
            dtype=np.float64,
        ).reshape(-1, 5),
        (
            FLOOR_NAME,
            *(name for name, _ in boxes),
            *(s.name for s in walls),
            *(c.name for c in site.circles),
        ),
    )


def with_walkers(
    world: World3D, site: Site, t_s: float, params: WorldParams = DEFAULT_WORLD
) -> World3D:
    """``world`` with ``site``'s walkers where they are at ``t_s``, as cylinders."""
    if not site.movers:
        return world
    people = [m.circle_at(t_s) for m in site.movers]
    rows = np.array([(c.cx_m, c.cy_m, c.radius_m, 0.0, params.walker_height_m) for c in people])
    return World3D(
        world.boxes,
        world.walls,
        np.concatenate([world.cylinders, rows]),
        world.names + tuple(c.name for c in people),
    )


def grid_directions(azimuths_rad: FloatArray, elevations_rad: FloatArray) -> FloatArray:
    """(azimuths x elevations, 3) unit vectors, azimuth-major (a scanner's columns)."""
    az, el = np.meshgrid(azimuths_rad, elevations_rad, indexing="ij")
    cos_el = np.cos(el).ravel()
    return np.column_stack(
        [cos_el * np.cos(az).ravel(), cos_el * np.sin(az).ravel(), np.sin(el).ravel()]
    )


class Hits3D(NamedTuple):
    """Per ray: distance to the nearest hit (inf: none) and what it hit (`NO_HIT`: none)."""

    range_m: FloatArray
    surface_index: NDArray[np.int64]


def inside_solid(world: World3D, origin_m: FloatArray) -> bool:
    """Whether a point is at or below the floor or inside (or on) a solid: blinded."""
    ox, oy, oz = (float(v) for v in origin_m)
    if oz <= 0.0:
        return True
    b = world.boxes
    rx, ry = ox - b[:, 0], oy - b[:, 1]
    c, s = np.cos(b[:, 2]), np.sin(b[:, 2])
    in_box = (
        (np.abs(c * rx + s * ry) <= b[:, 3])
        & (np.abs(-s * rx + c * ry) <= b[:, 4])
        & (b[:, 5] <= oz)
        & (oz <= b[:, 6])
    )
    cy = world.cylinders
    in_cylinder = (
        (np.hypot(ox - cy[:, 0], oy - cy[:, 1]) <= cy[:, 2]) & (cy[:, 3] <= oz) & (oz <= cy[:, 4])
    )
    return bool(in_box.any() or in_cylinder.any())


def cast_rays_3d(
    world: World3D, origin_m: FloatArray, directions: FloatArray, max_range_m: float
) -> Hits3D:
    """The nearest hit of each ray from ``origin_m`` (x, y, z) along unit ``directions``
    (R, 3), site frame, within ``max_range_m``; all misses from a blinded origin."""
    origin = np.asarray(origin_m, dtype=np.float64).reshape(3)
    rays = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    range_m = np.full(rays.shape[0], np.inf)
    index = np.full(rays.shape[0], NO_HIT, dtype=np.int64)
    if rays.shape[0] == 0 or not np.isfinite(origin).all() or inside_solid(world, origin):
        return Hits3D(range_m, index)
    boxes, box_ids = _box_candidates(world, origin, max_range_m)
    walls, wall_ids = _wall_candidates(world, origin, max_range_m)
    cylinders, cylinder_ids = _cylinder_candidates(world, origin, max_range_m)
    widest = max(boxes.shape[0], walls.shape[0], cylinders.shape[0], 1)
    step = max(1, _CHUNK_ELEMENTS // widest)
    kinds = (
        (_box_t, boxes, box_ids),
        (_wall_t, walls, wall_ids),
        (_cylinder_t, cylinders, cylinder_ids),
    )
    for start in range(0, rays.shape[0], step):
        chunk = slice(start, start + step)
        d = rays[chunk]
        # Rays parallel to a face or a wall divide by zero or overflow into +-inf or nan;
        # every test on them is a comparison that inf decides and nan fails, as intended.
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            best = _floor_t(origin, d)
            best_index = np.where(np.isfinite(best), FLOOR_INDEX, NO_HIT)
            for distances, solids, ids in kinds:
                if ids.size == 0:
                    continue
                t = distances(origin, d, solids)
                nearest = np.argmin(t, axis=1)
                nearest_t = np.take_along_axis(t, nearest[:, None], axis=1)[:, 0]
                closer = nearest_t < best
                best = np.where(closer, nearest_t, best)
                best_index = np.where(closer, ids[nearest], best_index)
        within = best <= max_range_m
        range_m[chunk] = np.where(within, best, np.inf)
        index[chunk] = np.where(within, best_index, NO_HIT)
    return Hits3D(range_m, index)


def _box_candidates(
    world: World3D, origin: FloatArray, max_range_m: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    """The boxes whose bounding circle and height come within range of the origin."""
    b = world.boxes
    radius = np.hypot(b[:, 3], b[:, 4])
    horizontal = np.maximum(np.hypot(b[:, 0] - origin[0], b[:, 1] - origin[1]) - radius, 0.0)
    vertical = np.maximum(np.maximum(b[:, 5] - origin[2], origin[2] - b[:, 6]), 0.0)
    keep = np.flatnonzero(np.hypot(horizontal, vertical) <= max_range_m)
    return b[keep], keep.astype(np.int64) + 1


def _wall_candidates(
    world: World3D, origin: FloatArray, max_range_m: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    w = world.walls
    x0, y0, x1, y1 = w[:, 0], w[:, 1], w[:, 2], w[:, 3]
    ex, ey = x1 - x0, y1 - y0
    length_sq = ex * ex + ey * ey
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(
            length_sq > 0.0, ((origin[0] - x0) * ex + (origin[1] - y0) * ey) / length_sq, 0
        )
    s = np.clip(s, 0.0, 1.0)
    horizontal = np.hypot(x0 + s * ex - origin[0], y0 + s * ey - origin[1])
    keep = np.flatnonzero(horizontal <= max_range_m)
    return w[keep], keep.astype(np.int64) + world.first_wall


def _cylinder_candidates(
    world: World3D, origin: FloatArray, max_range_m: float
) -> tuple[FloatArray, NDArray[np.int64]]:
    c = world.cylinders
    horizontal = np.hypot(c[:, 0] - origin[0], c[:, 1] - origin[1]) - c[:, 2]
    keep = np.flatnonzero(horizontal <= max_range_m)
    return c[keep], keep.astype(np.int64) + world.first_cylinder


def _floor_t(origin: FloatArray, d: FloatArray) -> FloatArray:
    """Distance to the floor along each ray (inf for rays level or rising)."""
    t: FloatArray = np.where(d[:, 2] < 0.0, -origin[2] / d[:, 2], np.inf)
    return t


def _box_t(origin: FloatArray, d: FloatArray, boxes: FloatArray) -> FloatArray:
    """(rays, boxes) entry distances by the slab method in each box's own frame (inf:
    a miss). An axis the ray is parallel to gives +-inf bounds, or nan exactly on a
    face; fmin/fmax drop the nan, so such a grazing ray may go either way."""
    c, s = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    rx, ry = origin[0] - boxes[:, 0], origin[1] - boxes[:, 1]
    local_ox, local_oy = c * rx + s * ry, -s * rx + c * ry
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    local_dx = dx * c + dy * s
    local_dy = dy * c - dx * s
    z_mid, z_half = (boxes[:, 5] + boxes[:, 6]) / 2.0, (boxes[:, 6] - boxes[:, 5]) / 2.0
    near, far = _slab(local_ox, local_dx, boxes[:, 3])
    for o, direction, half in (
        (local_oy, local_dy, boxes[:, 4]),
        (origin[2] - z_mid, dz, z_half),
    ):
        slab_near, slab_far = _slab(o, direction, half)
        near = np.fmax(near, slab_near)
        far = np.fmin(far, slab_far)
    hit = (near <= far) & (near > _MIN_RANGE_M)
    return np.where(hit, near, np.inf)


def _slab(
    origin: FloatArray, direction: FloatArray, half: FloatArray
) -> tuple[FloatArray, FloatArray]:
    inverse = 1.0 / direction
    a = (-half - origin) * inverse
    b = (half - origin) * inverse
    return np.fmin(a, b), np.fmax(a, b)


def _wall_t(origin: FloatArray, d: FloatArray, walls: FloatArray) -> FloatArray:
    """(rays, walls) hit distances: origin + t d = p0 + s e in the plan, t = (w x e) /
    (d x e), s = (w x d) / (d x e), w = p0 - origin; d is the unit 3D direction, so t
    is the 3D distance, and the hit's height must be within the wall's."""
    wx, wy = walls[:, 0] - origin[0], walls[:, 1] - origin[1]
    ex, ey = walls[:, 2] - walls[:, 0], walls[:, 3] - walls[:, 1]
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    denominator = dx * ey - dy * ex
    inverse = 1.0 / denominator
    t = (wx * ey - wy * ex) * inverse
    s = (wx * dy - wy * dx) * inverse
    z = origin[2] + t * dz
    hit = (
        (np.abs(denominator) > _PARALLEL_EPS)
        & (t > _MIN_RANGE_M)
        & (s >= 0.0)
        & (s <= 1.0)
        & (z >= walls[:, 4])
        & (z <= walls[:, 5])
    )
    return np.where(hit, t, np.inf)


def _cylinder_t(origin: FloatArray, d: FloatArray, cylinders: FloatArray) -> FloatArray:
    """(rays, cylinders) entry distances: the nearer root of |m + t d_xy|^2 = r^2 on the
    side (m = origin - centre, plan only) if its height is within the cylinder's, else
    the top or bottom disc; the origin is outside every cylinder (blinded otherwise)."""
    mx, my = origin[0] - cylinders[:, 0], origin[1] - cylinders[:, 1]
    r_sq = cylinders[:, 2] ** 2
    dx, dy, dz = d[:, 0:1], d[:, 1:2], d[:, 2:3]
    a = dx * dx + dy * dy
    half_b = dx * mx + dy * my
    t = (-half_b - np.sqrt(half_b * half_b - a * (mx * mx + my * my - r_sq))) / a
    z = origin[2] + t * dz
    side = (t > _MIN_RANGE_M) & (z >= cylinders[:, 3]) & (z <= cylinders[:, 4])
    best = np.where(side, t, np.inf)
    for cap_z in (cylinders[:, 4], cylinders[:, 3]):
        t_cap = (cap_z - origin[2]) / dz
        px, py = mx + t_cap * dx, my + t_cap * dy
        on_cap = (t_cap > _MIN_RANGE_M) & (px * px + py * py <= r_sq)
        best = np.where(on_cap & (t_cap < best), t_cap, best)
    return best
