"""Straight boards and walls in a cluster: split-and-merge, then the weighted line fit
(``line_fit``) of every piece kept, its ends clipped to the data and judged occluded or not.

**Split.** Iterative end-point fit: the chord from a piece's first to its last point, the
point farthest from it becomes a breakpoint when it is farther than
``split_distance_m``, recursively. It finds the launcher's corners (front board to side
board) without being told how many there are.

**Merge.** Splitting on a chord between two *noisy* end points over-splits a long
board now and then, and a lone outlier splits it twice. So pieces of fewer points than
a line needs are dropped as debris (the outlier goes with them), and neighbouring
pieces are merged, best pair first, while the merged line passes a χ² test: its
squared residuals, in units of the data sheet's σ (which bounds each point's σ along
the normal from above), sum to no more than the χ² quantile for ``n − 2`` degrees of
freedom; and while every point stays within the split
distance (so merge can never undo what split found). The Mahalanobis distance between
the two pieces' ``(r, α)`` is the textbook test, but IEPF puts its breakpoints on the
points farthest off the chord, at the ends of the pieces where they lever the fit most:
on simulated launcher scans it refused 23 % of the merges of one straight board (the
merged line's χ², 0.4 %).

**Ends.** A line ends at its first and last point projected onto it. An end is a true
end when the beam just beyond it sees nothing, or something clearly farther than the
line, or when the line meets a neighbour of the same cluster (a corner); it is flagged
occluded when that beam sees something in front of the line or the line's own
continuation (cut by a region of interest, a hole, a grazing gap), or when the field of
view ends there.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.perception.gates import chi_square_quantile
from appliance.perception.line_fit import (
    LineFit,
    RoughLine,
    fit_line,
    line_from_sums,
    moment_columns,
)
from appliance.perception.points import ScanPoints
from appliance.perception.types import (
    FitRejection,
    FloatArray,
    LineFeature,
    RejectReason,
    ScannerModel,
)

IndexArray = npt.NDArray[np.intp]


@dataclass(frozen=True)
class LineParams:
    """Split-and-merge and acceptance settings.

    ``split_distance_m`` 60 mm is five data-sheet σ: the noise alone almost never
    reaches it, the launcher's 45° corner at 0.8 m does by a factor of ten.
    ``merge_gate_z`` is the merge's χ² gate as a normal quantile (3.09: 99.9 %). Five
    points and 0.5 m keep the launcher's 0.8 m side boards and drop the facets a split
    makes of a cylinder or a person (0.5 m across at most).
    ``occlusion_margin_m`` is how much nearer or farther than the line the beam beyond
    an end must be to count as in front of it or clearly behind it.
    """

    split_distance_m: float = 0.06
    merge_gate_z: float = 3.09
    min_points: int = 5
    min_length_m: float = 0.5
    occlusion_margin_m: float = 0.1
    max_iterations: int = 20

    def __post_init__(self) -> None:
        if not self.split_distance_m > 0.0:
            raise ValueError(f"split_distance_m must be > 0, got {self.split_distance_m}")
        if self.min_points < 2:
            raise ValueError(f"min_points must be >= 2, got {self.min_points}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be >= 1, got {self.max_iterations}")


def split_breakpoints(xy_m: FloatArray, split_distance_m: float) -> list[int]:
    """Iterative end-point fit: sorted indices of the points the chords broke at,
    the first and the last point included."""
    n = int(xy_m.shape[0])
    if n == 0:
        return []
    breaks = {0, n - 1}
    pending = [(0, n - 1)]
    while pending:
        i, j = pending.pop()
        if j - i < 2:
            continue
        chord = xy_m[j] - xy_m[i]
        length = math.hypot(float(chord[0]), float(chord[1]))
        inner = xy_m[i + 1 : j] - xy_m[i]
        if length > 0.0:
            distance = np.abs(inner[:, 0] * chord[1] - inner[:, 1] * chord[0]) / length
        else:
            distance = np.hypot(inner[:, 0], inner[:, 1])
        k = int(np.argmax(distance))
        if distance[k] > split_distance_m:
            m = i + 1 + k
            breaks.add(m)
            pending += [(i, m), (m, j)]
    return sorted(breaks)


def _pieces(breaks: list[int]) -> list[tuple[int, int]]:
    """Non-overlapping inclusive pieces between breakpoints; a breakpoint (the corner)
    starts the piece after it."""
    if len(breaks) == 1:
        return [(breaks[0], breaks[0])]
    pieces = [(a, b - 1) for a, b in itertools.pairwise(breaks[:-1])]
    pieces.append((breaks[-2], breaks[-1]))
    return [(a, b) for a, b in pieces if b >= a]


_Candidate = tuple[float, tuple[IndexArray, RoughLine]]  # (χ² / gate, merged piece)


class _Cluster:
    """One segment's points with their moment columns: the isotropic line of any subset
    is then one indexed sum away, and split-and-merge tries many subsets."""

    def __init__(self, xy_m: FloatArray, scanner: ScannerModel) -> None:
        self.shift = xy_m.sum(axis=0) / max(xy_m.shape[0], 1)
        self.q = xy_m - self.shift
        self.moments = moment_columns(self.q)
        self.weight = 1.0 / (scanner.sigma_m**2 + scanner.floor_sigma_m**2)

    def line(self, indices: IndexArray) -> RoughLine | None:
        return line_from_sums(self.weight * self.moments[indices].sum(axis=0), self.shift)

    def residuals(self, indices: IndexArray, line: RoughLine) -> FloatArray:
        """Each point's distance from the line."""
        c, s = math.cos(line.alpha_rad), math.sin(line.alpha_rad)
        offset = line.r_m - float(self.shift[0]) * c - float(self.shift[1]) * s
        distance: FloatArray = np.abs(self.q[indices] @ np.array([c, s]) - offset)
        return distance


def split_and_merge(
    xy_m: FloatArray, params: LineParams, scanner: ScannerModel
) -> tuple[list[tuple[IndexArray, RoughLine]], int]:
    """The lines of one cluster as (local point indices, rough line), in point order,
    and the number of debris pieces dropped.

    The lines here are isotropic (σ_r for every point, no reweighting): the tests only
    need the right order of magnitude, and most pieces tried here are never kept, so
    the weighted fit is left to the caller, for the lines it keeps.
    """
    with np.errstate(all="ignore"):
        cluster = _Cluster(xy_m, scanner)
        if not np.isfinite(cluster.moments).all():
            return [], 0
        return _split_and_merge(cluster, xy_m, params)


def _split_and_merge(
    cluster: _Cluster, xy_m: FloatArray, params: LineParams
) -> tuple[list[tuple[IndexArray, RoughLine]], int]:
    pieces: list[tuple[IndexArray, RoughLine]] = []
    debris = 0
    for a, b in _pieces(split_breakpoints(xy_m, params.split_distance_m)):
        indices = np.arange(a, b + 1)
        line = cluster.line(indices) if indices.size >= params.min_points else None
        if line is None:
            debris += 1
        else:
            pieces.append((indices, line))

    def candidate(k: int) -> _Candidate | None:
        """Pieces k and k+1 merged, if the merged line passes both tests, with its χ²
        as a fraction of the gate (the smaller, the better the pair)."""
        union = np.concatenate([pieces[k][0], pieces[k + 1][0]])
        merged = cluster.line(union)
        if merged is None or cluster.residuals(union, merged).max() > params.split_distance_m:
            return None
        gate = chi_square_quantile(union.size - 2, params.merge_gate_z)
        return (merged.chi_square / gate, (union, merged)) if merged.chi_square <= gate else None

    candidates = [candidate(k) for k in range(len(pieces) - 1)]
    while True:
        viable = [(c[0], k, c[1]) for k, c in enumerate(candidates) if c is not None]
        if not viable:
            break
        _, k, merged = min(viable, key=lambda v: (v[0], v[1]))
        pieces[k : k + 2] = [merged]
        del candidates[k]  # only the pairs with the new piece change
        if k < len(candidates):
            candidates[k] = candidate(k)
        if k > 0:
            candidates[k - 1] = candidate(k - 1)
    for k in range(len(pieces) - 1):
        pieces[k : k + 2] = _settle_corner(cluster, pieces[k], pieces[k + 1], params)
    return pieces, debris


def _settle_corner(
    cluster: _Cluster,
    before: tuple[IndexArray, RoughLine],
    after: tuple[IndexArray, RoughLine],
    params: LineParams,
) -> list[tuple[IndexArray, RoughLine]]:
    """Move the boundary between two neighbouring lines to where the points say it is.

    The split put the corner on one noisy point, a short piece next to it may have been
    merged to the wrong side or dropped as debris; any of these bends a fit or cuts a
    line short. With both lines fitted on their bulk, every point from the first line's
    start to the second's end is given to the line that explains it, at the single
    boundary that minimises the summed squared residuals (one cumulative sum), and a
    point farther than the split distance from its line stays out.
    """
    lowest = params.min_points
    union = np.arange(before[0][0], after[0][-1] + 1)
    if union.size < 2 * lowest:
        return [before, after]
    residuals = [cluster.residuals(union, line) for _, line in (before, after)]
    # cost[k]: the first k points to the first line, the rest to the second.
    cost = np.concatenate(([0.0], np.cumsum(residuals[0] ** 2)))
    cost += np.concatenate((np.cumsum(residuals[1][::-1] ** 2)[::-1], [0.0]))
    boundary = lowest + int(np.argmin(cost[lowest : union.size - lowest + 1]))
    first = union[:boundary][residuals[0][:boundary] <= params.split_distance_m]
    second = union[boundary:][residuals[1][boundary:] <= params.split_distance_m]
    if np.array_equal(first, before[0]) and np.array_equal(second, after[0]):
        return [before, after]
    if min(first.size, second.size) < lowest:
        return [before, after]
    first_line, second_line = cluster.line(first), cluster.line(second)
    if first_line is None or second_line is None:
        return [before, after]
    return [(first, first_line), (second, second_line)]


def _line_range_m(fit: LineFit, origin: tuple[float, float], direction: FloatArray) -> float:
    """How far along a beam from ``origin`` the line is (inf if the beam never meets it)."""
    nx, ny = math.cos(fit.alpha_rad), math.sin(fit.alpha_rad)
    facing = float(direction[0]) * nx + float(direction[1]) * ny
    if abs(facing) < 1e-9:
        return math.inf
    t = (fit.r_m - origin[0] * nx - origin[1] * ny) / facing
    return t if t > 0.0 else math.inf


def end_occluded(
    points: ScanPoints,
    segment: tuple[int, int],
    end_index: int,
    step: int,
    fit: LineFit,
    margin_m: float,
) -> bool:
    """Whether the line's end at beam ``end_index`` may not be where the surface ends.

    ``step`` is −1 for the start, +1 for the end. The beam beyond is judged on the raw
    scan (not the regions of interest), so an end cut by a region says "occluded".
    """
    beyond = end_index + step
    if not 0 <= beyond < points.count:
        return True  # the field of view ends here, the surface may not
    if segment[0] <= beyond < segment[1]:
        return False  # one continuous surface bends here: a corner is a true end
    if not points.valid[beyond]:
        return False  # nothing behind the end: open sky or out of range
    expected = _line_range_m(fit, points.origin_xy_m, points.directions[beyond])
    if not math.isfinite(expected):
        return False
    return bool(points.ranges_m[beyond] <= expected + margin_m)


def extract_lines(
    points: ScanPoints,
    segment: tuple[int, int],
    params: LineParams,
    scanner: ScannerModel,
) -> list[LineFeature | FitRejection]:
    """Every line of one segment as a feature, or the reason a piece is not one."""
    start, stop = segment
    xy = points.xy_m[start:stop]
    directions = points.directions[start:stop]
    if stop - start < params.min_points:
        return [FitRejection(RejectReason.TOO_FEW_POINTS, f"{stop - start} points")]
    pieces, debris = split_and_merge(xy, params, scanner)
    results: list[LineFeature | FitRejection] = [
        FitRejection(RejectReason.TOO_FEW_POINTS, "split debris") for _ in range(debris)
    ]
    for indices, rough in pieces:
        ends = xy[[int(indices[0]), int(indices[-1])]]
        if float(np.hypot(*(ends[1] - ends[0]))) < params.min_length_m - params.split_distance_m:
            results.append(FitRejection(RejectReason.TOO_SHORT, "well short"))
            continue
        fit = fit_line(
            xy[indices], directions[indices], scanner, params.max_iterations, rough.alpha_rad
        )
        if isinstance(fit, FitRejection):
            results.append(fit)
            continue
        normal = np.array([math.cos(fit.alpha_rad), math.sin(fit.alpha_rad)])
        projected = ends - np.outer(ends @ normal - fit.r_m, normal)
        length = float(np.hypot(*(projected[1] - projected[0])))
        if length < params.min_length_m:
            results.append(FitRejection(RejectReason.TOO_SHORT, f"{length:.3f} m"))
            continue
        first, last = start + int(indices[0]), start + int(indices[-1])
        results.append(
            LineFeature(
                r_m=fit.r_m,
                alpha_rad=fit.alpha_rad,
                covariance=fit.covariance,
                start_xy_m=(float(projected[0, 0]), float(projected[0, 1])),
                end_xy_m=(float(projected[1, 0]), float(projected[1, 1])),
                start_occluded=end_occluded(
                    points, segment, first, -1, fit, params.occlusion_margin_m
                ),
                end_occluded=end_occluded(
                    points, segment, last, +1, fit, params.occlusion_margin_m
                ),
                n_points=fit.n_points,
                rms_m=fit.rms_m,
                first_index=first,
                last_index=last,
            )
        )
    return results
