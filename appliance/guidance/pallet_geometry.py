"""The shapes the pallet planner works with: obstacles, the vehicle's footprint, a
pallet's entry faces, what the scanners see; and the exact overlap test between them.

**Obstacles** are convex polygons in the site frame: a pallet's footprint grown by how
unsure its position is (``k`` standard deviations along the covariance's worst axis,
as the merge's reference area is) and by a clearance, a wall segment thickened by the
clearance, a post as the octagon around its circle. Growing the obstacles rather than
the vehicle keeps the footprint the vehicle's own, so the same footprint is checked
against every obstacle and the margin is where the uncertainty is.

**The footprint** is the vehicle's outline, forks included: ``front_m`` ahead of the
vehicle centre (midway between the axles) and ``length_m - front_m`` behind it. Paths
are planned for the *guide point*, the middle of the unsteered front axle, half a
wheelbase ahead of the centre: with the rear axle steering, it is the point that moves
along the vehicle's heading (no sideslip), so a path's tangent *is* the vehicle's
heading there and the footprint at each point of a path follows from the point alone.

**Overlap** is the separating-axis test of two convex polygons (they overlap unless
some edge normal of one separates their projections), vectorized over many footprint
poses at once: exact, so it is the check every plan passes last whatever the search
used to find it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from appliance.mapping.pallets import Pallet, PalletKind
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

# LMS111: 270° aperture, 20 m range on a 10 % target (the data sheet's figure).
DEFAULT_SCANNER_HALF_ANGLE_RAD = math.radians(135.0)
DEFAULT_SCANNER_RANGE_M = 20.0


@dataclass(frozen=True, eq=False)
class Obstacle:
    """A convex polygon (counter-clockwise, at least 3 corners) the vehicle must not touch."""

    name: str
    corners_xy_m: FloatArray  # (k, 2)
    is_target: bool = False

    def __post_init__(self) -> None:
        corners = np.array(self.corners_xy_m, dtype=np.float64).reshape(-1, 2)
        corners.flags.writeable = False
        object.__setattr__(self, "corners_xy_m", corners)


def rectangle_corners(pose: Pose2D, half_length_m: float, half_width_m: float) -> FloatArray:
    """Corners of a rectangle centred on ``pose``, counter-clockwise from front-left."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    local = np.array(
        [
            [half_length_m, half_width_m],
            [-half_length_m, half_width_m],
            [-half_length_m, -half_width_m],
            [half_length_m, -half_width_m],
        ]
    )
    return np.column_stack(
        [pose.x_m + c * local[:, 0] - s * local[:, 1], pose.y_m + s * local[:, 0] + c * local[:, 1]]
    )


def position_sigma_m(covariance: FloatArray) -> float:
    """σ along the worst axis of a 3x3 (x, y, yaw) covariance's position block."""
    a, b, c = float(covariance[0, 0]), float(covariance[0, 1]), float(covariance[1, 1])
    worst = 0.5 * (a + c) + math.sqrt(0.25 * (a - c) ** 2 + b * b)
    return math.sqrt(worst) if math.isfinite(worst) and worst > 0.0 else 0.0


def pallet_obstacle(
    pallet: Pallet, sigmas: float, clearance_m: float, is_target: bool = False
) -> Obstacle:
    """The pallet's footprint grown on every side by ``sigmas`` σ of its position and
    ``clearance_m`` (its yaw's uncertainty is left to the clearance: a degree turns a
    pallet's corner by a centimetre)."""
    grow = sigmas * position_sigma_m(pallet.covariance) + clearance_m
    corners = rectangle_corners(
        pallet.pose, pallet.kind.length_m / 2.0 + grow, pallet.kind.width_m / 2.0 + grow
    )
    return Obstacle(pallet.name or "pallet", corners, is_target)


def wall_obstacle(
    x0_m: float, y0_m: float, x1_m: float, y1_m: float, clearance_m: float, name: str = "wall"
) -> Obstacle:
    """A wall segment as the rectangle ``clearance_m`` around it (ends included)."""
    length = math.hypot(x1_m - x0_m, y1_m - y0_m)
    yaw = math.atan2(y1_m - y0_m, x1_m - x0_m) if length > 0.0 else 0.0
    centre = Pose2D(0.5 * (x0_m + x1_m), 0.5 * (y0_m + y1_m), yaw)
    half = max(clearance_m, 1e-3)
    return Obstacle(name, rectangle_corners(centre, 0.5 * length + half, half))


def disc_obstacle(
    x_m: float, y_m: float, radius_m: float, clearance_m: float, name: str = "post"
) -> Obstacle:
    """A post: the regular octagon around its circle grown by ``clearance_m``."""
    outer = (radius_m + clearance_m) / math.cos(math.pi / 8.0)
    angles = np.arange(8) * (math.pi / 4.0) + math.pi / 8.0
    return Obstacle(
        name, np.column_stack([x_m + outer * np.cos(angles), y_m + outer * np.sin(angles)])
    )


@dataclass(frozen=True)
class ScannerField:
    """One scanner's field in the vehicle frame: its mount, half its aperture, its range."""

    mount: Pose2D
    half_angle_rad: float = DEFAULT_SCANNER_HALF_ANGLE_RAD
    range_m: float = DEFAULT_SCANNER_RANGE_M

    def sees(self, vehicle: Pose2D, x_m: float, y_m: float) -> bool:
        """Whether the site point (x, y) lies inside this field with the vehicle at ``vehicle``."""
        sensor = vehicle.compose(self.mount)
        dx, dy = x_m - sensor.x_m, y_m - sensor.y_m
        bearing = math.remainder(math.atan2(dy, dx) - sensor.yaw_rad, math.tau)
        return math.hypot(dx, dy) <= self.range_m and abs(bearing) <= self.half_angle_rad


@dataclass(frozen=True)
class VehicleShape:
    """The vehicle as the planner sees it (the vehicle file's geometry, forks, limits).

    The outline is one rectangle (``length_m`` x ``width_m``, its front ``front_m``
    ahead of the centre), or, with ``forks_width_m`` > 0, two: the body up to the
    forks' heel at ``heel_forward_m``, and the forks from there to the front, only as
    wide as they are. The narrower forks matter at a pallet in a row: they go between
    the neighbours where the body, a metre back, never does.
    """

    length_m: float  # overall, forks included
    width_m: float
    front_m: float  # from the vehicle centre to the front of the outline (the fork tips)
    wheelbase_m: float
    max_steer_rad: float  # the effective steering angle's limit
    tips_forward_m: float  # from the vehicle centre to the fork tips
    forks_offset_y_m: float = 0.0  # the forks' centre line, left of the vehicle's axis
    scanners: tuple[ScannerField, ...] = field(default=())
    heel_forward_m: float = 0.0  # the forks' heel ahead of the centre (with forks_width_m)
    forks_width_m: float = 0.0  # across both forks' outer edges; 0: the outline is one box

    @property
    def guide_forward_m(self) -> float:
        """The guide point (the unsteered front axle's middle) ahead of the centre."""
        return 0.5 * self.wheelbase_m

    @property
    def min_turning_radius_m(self) -> float:
        """Of the guide point, at full lock: ``L / tan(max steer)``."""
        return self.wheelbase_m / math.tan(self.max_steer_rad)

    def parts_local_m(self) -> tuple[tuple[float, float, float, float], ...]:
        """The outline's boxes in the guide point's frame: (rear x, front x, right y,
        left y) each."""
        g = self.guide_forward_m
        front = self.front_m - g
        rear = front - self.length_m
        half = 0.5 * self.width_m
        heel = self.heel_forward_m - g
        if self.forks_width_m <= 0.0 or not rear < heel < front:
            return ((rear, front, -half, half),)
        forks = 0.5 * self.forks_width_m
        offset = self.forks_offset_y_m
        return ((rear, heel, -half, half), (heel, front, offset - forks, offset + forks))

    def centre_of(self, guide: Pose2D) -> Pose2D:
        return guide.compose(Pose2D(-self.guide_forward_m, 0.0, 0.0))

    def guide_of(self, centre: Pose2D) -> Pose2D:
        return centre.compose(Pose2D(self.guide_forward_m, 0.0, 0.0))


def box_corners(box: tuple[float, float, float, float], guide_poses: FloatArray) -> FloatArray:
    """(N, 4, 2) corners of one box of the outline at each guide pose (x, y, heading)."""
    rear, front, right, left = box
    local = np.array([[front, left], [rear, left], [rear, right], [front, right]])
    c, s = np.cos(guide_poses[:, 2])[:, None], np.sin(guide_poses[:, 2])[:, None]
    x = guide_poses[:, 0:1] + c * local[None, :, 0] - s * local[None, :, 1]
    y = guide_poses[:, 1:2] + s * local[None, :, 0] + c * local[None, :, 1]
    return np.stack([x, y], axis=-1)


def footprint_corners(shape: VehicleShape, guide_poses: FloatArray) -> list[FloatArray]:
    """Each box of the outline, (N, 4, 2), at each of the (N, 3) guide poses."""
    return [box_corners(box, guide_poses) for box in shape.parts_local_m()]


def _edge_normals(corners: FloatArray) -> FloatArray:
    edges = np.roll(corners, -1, axis=-2) - corners
    return np.stack([edges[..., 1], -edges[..., 0]], axis=-1)


def overlaps(polygons: FloatArray, obstacle: Obstacle) -> BoolArray:
    """Which of the (N, k, 2) convex polygons overlap ``obstacle`` (touching counts as
    apart): the separating-axis test over both polygons' edge normals."""
    others = obstacle.corners_xy_m
    hit = np.ones(polygons.shape[0], dtype=bool)
    # The obstacle's axes: fixed; the polygons': one set per polygon.
    for axis in _edge_normals(others):
        own = polygons @ axis
        theirs = others @ axis
        hit &= (own.max(axis=1) > theirs.min()) & (own.min(axis=1) < theirs.max())
    axes = _edge_normals(polygons)  # (N, k, 2)
    for j in range(axes.shape[1]):
        axis = axes[:, j, :]
        own = np.einsum("nkd,nd->nk", polygons, axis)
        theirs = others @ axis.T  # (m, N)
        hit &= (own.max(axis=1) > theirs.min(axis=0)) & (own.min(axis=1) < theirs.max(axis=0))
    return hit


def first_collision(
    shape: VehicleShape, guide_poses: FloatArray, obstacles: Sequence[Obstacle]
) -> tuple[int, str] | None:
    """The first guide pose (index, obstacle's name) whose outline overlaps an obstacle;
    None when all are clear."""
    if guide_poses.shape[0] == 0:
        return None
    first: tuple[int, str] | None = None
    for corners in footprint_corners(shape, guide_poses):
        for obstacle in obstacles:
            hits = np.flatnonzero(overlaps(corners, obstacle))
            if hits.size and (first is None or int(hits[0]) < first[0]):
                first = (int(hits[0]), obstacle.name)
    return first


@dataclass(frozen=True)
class EntryFace:
    """One side of a pallet the forks may enter by.

    ``index`` counts the sides counter-clockwise from the one the pallet's yaw points at
    (0: +length, 1: +width, 2: -length, 3: -width); ``entry_yaw_rad`` is the direction
    the forks move in to enter (into the pallet, against the side's outward normal).
    """

    index: int
    entry_yaw_rad: float
    centre_x_m: float
    centre_y_m: float
    half_span_m: float  # half the face's width
    depth_m: float  # from the face to the pallet's centre

    def frame(self) -> Pose2D:
        """The face's frame: origin at its centre, x into the pallet, y to the left."""
        return Pose2D(self.centre_x_m, self.centre_y_m, self.entry_yaw_rad)

    def ends_xy_m(self) -> tuple[tuple[float, float], tuple[float, float]]:
        frame = self.frame()
        return frame.apply(0.0, self.half_span_m), frame.apply(0.0, -self.half_span_m)


def entry_face_indices(kind: PalletKind) -> tuple[int, ...]:
    """A EUR pallet is entered by its short faces (the forks along its length); a square
    (JIS) pallet by any of its four."""
    return (0, 1, 2, 3) if kind.length_m == kind.width_m else (0, 2)


def entry_face(pallet: Pallet, index: int) -> EntryFace:
    outward = pallet.yaw_rad + index * math.pi / 2.0
    depth = (pallet.kind.length_m if index % 2 == 0 else pallet.kind.width_m) / 2.0
    span = (pallet.kind.width_m if index % 2 == 0 else pallet.kind.length_m) / 2.0
    return EntryFace(
        index,
        math.remainder(outward + math.pi, math.tau),
        pallet.x_m + depth * math.cos(outward),
        pallet.y_m + depth * math.sin(outward),
        span,
        depth,
    )


def nearest_entry_face(pallet: Pallet, entry_yaw_rad: float) -> EntryFace:
    """The allowed face whose entry direction is nearest ``entry_yaw_rad``: which face of a
    re-detected pallet (its yaw known only up to its symmetry) the plan's face is."""
    faces = [entry_face(pallet, i) for i in entry_face_indices(pallet.kind)]
    return min(faces, key=lambda f: abs(math.remainder(f.entry_yaw_rad - entry_yaw_rad, math.tau)))


def view_pose(shape: VehicleShape, face: EntryFace, standoff_m: float) -> Pose2D:
    """The vehicle centre facing ``face`` squarely with the fork tips ``standoff_m`` before
    it (the forks' centre line on the face's centre line)."""
    return face.frame().compose(
        Pose2D(-standoff_m - shape.tips_forward_m, -shape.forks_offset_y_m, 0.0)
    )


def face_in_view(shape: VehicleShape, vehicle: Pose2D, face: EntryFace) -> str:
    """Why the scanners would not see ``face`` from ``vehicle`` ("" when every scanner
    has both its ends in its field, on the face's outer side)."""
    frame = face.frame()
    for number, scanner in enumerate(shape.scanners):
        sensor = vehicle.compose(scanner.mount)
        along = (sensor.x_m - frame.x_m) * math.cos(frame.yaw_rad) + (
            sensor.y_m - frame.y_m
        ) * math.sin(frame.yaw_rad)
        if along >= 0.0:
            return f"scanner {number} is not in front of the face"
        for x, y in face.ends_xy_m():
            if not scanner.sees(vehicle, x, y):
                return f"scanner {number} does not see the face's end ({x:.2f}, {y:.2f})"
    return ""
