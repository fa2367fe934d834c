"""Planning the forklift's way to a pallet it may not see (Kinouchi et al., 2.1 and 3).

The worker's map says where the pallet roughly is; the vehicle's own 2D scanners are
what will say exactly, but only from where they can see it. So the plan does not drive
to the pallet: it drives to a *view pose* facing one of the pallet's entry faces
squarely, the fork tips ``approach_standoff_m`` before it, from where both front
scanners have the face in their fields, and it arrives there along a final straight so
that the vehicle stands square and still when it looks. From there the approach
controller (``pallet_approach``) detects the pallet again and plans the last straight
from what it sees.

Steps (`plan_pallet_approach`):

1. **Obstacles**: every pallet of the map grown by ``position_sigmas`` σ of its position
   and a clearance (the target too: the vehicle must not touch it on the way), and any
   static obstacles (walls, posts) the caller grew the same way.
2. **Faces**: the ones the forks may enter by (a EUR pallet's two short faces, a JIS
   pallet's four), each kept only if its *corridor* is free of every other obstacle: the
   rectangle straight out of the face as wide as the vehicle plus a margin and as long
   as the standoff, the vehicle, the final straight and a turning allowance. A face
   whose view pose would not show the face to the scanners is dropped too.
3. **Path**: for each kept face, cheapest first by a lower bound (the guide point's
   shortest way around the obstacles), the search of ``pallet_search`` from the
   vehicle's pose to the final straight's start, shortened by Dubins shortcuts, then the
   straight; a face whose bound is already longer than a found path is not searched.
   Every path is checked once more with the exact outline against every obstacle.

Nothing here raises for a bad situation: no face, no path, a start inside an obstacle
are a `PlanRefusal` with the reason (and each face's own).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from appliance.guidance.arc_paths import PathPiece, sample_pieces
from appliance.guidance.pallet_geometry import (
    EntryFace,
    Obstacle,
    VehicleShape,
    entry_face,
    entry_face_indices,
    face_in_view,
    first_collision,
    overlaps,
    pallet_obstacle,
    rectangle_corners,
    view_pose,
)
from appliance.guidance.pallet_search import (
    FootprintChecker,
    GuideDistances,
    OccupancyGrid,
    SearchParams,
    search,
    shortcut,
)
from appliance.mapping.merge import MergedPallet, ReferenceArea
from appliance.mapping.pallets import Pallet
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]

# An 8-connected grid's distances exceed the straight line's by up to 1 / cos(22.5°):
# divided by it, they bound a path's length from below.
_EIGHT_CONNECTED_EXCESS = 1.0 / math.cos(math.pi / 8.0)


@dataclass(frozen=True)
class PalletPlanParams:
    approach_standoff_m: float = 1.5  # the fork tips before the face at the view pose
    final_straight_m: float = 2.0  # driven straight into the view pose
    clearance_m: float = 0.2  # around every pallet, beyond its uncertainty
    position_sigmas: float = 3.0  # a pallet grows by this many σ of its position
    # Each side of the vehicle in a face's corridor, beyond the obstacles' own growth.
    corridor_margin_m: float = 0.0
    corridor_turn_allowance_m: float = 0.5  # the corridor's length beyond the straight
    # The path's curvature stays within this fraction of the vehicle's: the rest is the
    # tracker's, to correct with while it follows.
    curvature_fraction: float = 0.6
    region_margin_m: float = 6.0  # the search stays within this of start, goal, target
    sample_m: float = 0.05  # the plan's points are this far apart
    search: SearchParams = field(default_factory=SearchParams)


@dataclass(frozen=True)
class PalletTarget:
    """The pallet to go to, as the merged map has it (its reference area when it is a
    worker's pallet the vehicle has not seen)."""

    pallet: Pallet
    reference_area: ReferenceArea | None = None

    @classmethod
    def from_merged(cls, merged: MergedPallet) -> PalletTarget:
        return cls(merged.pallet, merged.reference_area)


@dataclass(frozen=True)
class FaceVerdict:
    """What became of one entry face: ``refused`` says why it is not the plan's."""

    face: EntryFace
    refused: str = ""
    bound_m: float = math.inf  # the lower bound the faces were ranked by
    length_m: float = math.nan  # the planned path's, when one was found


@dataclass(frozen=True, eq=False)
class PalletPlan:
    """A way to a pallet's view pose, for the guide point (the unsteered front axle's
    middle, ``guide_forward_m`` ahead of the vehicle centre): points, the vehicle's
    heading at each (the path's tangent), the curvature driven there and the arc length."""

    target: Pallet
    reference_area: ReferenceArea | None
    face: EntryFace
    view_pose: Pose2D  # the vehicle centre
    guide_xy_m: FloatArray  # (N, 2)
    headings_rad: FloatArray  # (N,)
    curvature_per_m: FloatArray  # (N,)
    arc_m: FloatArray  # (N,)
    straight_start_m: float  # the arc length where the final straight begins
    guide_forward_m: float
    faces: tuple[FaceVerdict, ...]
    expansions: int

    @property
    def length_m(self) -> float:
        return float(self.arc_m[-1])

    def guide_poses(self) -> FloatArray:
        """(N, 3): x, y, heading of the guide point."""
        return np.column_stack([self.guide_xy_m, self.headings_rad])

    def centres_xy_m(self) -> FloatArray:
        """(N, 2): where the vehicle centre is at each point."""
        back = np.column_stack([np.cos(self.headings_rad), np.sin(self.headings_rad)])
        result: FloatArray = self.guide_xy_m - self.guide_forward_m * back
        return result


@dataclass(frozen=True)
class PlanRefusal:
    reason: str
    faces: tuple[FaceVerdict, ...] = ()


def _finite_pose(pose: Pose2D) -> bool:
    return all(math.isfinite(v) for v in pose)


def _shape_problem(shape: VehicleShape) -> str:
    values = (
        shape.length_m,
        shape.width_m,
        shape.front_m,
        shape.wheelbase_m,
        shape.max_steer_rad,
        shape.tips_forward_m,
        shape.forks_offset_y_m,
    )
    if not all(math.isfinite(v) for v in values):
        return "the vehicle's dimensions are not finite"
    if shape.length_m <= 0.0 or shape.width_m <= 0.0 or shape.wheelbase_m <= 0.0:
        return "the vehicle's length, width and wheelbase must be positive"
    if not 0.0 < shape.max_steer_rad < math.pi / 2.0:
        return "the vehicle's steering limit must be between 0 and 90°"
    if not 0.0 < shape.front_m <= shape.length_m + 1e-9:
        return "the vehicle's front must be within its length, ahead of the centre"
    return ""


def _same_pallet(a: Pallet, b: Pallet) -> bool:
    """``b`` is the target itself, or the map's copy of it (its centre within half the
    smaller side of the target's)."""
    return a is b or math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) < 0.5 * min(
        a.kind.length_m, a.kind.width_m
    )


def map_obstacles(
    target: Pallet,
    pallets: Sequence[Pallet],
    params: PalletPlanParams,
    static_obstacles: Sequence[Obstacle] = (),
) -> tuple[Obstacle, ...]:
    """The target and the map's other pallets, grown, and the static obstacles."""
    grow = (params.position_sigmas, params.clearance_m)
    own = pallet_obstacle(target, *grow, is_target=True)
    others = tuple(pallet_obstacle(p, *grow) for p in pallets if not _same_pallet(target, p))
    return (own, *others, *static_obstacles)


def corridor_corners(
    shape: VehicleShape, face: EntryFace, params: PalletPlanParams
) -> list[FloatArray]:
    """What the outline sweeps lining up with ``face`` and driving in: each box of it
    from where the fork tips reach the face back to the final straight's start, a
    turning allowance beyond (each box as wide as it is, plus the margin)."""
    back = params.approach_standoff_m + params.final_straight_m + params.corridor_turn_allowance_m
    frame = face.frame().compose(Pose2D(-shape.tips_forward_m, -shape.forks_offset_y_m, 0.0))
    boxes = []
    for rear, front, right, left in shape.parts_local_m():
        rear_m = rear + shape.guide_forward_m - back
        front_m = front + shape.guide_forward_m
        margin = params.corridor_margin_m
        centre = frame.compose(Pose2D(0.5 * (rear_m + front_m), 0.5 * (right + left), 0.0))
        boxes.append(
            rectangle_corners(centre, 0.5 * (front_m - rear_m), 0.5 * (left - right) + margin)
        )
    return boxes


def _corridor_blocker(boxes: Sequence[FloatArray], obstacles: Sequence[Obstacle]) -> str:
    for corners in boxes:
        for obstacle in obstacles:
            if not obstacle.is_target and overlaps(corners[None], obstacle)[0]:
                return obstacle.name
    return ""


def _region(
    start: Pose2D, goals: Sequence[Pose2D], target: Pallet, margin_m: float
) -> tuple[float, float, float, float]:
    xs = [start.x_m, target.x_m, *(g.x_m for g in goals)]
    ys = [start.y_m, target.y_m, *(g.y_m for g in goals)]
    reach = margin_m + max(target.kind.length_m, target.kind.width_m)
    return min(xs) - reach, min(ys) - reach, max(xs) + reach, max(ys) + reach


@dataclass(frozen=True)
class _Candidate:
    face: EntryFace
    view: Pose2D  # vehicle centre
    straight_start: Pose2D  # guide point


@dataclass(frozen=True, eq=False)
class _Route:
    candidate: _Candidate
    poses: FloatArray  # (N, 3) of the guide point
    curvature: FloatArray
    arc: FloatArray
    expansions: int

    @property
    def length_m(self) -> float:
        return float(self.arc[-1])


def plan_pallet_approach(
    start: Pose2D,
    target: PalletTarget,
    pallets: Sequence[Pallet],
    shape: VehicleShape,
    params: PalletPlanParams,
    static_obstacles: Sequence[Obstacle] = (),
) -> PalletPlan | PlanRefusal:
    """A forward path from the vehicle centre's ``start`` to the view pose of the
    cheapest usable entry face of ``target``; or why there is none. ``pallets`` is the
    map (the target's own entry in it is recognized and not counted twice);
    ``static_obstacles`` are already grown (``wall_obstacle``, ``disc_obstacle``)."""
    if not _finite_pose(start):
        return PlanRefusal("the vehicle's pose is not finite")
    problem = _shape_problem(shape)
    if problem:
        return PlanRefusal(problem)
    obstacles = map_obstacles(target.pallet, pallets, params, static_obstacles)
    guide_start = shape.guide_of(start)
    radius_m = shape.min_turning_radius_m / params.curvature_fraction

    verdicts: dict[int, FaceVerdict] = {}
    candidates: list[_Candidate] = []
    for index in entry_face_indices(target.pallet.kind):
        face = entry_face(target.pallet, index)
        blocker = _corridor_blocker(corridor_corners(shape, face, params), obstacles)
        if blocker:
            verdicts[index] = FaceVerdict(face, f"its corridor is blocked by {blocker}")
            continue
        view = view_pose(shape, face, params.approach_standoff_m)
        unseen = face_in_view(shape, view, face)
        if unseen:
            verdicts[index] = FaceVerdict(face, f"from its view pose {unseen}")
            continue
        view_guide = shape.guide_of(view)
        straight_start = view_guide.compose(Pose2D(-params.final_straight_m, 0.0, 0.0))
        candidates.append(_Candidate(face, view, straight_start))
    if not candidates:
        return _refusal("no entry face is free", verdicts)

    region = _region(start, [c.view for c in candidates], target.pallet, params.region_margin_m)
    grid = OccupancyGrid(obstacles, region, params.search.grid_resolution_m)
    checker = FootprintChecker(shape, grid, params.search.footprint_sample_m)
    guide = GuideDistances(grid, 0.5 * shape.width_m, params.search.heuristic_cell_m)
    from_start = guide.field_from(guide_start.x_m, guide_start.y_m)
    bounds = {
        c.face.index: guide.distance_m(from_start, c.straight_start.x_m, c.straight_start.y_m)
        / _EIGHT_CONNECTED_EXCESS
        + params.final_straight_m
        for c in candidates
    }
    candidates.sort(key=lambda c: bounds[c.face.index])

    best: _Route | None = None
    for candidate in candidates:
        index = candidate.face.index
        bound = bounds[index]
        if best is not None and bound >= best.length_m:
            verdicts[index] = FaceVerdict(
                candidate.face,
                f"its bound is longer than face {best.candidate.face.index}'s path",
                bound,
            )
            continue
        route = _route_to(
            candidate, guide_start, radius_m, shape, params, obstacles, checker, guide
        )
        if isinstance(route, str):
            verdicts[index] = FaceVerdict(candidate.face, route, bound)
            continue
        verdicts[index] = FaceVerdict(candidate.face, "", bound, route.length_m)
        if best is None or route.length_m < best.length_m:
            best = route
    if best is None:
        return _refusal("no path to any free entry face", verdicts)
    chosen = best.candidate.face.index
    for index, verdict in verdicts.items():
        if index != chosen and not verdict.refused:
            verdicts[index] = FaceVerdict(
                verdict.face,
                f"its path is longer than face {chosen}'s",
                verdict.bound_m,
                verdict.length_m,
            )
    return PalletPlan(
        target=target.pallet,
        reference_area=target.reference_area,
        face=best.candidate.face,
        view_pose=best.candidate.view,
        guide_xy_m=best.poses[:, :2],
        headings_rad=best.poses[:, 2],
        curvature_per_m=best.curvature,
        arc_m=best.arc,
        straight_start_m=best.length_m - params.final_straight_m,
        guide_forward_m=shape.guide_forward_m,
        faces=tuple(verdicts[i] for i in sorted(verdicts)),
        expansions=best.expansions,
    )


def _refusal(reason: str, verdicts: dict[int, FaceVerdict]) -> PlanRefusal:
    faces = tuple(verdicts[i] for i in sorted(verdicts))
    details = "; ".join(f"face {v.face.index}: {v.refused}" for v in faces)
    return PlanRefusal(f"{reason} ({details})" if details else reason, faces)


def _route_to(
    candidate: _Candidate,
    guide_start: Pose2D,
    radius_m: float,
    shape: VehicleShape,
    params: PalletPlanParams,
    obstacles: Sequence[Obstacle],
    checker: FootprintChecker,
    guide: GuideDistances,
) -> _Route | str:
    straight = PathPiece(0.0, params.final_straight_m)
    straight_poses, _, _ = sample_pieces(candidate.straight_start, (straight,), params.sample_m)
    hit = first_collision(shape, straight_poses, obstacles)
    if hit is not None:
        return f"its final straight overlaps {hit[1]}"
    found = search(guide_start, candidate.straight_start, radius_m, checker, guide, params.search)
    if isinstance(found, str):
        return found
    pieces = shortcut(guide_start, found.pieces, radius_m, checker, params.search)
    poses, curvature, arc = sample_pieces(guide_start, (*pieces, straight), params.sample_m)
    hit = first_collision(shape, poses, obstacles)
    if hit is not None:
        return f"the path found overlaps {hit[1]} at {arc[hit[0]]:.1f} m (exact check)"
    for array in (poses, curvature, arc):
        array.flags.writeable = False
    return _Route(candidate, poses, curvature, arc, found.expansions)
