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

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from appliance.perception import line_kernels
from appliance.perception.gates import chi_square_quantile
from appliance.perception.line_fit import (
    LineFit,
    RoughLine,
    fit_line_moments,
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


def _rows(array: FloatArray, indices: IndexArray) -> FloatArray:
    """``array[indices]``, as a view when the indices are a run (the usual piece)."""
    first, last = int(indices[0]), int(indices[-1])
    rows: FloatArray = (
        array[first : last + 1] if last - first + 1 == indices.shape[0] else array[indices]
    )
    return rows


@lru_cache(maxsize=8)
def _gates(merge_gate_z: float, points: int) -> FloatArray:
    """The merge's χ² gate by degrees of freedom, 0 to ``points``: a table, so the
    compiled split-and-merge reads it (the quantile itself is `gates`')."""
    table = np.array([chi_square_quantile(dof, merge_gate_z) for dof in range(points + 1)])
    table.flags.writeable = False
    return table


class _Cluster(NamedTuple):
    """One segment's points moved to their mean, their moment columns, and its pieces:
    (local point indices, isotropic rough line) in point order, and the debris."""

    shift_xy: tuple[float, float]
    q: FloatArray
    moments: FloatArray
    pieces: list[tuple[IndexArray, RoughLine]]
    debris: int


def _cluster(xy_m: FloatArray, params: LineParams, scanner: ScannerModel) -> _Cluster | None:
    """Split, merge and settle the corners of one cluster (`line_kernels.cluster_lines`;
    the rules are this module's docstring's, and `line_kernels.settle_corner` says how a
    corner moves); None if its coordinates overflow."""
    finite, shift_x, shift_y, q, moments, flat, offsets, fields, debris = (
        line_kernels.cluster_lines(
            np.ascontiguousarray(xy_m[:, 0]),
            np.ascontiguousarray(xy_m[:, 1]),
            1.0 / (scanner.sigma_m**2 + scanner.floor_sigma_m**2),
            params.split_distance_m,
            params.min_points,
            _gates(params.merge_gate_z, max(xy_m.shape[0], 1024)),
        )
    )
    if not finite:
        return None
    bounds = offsets.tolist()
    pieces = [
        (flat[a:b], RoughLine(*row))
        for a, b, row in zip(bounds[:-1], bounds[1:], fields.tolist(), strict=True)
    ]
    return _Cluster((shift_x, shift_y), q, moments, pieces, int(debris))


def split_and_merge(
    xy_m: FloatArray, params: LineParams, scanner: ScannerModel
) -> tuple[list[tuple[IndexArray, RoughLine]], int]:
    """The lines of one cluster as (local point indices, rough line), in point order,
    and the number of debris pieces dropped.

    The lines here are isotropic (σ_r for every point, no reweighting): the tests only
    need the right order of magnitude, and most pieces tried here are never kept, so
    the weighted fit is left to the caller, for the lines it keeps.
    """
    cluster = _cluster(xy_m, params, scanner)
    return ([], 0) if cluster is None else (cluster.pieces, cluster.debris)


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
    cluster = _cluster(xy, params, scanner)
    if cluster is None:
        return []
    results: list[LineFeature | FitRejection] = [
        FitRejection(RejectReason.TOO_FEW_POINTS, "split debris") for _ in range(cluster.debris)
    ]
    shortest_chord_m = params.min_length_m - params.split_distance_m
    for indices, rough in cluster.pieces:
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
