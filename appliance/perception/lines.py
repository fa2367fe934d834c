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
from appliance.perception.jit import F64, IN_1D, kernel
from appliance.perception.line_fit import (
    LineFit,
    RoughLine,
    column_sums,
    fit_line_moments,
    line_from_list,
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
    xs, ys = np.ascontiguousarray(xy_m[:, 0]), np.ascontiguousarray(xy_m[:, 1])
    breaks: list[int] = np.flatnonzero(_split(xs, ys, split_distance_m)).tolist()
    return breaks


@kernel(IN_1D, IN_1D, F64)
def _split(xs: FloatArray, ys: FloatArray, split_distance_m: float) -> npt.NDArray[np.bool_]:
    """`split_breakpoints` as a mask over the points."""
    n = xs.shape[0]
    breaks = np.zeros(n, dtype=np.bool_)
    if n == 0:
        return breaks
    breaks[0] = breaks[n - 1] = True
    pending = [(0, n - 1)]
    while pending:
        i, j = pending.pop()
        if j - i < 2:
            continue
        xi, yi = xs[i], ys[i]
        chord_x, chord_y = xs[j] - xi, ys[j] - yi
        length = math.hypot(chord_x, chord_y)
        farthest, k = -1.0, i + 1
        for m in range(i + 1, j):
            inner_x, inner_y = xs[m] - xi, ys[m] - yi
            if length > 0.0:
                distance = abs(inner_x * chord_y - inner_y * chord_x) / length
            else:
                distance = math.hypot(inner_x, inner_y)
            if math.isnan(distance):  # numpy's argmax takes the first NaN: no split
                farthest, k = distance, m
                break
            if distance > farthest:
                farthest, k = distance, m
        if farthest > split_distance_m:
            breaks[k] = True
            pending.append((i, k))
            pending.append((k, j))
    return breaks


def _pieces(breaks: list[int]) -> list[tuple[int, int]]:
    """Non-overlapping inclusive pieces between breakpoints; a breakpoint (the corner)
    starts the piece after it."""
    if len(breaks) == 1:
        return [(breaks[0], breaks[0])]
    pieces = [(a, b - 1) for a, b in itertools.pairwise(breaks[:-1])]
    pieces.append((breaks[-2], breaks[-1]))
    return [(a, b) for a, b in pieces if b >= a]


def _rows(array: FloatArray, indices: IndexArray) -> FloatArray:
    """``array[indices]``, as a view when the indices are a run (the usual piece): the
    same rows in the same order, so every sum over them is the same to the last bit."""
    first, last = int(indices[0]), int(indices[-1])
    rows: FloatArray = (
        array[first : last + 1] if last - first + 1 == indices.shape[0] else array[indices]
    )
    return rows


_Candidate = tuple[float, tuple[IndexArray, RoughLine]]  # (χ² / gate, merged piece)


class _Cluster:
    """One segment's points with their moment columns: the isotropic line of any subset
    is then one indexed sum away, and split-and-merge tries many subsets. Most are runs
    that start where a piece starts (a merge keeps the first piece's start): the running
    sums of the rows from each start are kept, and are the runs' sums to the last bit
    (``np.add.reduce`` adds the rows one after the other too)."""

    def __init__(self, xy_m: FloatArray, scanner: ScannerModel) -> None:
        self.shift = column_sums(xy_m) / max(xy_m.shape[0], 1)
        self.shift_xy = (float(self.shift[0]), float(self.shift[1]))
        self.q = xy_m - self.shift
        self.moments = moment_columns(self.q)
        self.weight = 1.0 / (scanner.sigma_m**2 + scanner.floor_sigma_m**2)
        self._running: dict[int, FloatArray] = {}  # by first row: the running sums

    def line(self, indices: IndexArray) -> RoughLine | None:
        first, last = int(indices[0]), int(indices[-1])
        if last - first + 1 != indices.shape[0]:  # not a run
            sums = column_sums(self.moments[indices]).tolist()
        else:
            if (running := self._running.get(first)) is None:
                running = self._running[first] = np.add.accumulate(self.moments[first:], axis=0)
            sums = running[last - first].tolist()
        return line_from_list([self.weight * v for v in sums], *self.shift_xy)

    def farthest(self, indices: IndexArray, line: RoughLine) -> float:
        """The largest distance of the points from the line, from the extremes of their
        projections on its normal (a difference of floats is monotonic in each, so this
        is the largest of the rounded distances, to the last bit)."""
        c, s = math.cos(line.alpha_rad), math.sin(line.alpha_rad)
        offset = line.r_m - self.shift_xy[0] * c - self.shift_xy[1] * s
        along = _rows(self.q, indices) @ np.array([c, s])
        return max(float(along.max()) - offset, offset - float(along.min()))


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
        line = cluster.line(indices) if indices.shape[0] >= params.min_points else None
        if line is None:
            debris += 1
        else:
            pieces.append((indices, line))
    if len(pieces) < 2:
        return pieces, debris

    def candidate(k: int) -> _Candidate | None:
        """Pieces k and k+1 merged, if the merged line passes both tests, with its χ²
        as a fraction of the gate (the smaller, the better the pair)."""
        union = np.concatenate((pieces[k][0], pieces[k + 1][0]))
        merged = cluster.line(union)
        if merged is None:
            return None
        gate = chi_square_quantile(union.shape[0] - 2, params.merge_gate_z)
        if not merged.chi_square <= gate:
            return None
        if cluster.farthest(union, merged) > params.split_distance_m:
            return None
        return merged.chi_square / gate, (union, merged)

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
    begin, end = int(before[0][0]), int(after[0][-1]) + 1
    size = end - begin
    if size < 2 * lowest:
        return [before, after]
    # Both lines' distances of every point from the first line's start to the second's end.
    residuals = np.empty((2, size))
    offsets = []
    for row, (_, line) in zip(residuals, (before, after), strict=True):
        c, s = math.cos(line.alpha_rad), math.sin(line.alpha_rad)
        np.matmul(cluster.q[begin:end], np.array([c, s]), out=row)
        offsets.append([line.r_m - cluster.shift_xy[0] * c - cluster.shift_xy[1] * s])
    residuals -= offsets
    np.abs(residuals, out=residuals)
    squares = residuals * residuals
    # cost[k]: the first k points to the first line, the rest to the second (k >= lowest).
    head = squares[0].cumsum()
    tail = squares[1, ::-1].cumsum()[::-1]
    cost = head[lowest - 1 : size - lowest] + tail[lowest : size - lowest + 1]
    boundary = lowest + int(cost.argmin())
    union = np.arange(begin, end)
    first = union[:boundary][residuals[0, :boundary] <= params.split_distance_m]
    second = union[boundary:][residuals[1, boundary:] <= params.split_distance_m]
    if _same(first, before[0]) and _same(second, after[0]):
        return [before, after]
    if min(first.shape[0], second.shape[0]) < lowest:
        return [before, after]
    first_line, second_line = cluster.line(first), cluster.line(second)
    if first_line is None or second_line is None:
        return [before, after]
    return [(first, first_line), (second, second_line)]


def _same(a: IndexArray, b: IndexArray) -> bool:
    return a.shape == b.shape and bool((a == b).all())


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
    with np.errstate(all="ignore"):
        cluster = _Cluster(xy, scanner)
        if not np.isfinite(cluster.moments).all():
            return []
        pieces, debris = _split_and_merge(cluster, xy, params)
    results: list[LineFeature | FitRejection] = [
        FitRejection(RejectReason.TOO_FEW_POINTS, "split debris") for _ in range(debris)
    ]
    shortest_chord_m = params.min_length_m - params.split_distance_m
    for indices, rough in pieces:
        first, last = start + int(indices[0]), start + int(indices[-1])
        (x0, y0), (x1, y1) = points.xy_m[first].tolist(), points.xy_m[last].tolist()
        if math.hypot(x1 - x0, y1 - y0) < shortest_chord_m:
            results.append(FitRejection(RejectReason.TOO_SHORT, "well short"))
            continue
        with np.errstate(all="ignore"):  # the cluster's moments serve every piece
            fit = fit_line_moments(
                _rows(cluster.q, indices),
                _rows(cluster.moments, indices),
                cluster.shift_xy,
                _rows(directions, indices),
                scanner,
                params.max_iterations,
                rough.alpha_rad,
            )
        if isinstance(fit, FitRejection):
            results.append(fit)
            continue
        # The ends projected onto the line.
        c, s = math.cos(fit.alpha_rad), math.sin(fit.alpha_rad)
        off0, off1 = x0 * c + y0 * s - fit.r_m, x1 * c + y1 * s - fit.r_m
        start_xy = (x0 - off0 * c, y0 - off0 * s)
        end_xy = (x1 - off1 * c, y1 - off1 * s)
        length = math.hypot(end_xy[0] - start_xy[0], end_xy[1] - start_xy[1])
        if length < params.min_length_m:
            results.append(FitRejection(RejectReason.TOO_SHORT, f"{length:.3f} m"))
            continue
        results.append(
            LineFeature(
                r_m=fit.r_m,
                alpha_rad=fit.alpha_rad,
                covariance=fit.covariance,
                start_xy_m=start_xy,
                end_xy_m=end_xy,
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
