"""The search behind the pallet planner: a forward path of arcs for the whole footprint.

Hybrid A* (Dolgov et al., 2008), forward only: from a pose, drive one of a few arcs
(straight, half and full planning curvature either way) for ``step_m``; keep the
successor if the vehicle's outline stays clear along it; remember the best cost per
cell of (x, y, heading); and every few expansions try the shortest Dubins path from the
node to the goal, which ends the search when it is clear. The cost is the length, a
little more on arcs and for changing curvature (a path that weaves is not shorter but
is harder to follow). The heuristic is the larger of the Dubins length (right in open
space, blind to obstacles) and the length of the shortest way for the guide point
around the obstacles grown by half the vehicle's width (right in a maze, blind to
turning): each is short of the true cost in its own way, the larger is the better.

Why not a grid path smoothed afterwards: this vehicle steers its rear axle, so in a
turn its tail swings *out* by ``sqrt(R² + d²) - R`` (d: the tail behind the front
axle; over a metre at full lock). A path found for a disc and then given fillets has
to be checked again and has no way to repair itself; the search checks the outline as
it goes, so what it finds is drivable and clear by construction (and checked once more
exactly by the planner). After the search, the chain of arcs is shortened by greedy
Dubins shortcuts between its nodes, each kept only when clear.

The outline is checked against an occupancy grid of the (already grown) obstacles,
dilated by one cell so that a sample point anywhere in a cell is judged by the cell's
worst; the outline is sampled every ``footprint_sample_m`` (edges and inside), finer
than the narrowest dilated obstacle, so nothing fits between the samples.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from appliance.guidance.arc_paths import (
    PathPiece,
    dubins_paths,
    pose_after,
    sample_piece,
    sample_pieces,
)
from appliance.guidance.pallet_geometry import Obstacle, VehicleShape
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class SearchParams:
    grid_resolution_m: float = 0.05
    footprint_sample_m: float = 0.1
    cell_m: float = 0.25  # the search's (x, y) cells
    heading_bins: int = 72  # 5° each
    step_m: float = 0.5  # one arc; longer than a cell's diagonal, so it leaves the cell
    sample_m: float = 0.1  # the outline is checked this often along a path
    max_expansions: int = 20000
    shot_every: int = 4  # try a Dubins path to the goal every this many expansions
    arc_penalty: float = 0.05  # extra cost per metre on an arc, as a fraction
    switch_penalty_m: float = 0.1  # extra cost per change of curvature
    heuristic_weight: float = 1.5  # > 1: faster, a little longer (shortcuts win it back)
    heuristic_cell_m: float = 0.2
    max_shortcut_tries: int = 400


class OccupancyGrid:
    """The obstacles on a grid over ``bounds``; outside it, everything is blocked."""

    def __init__(
        self,
        obstacles: Sequence[Obstacle],
        bounds: tuple[float, float, float, float],
        resolution_m: float,
    ) -> None:
        x0, y0, x1, y1 = bounds
        self.resolution_m = resolution_m
        self.origin = (x0, y0)
        self.shape = (
            max(1, math.ceil((y1 - y0) / resolution_m)),
            max(1, math.ceil((x1 - x0) / resolution_m)),
        )
        occupied = np.zeros(self.shape, dtype=bool)
        for obstacle in obstacles:
            _rasterize(occupied, obstacle.corners_xy_m, self.origin, resolution_m)
        # Distance from each cell's centre to the nearest occupied one's (m).
        self.clearance_m: FloatArray = (
            ndimage.distance_transform_edt(~occupied) * resolution_m
            if occupied.any()
            else np.full(self.shape, math.inf)
        )
        self.blocked: BoolArray = ndimage.binary_dilation(occupied, np.ones((3, 3), dtype=bool))

    def cells(self, xy_m: FloatArray) -> tuple[NDArray[np.int64], NDArray[np.int64], BoolArray]:
        """Row and column of each point (clipped) and whether it is inside the grid."""
        col = np.floor((xy_m[..., 0] - self.origin[0]) / self.resolution_m).astype(np.int64)
        row = np.floor((xy_m[..., 1] - self.origin[1]) / self.resolution_m).astype(np.int64)
        inside = (row >= 0) & (row < self.shape[0]) & (col >= 0) & (col < self.shape[1])
        return np.clip(row, 0, self.shape[0] - 1), np.clip(col, 0, self.shape[1] - 1), inside

    def points_blocked(self, xy_m: FloatArray) -> BoolArray:
        row, col, inside = self.cells(xy_m)
        result: BoolArray = self.blocked[row, col] | ~inside
        return result


def _rasterize(
    occupied: BoolArray, corners: FloatArray, origin: tuple[float, float], resolution_m: float
) -> None:
    """Mark the cells whose centre is inside the convex polygon, and every cell its
    boundary passes through (a thin wall has no centre inside it)."""
    rows, cols = occupied.shape
    lo = np.floor((corners.min(axis=0) - origin) / resolution_m).astype(int)
    hi = np.ceil((corners.max(axis=0) - origin) / resolution_m).astype(int)
    c0, r0 = max(lo[0], 0), max(lo[1], 0)
    c1, r1 = min(hi[0], cols - 1), min(hi[1], rows - 1)
    if c0 <= c1 and r0 <= r1:
        xs = origin[0] + (np.arange(c0, c1 + 1) + 0.5) * resolution_m
        ys = origin[1] + (np.arange(r0, r1 + 1) + 0.5) * resolution_m
        px, py = np.meshgrid(xs, ys)
        inside_left = np.ones(px.shape, dtype=bool)
        inside_right = np.ones(px.shape, dtype=bool)
        for i in range(len(corners)):
            ax, ay = corners[i]
            bx, by = corners[(i + 1) % len(corners)]
            cross = (bx - ax) * (py - ay) - (by - ay) * (px - ax)
            inside_left &= cross >= 0.0
            inside_right &= cross <= 0.0
        occupied[r0 : r1 + 1, c0 : c1 + 1] |= inside_left | inside_right
    for i in range(len(corners)):
        a, b = corners[i], corners[(i + 1) % len(corners)]
        count = max(2, math.ceil(float(np.hypot(*(b - a))) / (0.5 * resolution_m)) + 1)
        points = a + np.linspace(0.0, 1.0, count)[:, None] * (b - a)
        col = np.floor((points[:, 0] - origin[0]) / resolution_m).astype(int)
        row = np.floor((points[:, 1] - origin[1]) / resolution_m).astype(int)
        keep = (row >= 0) & (row < rows) & (col >= 0) & (col < cols)
        occupied[row[keep], col[keep]] = True


class FootprintChecker:
    """Whether the outline at guide poses is clear of the grid's obstacles."""

    def __init__(self, shape: VehicleShape, grid: OccupancyGrid, spacing_m: float) -> None:
        points = []
        for rear, front, right, left in shape.parts_local_m():
            xs = np.linspace(rear, front, max(2, math.ceil((front - rear) / spacing_m) + 1))
            ys = np.linspace(right, left, max(2, math.ceil((left - right) / spacing_m) + 1))
            px, py = np.meshgrid(xs, ys)
            points.append(np.column_stack([px.ravel(), py.ravel()]))
        self.local_m = np.concatenate(points)
        self.grid = grid

    def clear(self, poses: FloatArray) -> BoolArray:
        """One flag per guide pose (x, y, heading) of the (N, 3) array."""
        c, s = np.cos(poses[:, 2])[:, None], np.sin(poses[:, 2])[:, None]
        lx, ly = self.local_m[None, :, 0], self.local_m[None, :, 1]
        world = np.stack(
            [poses[:, 0:1] + c * lx - s * ly, poses[:, 1:2] + s * lx + c * ly], axis=-1
        )
        result: BoolArray = np.asarray(~self.grid.points_blocked(world).any(axis=1), dtype=bool)
        return result


class GuideDistances:
    """Shortest distances for the guide point (8-connected cells, obstacles grown by
    half the vehicle's width) from one point to every cell."""

    def __init__(self, grid: OccupancyGrid, half_width_m: float, cell_m: float) -> None:
        x0, y0 = grid.origin
        height = grid.shape[0] * grid.resolution_m
        width = grid.shape[1] * grid.resolution_m
        self.cell_m = cell_m
        self.origin = (x0, y0)
        self.shape = (max(1, int(height // cell_m)), max(1, int(width // cell_m)))
        rows, cols = self.shape
        cy = y0 + (np.arange(rows) + 0.5) * cell_m
        cx = x0 + (np.arange(cols) + 0.5) * cell_m
        px, py = np.meshgrid(cx, cy)
        r, c, _ = grid.cells(np.stack([px, py], axis=-1))
        # A cell is open when its centre is far enough from every obstacle, less the
        # cell's own half diagonal: a guide point anywhere in it may be clear.
        self.open = grid.clearance_m[r, c] >= half_width_m - 0.75 * cell_m
        index = np.arange(rows * cols).reshape(rows, cols)
        sources: list[NDArray[np.int64]] = []
        targets: list[NDArray[np.int64]] = []
        weights: list[FloatArray] = []
        for dr, dc in ((0, 1), (1, 0), (1, 1), (1, -1)):
            a = index[0 : rows - dr, max(0, -dc) : cols - max(0, dc)]
            b = index[dr:rows, max(0, dc) : cols - max(0, -dc)]
            both = self.open.ravel()[a.ravel()] & self.open.ravel()[b.ravel()]
            sources.append(a.ravel()[both])
            targets.append(b.ravel()[both])
            weights.append(np.full(int(both.sum()), math.hypot(dr, dc) * cell_m))
        n = rows * cols
        self._graph = coo_matrix(
            (np.concatenate(weights), (np.concatenate(sources), np.concatenate(targets))),
            shape=(n, n),
        ).tocsr()

    def index_of(self, x_m: float, y_m: float) -> int | None:
        col = math.floor((x_m - self.origin[0]) / self.cell_m)
        row = math.floor((y_m - self.origin[1]) / self.cell_m)
        if not (0 <= row < self.shape[0] and 0 <= col < self.shape[1]):
            return None
        return row * self.shape[1] + col

    def field_from(self, x_m: float, y_m: float) -> FloatArray:
        """Distances from (x, y) to every cell (inf where it cannot go), flattened."""
        index = self.index_of(x_m, y_m)
        if index is None:
            return np.full(self.shape[0] * self.shape[1], math.inf)
        return np.asarray(dijkstra(self._graph, directed=False, indices=index), dtype=np.float64)

    def distance_m(self, field: FloatArray, x_m: float, y_m: float) -> float:
        """From ``field``'s point to (x, y): the best of its cell and the 8 around it (a
        point near an obstacle may sit in a cell judged closed)."""
        col = math.floor((x_m - self.origin[0]) / self.cell_m)
        row = math.floor((y_m - self.origin[1]) / self.cell_m)
        best = math.inf
        for r in (row - 1, row, row + 1):
            for c in (col - 1, col, col + 1):
                if 0 <= r < self.shape[0] and 0 <= c < self.shape[1]:
                    best = min(best, float(field[r * self.shape[1] + c]))
        return best


@dataclass(frozen=True)
class SearchResult:
    pieces: tuple[PathPiece, ...]
    expansions: int


def _key(pose: Pose2D, params: SearchParams) -> tuple[int, int, int]:
    return (
        math.floor(pose.x_m / params.cell_m),
        math.floor(pose.y_m / params.cell_m),
        math.floor((pose.yaw_rad % math.tau) / (math.tau / params.heading_bins))
        % params.heading_bins,
    )


def _clear_path(
    start: Pose2D, pieces: Sequence[PathPiece], checker: FootprintChecker, sample_m: float
) -> bool:
    poses, _, _ = sample_pieces(start, pieces, sample_m)
    return bool(checker.clear(poses).all())


def _shot(
    pose: Pose2D, goal: Pose2D, radius_m: float, checker: FootprintChecker, sample_m: float
) -> tuple[PathPiece, ...] | None:
    """The shortest clear Dubins path from ``pose`` to ``goal`` (two words tried)."""
    for pieces in dubins_paths(pose, goal, radius_m)[:2]:
        if _clear_path(pose, pieces, checker, sample_m):
            return pieces
    return None


def search(
    start: Pose2D,
    goal: Pose2D,
    radius_m: float,
    checker: FootprintChecker,
    guide_distances: GuideDistances,
    params: SearchParams,
) -> SearchResult | str:
    """A clear forward path of arcs (curvature within ``1 / radius_m``) for the guide
    point from ``start`` to ``goal``; a reason when there is none."""
    to_goal = guide_distances.field_from(goal.x_m, goal.y_m)
    if not checker.clear(np.array([[start.x_m, start.y_m, start.yaw_rad]]))[0]:
        return "the vehicle's outline at its start overlaps an obstacle (or leaves the map)"
    if not checker.clear(np.array([[goal.x_m, goal.y_m, goal.yaw_rad]]))[0]:
        return "the vehicle's outline at the final straight's start overlaps an obstacle"
    if guide_distances.distance_m(to_goal, start.x_m, start.y_m) == math.inf:
        return "no way around the obstacles is wide enough for the vehicle"
    curvatures = (0.0, 0.5 / radius_m, -0.5 / radius_m, 1.0 / radius_m, -1.0 / radius_m)
    count = max(1, math.ceil(params.step_m / params.sample_m))
    along = np.linspace(0.0, params.step_m, count + 1)[1:]
    # Each arc's samples in the node's frame: (arcs, samples, 3).
    local = np.stack(
        [
            sample_piece(Pose2D(0.0, 0.0, 0.0), PathPiece(k, params.step_m), along)
            for k in curvatures
        ]
    )

    def heuristic(pose: Pose2D) -> float:
        grid = guide_distances.distance_m(to_goal, pose.x_m, pose.y_m)
        paths = dubins_paths(pose, goal, radius_m)
        dubins = sum(p.length_m for p in paths[0]) if paths else 0.0
        return max(grid, dubins)

    poses: list[Pose2D] = [start]
    parents: list[int] = [-1]
    pieces_in: list[PathPiece | None] = [None]
    costs: list[float] = [0.0]
    best: dict[tuple[int, int, int], float] = {_key(start, params): 0.0}
    heap: list[tuple[float, int]] = [(heuristic(start), 0)]
    expansions = 0
    while heap:
        _, node = heapq.heappop(heap)
        pose = poses[node]
        if costs[node] > best.get(_key(pose, params), math.inf):
            continue  # a better way to this cell was found after this one was queued
        expansions += 1
        if expansions > params.max_expansions:
            return f"no path found within {params.max_expansions} expansions"
        if (expansions - 1) % max(1, params.shot_every) == 0:
            shot = _shot(pose, goal, radius_m, checker, params.sample_m)
            if shot is not None:
                return SearchResult(_chain(node, parents, pieces_in) + shot, expansions)
        c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
        world = np.empty_like(local)
        world[..., 0] = pose.x_m + c * local[..., 0] - s * local[..., 1]
        world[..., 1] = pose.y_m + s * local[..., 0] + c * local[..., 1]
        world[..., 2] = pose.yaw_rad + local[..., 2]
        flags = np.asarray(
            checker.clear(world.reshape(-1, 3)).reshape(len(curvatures), count).all(axis=1)
        )
        clear = [bool(flag) for flag in flags]
        previous = pieces_in[node]
        for k_index, curvature in enumerate(curvatures):
            if not clear[k_index]:
                continue
            end = Pose2D(*(float(v) for v in world[k_index, -1]))
            cost = costs[node] + params.step_m * (1.0 + params.arc_penalty * (curvature != 0.0))
            if previous is not None and previous.curvature_per_m != curvature:
                cost += params.switch_penalty_m
            key = _key(end, params)
            if cost >= best.get(key, math.inf):
                continue
            best[key] = cost
            poses.append(end)
            parents.append(node)
            pieces_in.append(PathPiece(curvature, params.step_m))
            costs.append(cost)
            h = heuristic(end)
            if h < math.inf:
                heapq.heappush(heap, (cost + params.heuristic_weight * h, len(poses) - 1))
    return f"no path: every way is blocked ({expansions} expansions)"


def _chain(
    node: int, parents: list[int], pieces_in: list[PathPiece | None]
) -> tuple[PathPiece, ...]:
    chain: list[PathPiece] = []
    while node > 0:
        piece = pieces_in[node]
        if piece is not None:
            chain.append(piece)
        node = parents[node]
    return tuple(reversed(chain))


def shortcut(
    start: Pose2D,
    pieces: Sequence[PathPiece],
    radius_m: float,
    checker: FootprintChecker,
    params: SearchParams,
) -> tuple[PathPiece, ...]:
    """The chain shortened greedily: from each node, the farthest later node a clear
    Dubins path reaches more briefly than the chain does."""
    nodes = [start]
    for piece in pieces:
        nodes.append(pose_after(nodes[-1], piece))
    lengths = np.concatenate([[0.0], np.cumsum([p.length_m for p in pieces])])
    result: list[PathPiece] = []
    i, tries = 0, 0
    while i < len(pieces):
        jumped = False
        for j in range(len(pieces), i + 1, -1):
            if tries >= params.max_shortcut_tries:
                break
            along_chain = float(lengths[j] - lengths[i])
            for candidate in dubins_paths(nodes[i], nodes[j], radius_m)[:2]:
                if sum(p.length_m for p in candidate) >= along_chain - 1e-6:
                    break
                tries += 1
                if _clear_path(nodes[i], candidate, checker, params.sample_m):
                    result.extend(candidate)
                    i, jumped = j, True
                    break
            if jumped:
                break
        if not jumped:
            result.append(pieces[i])
            i += 1
    return _merged(result)


def _merged(pieces: Sequence[PathPiece]) -> tuple[PathPiece, ...]:
    """Neighbouring pieces of one curvature as one."""
    out: list[PathPiece] = []
    for piece in pieces:
        if piece.length_m <= 1e-9:
            continue
        if out and abs(out[-1].curvature_per_m - piece.curvature_per_m) < 1e-12:
            out[-1] = PathPiece(piece.curvature_per_m, out[-1].length_m + piece.length_m)
        else:
            out.append(piece)
    return tuple(out)
