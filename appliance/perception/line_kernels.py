"""The compiled loops of the line fits (`jit`): the weighted line's iterations
(`line_fit`) and split-and-merge with its corners (`lines`).

What each computes, and why, is said where it is used: `line_fit` derives the weighted
total-least-squares line and its covariance, `lines` the splitting, merging and corner
rule. Here they are loops over a cluster's points, with the sums taken in the order the
numpy code took them (a run of rows is added one row after the other), so a rough line
is the one the plain sums give to the last bit. A kernel calls only kernels of this file
(numba's cache is invalidated by a change of the file a kernel is in, not of the files
it calls into).
"""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt

from appliance.perception.jit import F64, I64, IN_1D, IN_2D, IN_INDEX, OUT_1D, kernel
from appliance.perception.types import FloatArray

IndexArray = npt.NDArray[np.int64]
Rough = tuple[bool, float, float, float, float, float, float]  # found, then `RoughLine`'s

_IRLS_TOLERANCE = 1e-12
_RESOLUTION = 1e-10  # a spread below this fraction of the coordinates is rounding


@kernel(F64)
def wrap_angle(angle_rad: float) -> float:
    """The angle in (−π, π]."""
    wrapped = math.atan2(math.sin(angle_rad), math.cos(angle_rad))
    return math.pi if wrapped <= -math.pi else wrapped


@kernel(F64, F64, F64, F64, F64, F64, F64, F64)
def rough_line(total: float, sx: float, sy: float, sxx: float, syy: float, sxy: float,
               shift_x: float, shift_y: float
              ) -> tuple[bool, float, float, float, float, float, float]:  # fmt: skip
    """(found, then `RoughLine`'s fields) of the moment sums."""
    if not total > 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    mx, my = sx / total, sy / total
    cxx, cyy, cxy = sxx - total * mx * mx, syy - total * my * my, sxy - total * mx * my
    px, py = mx + shift_x, my + shift_y
    resolution = _RESOLUTION * max(abs(px), abs(py))  # spreads below this are rounding
    if not (cxx + cyy > total * resolution * resolution and math.isfinite(cxx + cyy + cxy)):
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    alpha = 0.5 * math.atan2(-2.0 * cxy, cyy - cxx)
    c, s = math.cos(alpha), math.sin(alpha)
    r = px * c + py * s
    if r < 0.0:
        r, alpha, c, s = -r, alpha + math.pi, -c, -s
    spread = cxx * s * s - 2.0 * cxy * s * c + cyy * c * c
    across = cxx * c * c + 2.0 * cxy * s * c + cyy * s * s
    return True, r, wrap_angle(alpha), spread, -s * px + c * py, total, across


@kernel(IN_2D, F64, F64, F64, OUT_1D)
def weights_into(directions: FloatArray, alpha: float, sigma_m: float, floor_sigma_m: float,
                 out: FloatArray) -> None:  # fmt: skip
    """Each point's weight, 1 / the variance of its offset along the normal at ``alpha``
    (`ScannerModel.normal_variance`), into ``out``."""
    c, s = math.cos(alpha), math.sin(alpha)
    lowest = (1e-3 * sigma_m) ** 2
    for k in range(directions.shape[0]):
        variance = sigma_m * (directions[k, 0] * c + directions[k, 1] * s)
        variance *= variance
        variance += floor_sigma_m**2
        if floor_sigma_m**2 < lowest:
            variance = max(variance, lowest)
        out[k] = 1.0 / variance


@kernel(IN_1D, IN_2D, OUT_1D)
def weighted_sums(weights: FloatArray, moments: FloatArray, out: FloatArray) -> None:
    """``weights @ moments`` into ``out``, the points added in order."""
    for j in range(6):
        out[j] = 0.0
    for k in range(moments.shape[0]):
        w = weights[k]
        for j in range(6):
            out[j] += w * moments[k, j]


@kernel(IN_2D, IN_2D, F64, F64, F64, F64, F64, I64)
def irls(moments: FloatArray, directions: FloatArray, alpha_start_rad: float, sigma_m: float,
         floor_sigma_m: float, shift_x: float, shift_y: float, iterations: int
        ) -> tuple[bool, FloatArray, float, float, float, float, float, float]:  # fmt: skip
    """The weighted line iterated to its fixed point: (found, the weights it ends with,
    then `RoughLine`'s fields). Each pass fits the line with the weights of the last
    pass's normal; it stops when a pass moves the line by no more than rounding."""
    weights = np.empty(moments.shape[0])
    sums = np.empty(6)
    weights_into(directions, alpha_start_rad, sigma_m, floor_sigma_m, weights)
    found = False
    r = alpha = spread = along = total = across = 0.0
    for iteration in range(iterations):
        weighted_sums(weights, moments, sums)
        previous_r, previous_alpha = r, alpha
        found, r, alpha, spread, along, total, across = rough_line(
            sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], shift_x, shift_y
        )
        if not found:
            break
        if iteration > 0:
            change = max(abs(r - previous_r), abs(wrap_angle(alpha - previous_alpha)))
            if change <= _IRLS_TOLERANCE * (1.0 + r):
                break  # the weights this line was fitted with are its own, to rounding
        weights_into(directions, alpha, sigma_m, floor_sigma_m, weights)
    return found, weights, r, alpha, spread, along, total, across


@kernel(IN_2D, IN_1D, F64, F64, F64, F64)
def residual_figures(q: FloatArray, weights: FloatArray, r_m: float, alpha_rad: float,
                     shift_x: float, shift_y: float) -> tuple[float, float, float]:  # fmt: skip
    """The residuals' rms, the largest residual and ``Σ w e²``."""
    c, s = math.cos(alpha_rad), math.sin(alpha_rad)
    offset = r_m - shift_x * c - shift_y * s
    squares = 0.0
    worst = 0.0
    chi_square = 0.0
    for k in range(q.shape[0]):
        residual = q[k, 0] * c + q[k, 1] * s - offset
        square = residual * residual
        squares += square
        worst = max(worst, square)  # a NaN makes the rms NaN: the fit is refused
        chi_square += weights[k] * square
    return math.sqrt(squares / q.shape[0]), math.sqrt(worst), chi_square


@kernel(IN_1D, IN_1D, F64)
def split_mask(xs: FloatArray, ys: FloatArray, split_distance_m: float) -> npt.NDArray[np.bool_]:
    """Iterative end-point fit: the points the chords broke at, the first and the last
    point included, as a mask over the points."""
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


@kernel(IN_2D, IN_INDEX, F64, F64, F64)
def piece_line(moments: FloatArray, indices: IndexArray, weight: float, shift_x: float,
               shift_y: float) -> Rough:  # fmt: skip
    """The isotropic rough line of the points ``indices`` (every point weighted
    ``weight``) from their `moment_columns`, the rows added in order."""
    sums = np.zeros(6)
    for k in indices:
        for j in range(6):
            sums[j] += moments[k, j]
    return rough_line(
        weight * sums[0], weight * sums[1], weight * sums[2], weight * sums[3],
        weight * sums[4], weight * sums[5], shift_x, shift_y,
    )  # fmt: skip


@kernel(IN_2D, IN_INDEX, F64, F64, F64, F64)
def farthest(q: FloatArray, indices: IndexArray, r_m: float, alpha_rad: float, shift_x: float,
             shift_y: float) -> float:  # fmt: skip
    """The largest distance of the points from the line, from the extremes of their
    projections on its normal (so the largest of the rounded distances)."""
    c, s = math.cos(alpha_rad), math.sin(alpha_rad)
    offset = r_m - shift_x * c - shift_y * s
    low, high = math.inf, -math.inf
    for k in indices:
        along = q[k, 0] * c + q[k, 1] * s
        low, high = min(low, along), max(high, along)
    return max(high - offset, offset - low)


@kernel(IN_2D, IN_2D, F64, F64, F64, F64, IN_1D, IN_INDEX, IN_INDEX)
def merge_candidate(q: FloatArray, moments: FloatArray, weight: float, shift_x: float,
                    shift_y: float, split_distance_m: float, gates: FloatArray,
                    before: IndexArray, after: IndexArray
                   ) -> tuple[bool, float, IndexArray, Rough]:  # fmt: skip
    """Two neighbouring pieces merged, if the merged line passes both tests (its χ²
    within ``gates[n − 2]``, every point within the split distance): (passes, χ² as a
    fraction of the gate, the merged indices, its line)."""
    union = np.concatenate((before, after))
    line = piece_line(moments, union, weight, shift_x, shift_y)
    if not line[0]:
        return False, 0.0, union, line
    gate = gates[union.shape[0] - 2]
    if not line[6] <= gate:
        return False, 0.0, union, line
    if farthest(q, union, line[1], line[2], shift_x, shift_y) > split_distance_m:
        return False, 0.0, union, line
    return True, line[6] / gate, union, line


@kernel(IN_INDEX, IN_INDEX)
def _same(a: IndexArray, b: IndexArray) -> bool:
    if a.shape[0] != b.shape[0]:
        return False
    for i in range(a.shape[0]):  # noqa: SIM110 (a generator is not compiled as well)
        if a[i] != b[i]:
            return False
    return True


@kernel(IN_2D, IN_2D, F64, F64, F64, F64, I64, IN_INDEX, F64, F64, IN_INDEX, F64, F64)
def settle_corner(q: FloatArray, moments: FloatArray, weight: float, shift_x: float,
                  shift_y: float, split_distance_m: float, min_points: int,
                  before: IndexArray, before_r_m: float, before_alpha_rad: float,
                  after: IndexArray, after_r_m: float, after_alpha_rad: float
                 ) -> tuple[bool, IndexArray, Rough, IndexArray, Rough]:  # fmt: skip
    """Move the boundary between two neighbouring lines to where the points say it is:
    (moved, the first piece and its line, the second's).

    The split put the corner on one noisy point, a short piece next to it may have been
    merged to the wrong side or dropped as debris; any of these bends a fit or cuts a line
    short. With both lines fitted on their bulk, every point from the first line's start
    to the second's end is given to the line that explains it, at the single boundary that
    minimises the summed squared residuals (one cumulative sum), and a point farther than
    the split distance from its line stays out.
    """
    begin, end = before[0], after[after.shape[0] - 1] + 1
    size = end - begin
    # Not moved: no pieces (the caller keeps its own) and a line that is not found.
    nothing = np.empty(0, dtype=np.int64)
    unchanged = piece_line(moments, nothing, weight, shift_x, shift_y)
    if size < 2 * min_points:
        return False, nothing, unchanged, nothing, unchanged
    residuals = np.empty((2, size))
    for row, r_m, alpha_rad in ((0, before_r_m, before_alpha_rad), (1, after_r_m, after_alpha_rad)):
        c, s = math.cos(alpha_rad), math.sin(alpha_rad)
        offset = r_m - shift_x * c - shift_y * s
        for i in range(size):
            residuals[row, i] = abs(q[begin + i, 0] * c + q[begin + i, 1] * s - offset)
    # cost[k]: the first k points to the first line, the rest to the second.
    head = np.empty(size)
    tail = np.empty(size)
    running = 0.0
    for i in range(size):
        running += residuals[0, i] * residuals[0, i]
        head[i] = running
    running = 0.0
    for i in range(size - 1, -1, -1):
        running += residuals[1, i] * residuals[1, i]
        tail[i] = running
    boundary, lowest_cost = min_points, math.inf
    for k in range(min_points, size - min_points + 1):
        cost = head[k - 1] + tail[k]
        if math.isnan(cost):  # numpy's argmin takes the first NaN
            boundary = k
            break
        if cost < lowest_cost:
            boundary, lowest_cost = k, cost
    first = np.empty(boundary, dtype=np.int64)
    second = np.empty(size - boundary, dtype=np.int64)
    n_first = n_second = 0
    for i in range(size):
        if i < boundary and residuals[0, i] <= split_distance_m:
            first[n_first] = begin + i
            n_first += 1
        elif i >= boundary and residuals[1, i] <= split_distance_m:
            second[n_second] = begin + i
            n_second += 1
    first, second = first[:n_first], second[:n_second]
    if _same(first, before) and _same(second, after):
        return False, nothing, unchanged, nothing, unchanged
    if min(n_first, n_second) < min_points:
        return False, nothing, unchanged, nothing, unchanged
    first_line = piece_line(moments, first, weight, shift_x, shift_y)
    second_line = piece_line(moments, second, weight, shift_x, shift_y)
    if not (first_line[0] and second_line[0]):
        return False, nothing, unchanged, nothing, unchanged
    return True, first, first_line, second, second_line


@kernel(IN_1D, IN_1D, IN_2D, IN_2D, F64, F64, F64, F64, I64, IN_1D)
def split_and_merge(xs: FloatArray, ys: FloatArray, q: FloatArray, moments: FloatArray,
                    weight: float, shift_x: float, shift_y: float, split_distance_m: float,
                    min_points: int, gates: FloatArray
                   ) -> tuple[IndexArray, IndexArray, FloatArray, int]:  # fmt: skip
    """`lines.split_and_merge` of one cluster: its points ``xs``, ``ys``, their offsets
    ``q`` from (``shift_x``, ``shift_y``) and `moment_columns` of those, each point
    weighted ``weight``; ``gates[m]`` the merge's χ² gate for m degrees of freedom.
    Returns the pieces' point indices one after the other, where each piece starts in
    them (and where the last ends), their lines' `RoughLine` fields, one row each, and
    the number of debris pieces dropped."""
    breaks = np.flatnonzero(split_mask(xs, ys, split_distance_m))
    # Typed empty lists: numba takes a list's type from its first element.
    pieces = [np.arange(0, dtype=np.int64)]
    lines = [piece_line(moments, pieces[0], weight, shift_x, shift_y)]
    bounds = [(np.int64(0), np.int64(0))]
    pieces.pop()
    lines.pop()
    bounds.pop()
    if breaks.shape[0] == 1:
        bounds.append((breaks[0], breaks[0]))
    for i in range(breaks.shape[0] - 1):
        # A breakpoint (the corner) starts the piece after it; the last piece keeps both ends.
        last = breaks[i + 1] - 1 if i + 2 < breaks.shape[0] else breaks[i + 1]
        if last >= breaks[i]:
            bounds.append((breaks[i], last))
    debris = 0
    for first, last in bounds:
        if last - first + 1 < min_points:
            debris += 1
            continue
        indices = np.arange(first, last + 1, dtype=np.int64)
        line = piece_line(moments, indices, weight, shift_x, shift_y)
        if line[0]:
            pieces.append(indices)
            lines.append(line)
        else:
            debris += 1
    if len(pieces) >= 2:
        candidates = [
            merge_candidate(
                q, moments, weight, shift_x, shift_y, split_distance_m, gates, pieces[k],
                pieces[k + 1],
            )
            for k in range(len(pieces) - 1)
        ]  # fmt: skip
        while True:
            best, best_score = -1, math.inf
            for k in range(len(candidates)):
                if candidates[k][0] and (best < 0 or candidates[k][1] < best_score):
                    best, best_score = k, candidates[k][1]
            if best < 0:
                break
            pieces[best] = candidates[best][2]
            lines[best] = candidates[best][3]
            pieces.pop(best + 1)
            lines.pop(best + 1)
            candidates.pop(best)  # only the pairs with the new piece change
            for k in (best, best - 1):
                if 0 <= k < len(candidates):
                    candidates[k] = merge_candidate(
                        q, moments, weight, shift_x, shift_y, split_distance_m, gates,
                        pieces[k], pieces[k + 1],
                    )  # fmt: skip
        for k in range(len(pieces) - 1):
            moved, head, head_line, tail, tail_line = settle_corner(
                q, moments, weight, shift_x, shift_y, split_distance_m, min_points,
                pieces[k], lines[k][1], lines[k][2], pieces[k + 1], lines[k + 1][1],
                lines[k + 1][2],
            )  # fmt: skip
            if moved:
                pieces[k], lines[k] = head, head_line
                pieces[k + 1], lines[k + 1] = tail, tail_line
    offsets = np.zeros(len(pieces) + 1, dtype=np.int64)
    for k in range(len(pieces)):
        offsets[k + 1] = offsets[k] + pieces[k].shape[0]
    flat = np.empty(offsets[-1], dtype=np.int64)
    fields = np.empty((len(pieces), 6))
    for k in range(len(pieces)):
        flat[offsets[k] : offsets[k + 1]] = pieces[k]
        _, r_m, alpha_rad, spread, along_m, total, across = lines[k]
        fields[k, 0], fields[k, 1], fields[k, 2] = r_m, alpha_rad, spread
        fields[k, 3], fields[k, 4], fields[k, 5] = along_m, total, across
    return flat, offsets, fields, debris


@kernel(IN_1D, IN_1D, F64, F64, I64, IN_1D)
def cluster_lines(xs: FloatArray, ys: FloatArray, weight: float, split_distance_m: float,
                  min_points: int, gates: FloatArray
                 ) -> tuple[bool, float, float, FloatArray, FloatArray, IndexArray, IndexArray,
                            FloatArray, int]:  # fmt: skip
    """`split_and_merge` of a cluster's points as they come: (every moment finite, the
    shift the points were moved by (their mean), their offsets ``q`` from it and
    `moment_columns` of those (the weighted fits of the pieces kept read their rows),
    then `split_and_merge`'s pieces, lines and debris)."""
    n = xs.shape[0]
    shift_x = shift_y = 0.0
    for k in range(n):
        shift_x += xs[k]
        shift_y += ys[k]
    shift_x /= max(n, 1)
    shift_y /= max(n, 1)
    q = np.empty((n, 2))
    moments = np.empty((n, 6))
    finite = True
    for k in range(n):
        x, y = xs[k] - shift_x, ys[k] - shift_y
        q[k, 0], q[k, 1] = x, y
        moments[k, 0], moments[k, 1], moments[k, 2] = 1.0, x, y
        moments[k, 3], moments[k, 4], moments[k, 5] = x * x, y * y, x * y
        finite = finite and math.isfinite(x * x + y * y + x * y)
    if not finite or n == 0:
        nothing = np.empty(0, dtype=np.int64)
        return False, shift_x, shift_y, q, moments, nothing, nothing, np.empty((0, 6)), 0
    flat, offsets, fields, debris = split_and_merge(
        xs, ys, q, moments, weight, shift_x, shift_y, split_distance_m, min_points, gates
    )
    return True, shift_x, shift_y, q, moments, flat, offsets, fields, debris
