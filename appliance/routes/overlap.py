"""Where a route comes back close to itself: crossings and close passes.

Stanley et al.'s planner finds the nearest point of the route by searching both ways from
the last one; where the route comes back within a couple of metres of itself (a figure
eight's crossing, a return leg beside the outward one, a loop closing on its start), a fix
error can make that search jump to the other part. The check names those places so the
person who made the route knows, and the planner refuses such jumps.

"Another part" is defined without a distance-along-the-path threshold (which would depend
on how tightly the route turns): two places are an overlap when they are within
``distance_m`` of each other and the route, between them, went further than
``1.5 * distance_m`` away from the first. A turn the vehicle can make never qualifies (on an
arc the distance from a point grows monotonically up to the diameter); a loop coming back,
a crossing or a parallel return does, however the route turned in between.

Pure numpy and scipy: the route is densified to a quarter of ``distance_m`` so that
segments (not only points) are compared, neighbour pairs come from a k-d tree, and the pairs
are grouped into places by connected components over (arc length, arc length) cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# More candidate pairs than this (a route coiled on itself) is not checked pair by pair.
MAX_PAIRS = 4_000_000
MAX_OVERLAPS = 1000  # described; a route with more is a scribble, and the count says so
_EXCURSION_FACTOR = 1.5


@dataclass(frozen=True)
class Overlap:
    """One place where the route comes back near itself: the closest pair found there
    (``first`` before ``second`` along the route), as arc lengths and positions."""

    first_distance_m: float
    second_distance_m: float
    first_xy_m: tuple[float, float]
    second_xy_m: tuple[float, float]
    gap_m: float  # how close the two parts come
    angle_deg: float  # between the two parts' directions of travel, 0..180
    first_extent_m: tuple[float, float]  # the stretch of each part that is within gap
    second_extent_m: tuple[float, float]


@dataclass(frozen=True)
class OverlapResult:
    overlaps: tuple[Overlap, ...]  # at most MAX_OVERLAPS, in order along the route
    count: int = 0  # how many places there are in all
    skipped_reason: str | None = None  # the route was not checked (too dense)


def _densify(points_m: FloatArray, step_m: float) -> tuple[FloatArray, FloatArray]:
    """Points at most ``step_m`` apart along the line, with their arc lengths."""
    deltas = np.diff(points_m, axis=0)
    seg_m = np.hypot(deltas[:, 0], deltas[:, 1])
    s_m = np.concatenate(([0.0], np.cumsum(seg_m)))
    pieces = np.maximum(np.ceil(seg_m / step_m).astype(np.int64), 1)
    seg_index = np.repeat(np.arange(len(seg_m)), pieces)
    starts = np.concatenate(([0], np.cumsum(pieces)[:-1]))
    fraction = (np.arange(len(seg_index)) - np.repeat(starts, pieces)) / np.repeat(pieces, pieces)
    dense = points_m[seg_index] + fraction[:, None] * deltas[seg_index]
    dense_s = s_m[seg_index] + fraction * seg_m[seg_index]
    return np.vstack((dense, points_m[-1:])), np.concatenate((dense_s, s_m[-1:]))


def find_overlaps(points_m: FloatArray, distance_m: float) -> OverlapResult:
    """Every place where (N, 2) ``points_m`` (consecutive points distinct) comes within
    ``distance_m`` of another part of itself; see the module docstring."""
    step_m = distance_m / 4.0
    dense, dense_s = _densify(points_m, step_m)
    out_m = _EXCURSION_FACTOR * distance_m
    tree = cKDTree(dense)
    count = int(np.sum(tree.query_ball_point(dense, out_m, return_length=True)))
    if count > 2 * MAX_PAIRS:
        return OverlapResult((), 0, f"the route passes near itself too often to check ({count})")
    pairs = tree.query_pairs(out_m, output_type="ndarray").astype(np.int64)
    if len(pairs) == 0:
        return OverlapResult(())
    first, second = pairs[:, 0], pairs[:, 1]  # query_pairs gives first < second
    order = np.lexsort((second, first))
    first, second = first[order], second[order]
    group_start = np.flatnonzero(np.concatenate(([True], first[1:] != first[:-1])))
    group_of = np.repeat(group_start, np.diff(np.concatenate((group_start, [len(first)]))))
    rank = np.arange(len(first)) - group_of
    # The initial run i+1, i+2, ... never left the excursion disc around point i.
    left_and_came_back = (second - first) != rank + 1
    gaps_m = np.hypot(*(dense[second] - dense[first]).T)
    keep = left_and_came_back & (gaps_m <= distance_m)
    if not np.any(keep):
        return OverlapResult(())
    first, second, gaps_m = first[keep], second[keep], gaps_m[keep]
    labels = _group(dense_s[first], dense_s[second], cell_m=2.0 * distance_m)
    overlaps = _describe(dense, dense_s, first, second, gaps_m, labels)
    return OverlapResult(tuple(overlaps), count=len(np.unique(labels)))


def _group(first_s_m: FloatArray, second_s_m: FloatArray, cell_m: float) -> IntArray:
    """A label per pair: pairs whose (arc length, arc length) cells touch are one place."""
    cells_i = np.floor(first_s_m / cell_m).astype(np.int64)
    cells_j = np.floor(second_s_m / cell_m).astype(np.int64)
    width = int(cells_j.max()) + 3
    keys = (cells_i + 1) * width + (cells_j + 1)
    unique_keys, cell_of_pair = np.unique(keys, return_inverse=True)
    rows: list[IntArray] = []
    cols: list[IntArray] = []
    for d_i, d_j in ((0, 1), (1, -1), (1, 0), (1, 1)):
        neighbour = unique_keys + d_i * width + d_j
        where = np.clip(np.searchsorted(unique_keys, neighbour), 0, len(unique_keys) - 1)
        found = unique_keys[where] == neighbour
        rows.append(np.flatnonzero(found))
        cols.append(where[found])
    row, col = np.concatenate(rows), np.concatenate(cols)
    graph = coo_matrix((np.ones(len(row)), (row, col)), shape=(len(unique_keys),) * 2)
    _count, cell_labels = connected_components(graph, directed=False)
    return np.asarray(cell_labels[cell_of_pair.ravel()], dtype=np.int64)


def _heading(dense: FloatArray, index: int) -> FloatArray:
    ahead = min(index + 1, len(dense) - 1)
    behind = ahead - 1
    delta = dense[ahead] - dense[behind]
    return np.asarray(delta / max(float(np.hypot(*delta)), 1e-12))


def _describe(
    dense: FloatArray,
    dense_s: FloatArray,
    first: IntArray,
    second: IntArray,
    gaps_m: FloatArray,
    labels: IntArray,
) -> list[Overlap]:
    """One Overlap per label: its closest pair, and the stretches its pairs cover."""
    order = np.lexsort((gaps_m, labels))
    labels, first, second, gaps_m = labels[order], first[order], second[order], gaps_m[order]
    starts = np.flatnonzero(np.concatenate(([True], labels[1:] != labels[:-1])))
    first_s, second_s = dense_s[first], dense_s[second]
    extents = [np.minimum.reduceat(values, starts) for values in (first_s, second_s)]
    extents += [np.maximum.reduceat(values, starts) for values in (first_s, second_s)]
    overlaps = []
    for k, best in enumerate(starts[:MAX_OVERLAPS]):
        i, j = int(first[best]), int(second[best])
        cos_angle = float(np.clip(np.dot(_heading(dense, i), _heading(dense, j)), -1.0, 1.0))
        overlaps.append(
            Overlap(
                first_distance_m=float(dense_s[i]),
                second_distance_m=float(dense_s[j]),
                first_xy_m=(float(dense[i, 0]), float(dense[i, 1])),
                second_xy_m=(float(dense[j, 0]), float(dense[j, 1])),
                gap_m=float(gaps_m[best]),
                angle_deg=float(np.degrees(np.arccos(cos_angle))),
                first_extent_m=(float(extents[0][k]), float(extents[2][k])),
                second_extent_m=(float(extents[1][k]), float(extents[3][k])),
            )
        )
    overlaps.sort(key=lambda overlap: overlap.first_distance_m)
    return overlaps
