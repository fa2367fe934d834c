"""The least-squares search behind the circle fits (`circles`), as compiled kernels (`jit`).

The residual of point ``p_i`` is ``r_i = |p_i − c| − R``, over ``x = (cx, cy)`` with ``R``
given or ``x = (cx, cy, R)``. One pass over the points accumulates the pairwise sums of
the rows ``[n_x, n_y, r, c n_x, c n_y, 1]`` (``n`` the radial unit vector, ``c = r /
|p − c|``): every sum the search needs, i.e. the gradient ``Jᵀr``, the normal matrix
``JᵀJ`` and the exact Hessian ``JᵀJ + Σ c (I − n nᵀ)`` (``J = −[n_x, n_y (, 1)]``). The
search is Levenberg–Marquardt on the exact Hessian: quadratic convergence in a handful of
steps, and the damping turns it into gradient descent far from a minimum.

These run on arcs of a few dozen points, several per scan: as numpy, each step was a
dozen calls costing more than their arithmetic; compiled, a whole search costs what one
of those calls did. A kernel calls only kernels of this file (numba's cache is
invalidated by a change of the file a kernel is in, not of the files it calls into).
"""

from __future__ import annotations

import math

import numpy as np

from appliance.perception.jit import BOOL, F64, I64, IN_1D, IN_2D, OUT_1D, OUT_2D, kernel
from appliance.perception.types import FloatArray

STEP_TOLERANCE = 1e-12
ROUNDING = 1.0 + 1e-14
_TINY = 1e-300  # keeps the damped diagonal positive where a column is all zero


@kernel(IN_1D, IN_1D, F64, F64, F64, OUT_2D)
def terms(xs: FloatArray, ys: FloatArray, cx: float, cy: float, radius_m: float,
          sums: FloatArray) -> bool:  # fmt: skip
    """The pairwise sums of the rows at centre (cx, cy) and radius ``radius_m``, written
    into the 6x6 ``sums``; whether they are all finite.

    A point on the centre has no radial direction: its ``n`` is taken as 0 (its residual
    stays ``−R``). Anything else not finite is reported as such.
    """
    for i in range(6):
        for j in range(6):
            sums[i, j] = 0.0
    row = np.empty(6)
    row[5] = 1.0
    for k in range(xs.shape[0]):
        dx = xs[k] - cx
        dy = ys[k] - cy
        distance = math.hypot(dx, dy)
        inverse = 1.0 / distance if distance > 0.0 else 1.0
        residual = distance - radius_m
        nx = dx * inverse
        ny = dy * inverse
        curvature = residual * inverse
        row[0] = nx
        row[1] = ny
        row[2] = residual
        row[3] = nx * curvature
        row[4] = ny * curvature
        for i in range(6):
            ri = row[i]
            for j in range(i, 6):
                sums[i, j] += ri * row[j]
    finite = True
    for i in range(6):
        for j in range(i, 6):
            sums[j, i] = sums[i, j]
            finite = finite and math.isfinite(sums[i, j])
    return finite


@kernel(IN_1D, IN_1D, F64, F64, F64)
def residuals(xs: FloatArray, ys: FloatArray, cx: float, cy: float, radius_m: float) -> FloatArray:
    """``|p_i − c| − R`` per point."""
    out = np.empty(xs.shape[0])
    for k in range(xs.shape[0]):
        out[k] = math.hypot(xs[k] - cx, ys[k] - cy) - radius_m
    return out


# The exact Hessian is JᵀJ + Σ c (I − n nᵀ) with J = −[n_x, n_y (, 1)], the gradient Jᵀr:
# in the sums g, JᵀJ is g[i][j] over i, j in (0, 1 (, 5)), Jᵀr is −g[i][2], and the
# curvature adds g[1][4] and g[0][3] on the diagonal, −g[0][4] and −g[1][3] off it.


@kernel(F64, F64, F64, F64, F64, F64, OUT_1D)
def _solve_2x2(a: float, b: float, c: float, d: float, u: float, v: float,
               out: FloatArray) -> bool:  # fmt: skip
    """``[[a, b], [c, d]] s = [u, v]`` by Gaussian elimination with partial pivoting."""
    if abs(c) > abs(a):
        a, b, u, c, d, v = c, d, v, a, b, u
    if not abs(a) > 0.0:
        return False
    factor = c / a
    d -= factor * b
    v -= factor * u
    if not abs(d) > 0.0:
        return False
    second = v / d
    first = (u - b * second) / a
    out[0] = first
    out[1] = second
    return math.isfinite(first) and math.isfinite(second)


@kernel(OUT_2D, OUT_1D)
def _solve_3x3(rows: FloatArray, out: FloatArray) -> bool:
    """The 3x3 system of the augmented ``rows`` ``[a, b, c, u]`` (overwritten), as
    `_solve_2x2`."""
    top, middle, bottom = 0, 1, 2
    if abs(rows[1, 0]) > abs(rows[0, 0]) and abs(rows[1, 0]) >= abs(rows[2, 0]):
        top, middle = 1, 0
    elif abs(rows[2, 0]) > abs(rows[0, 0]):
        top, bottom = 2, 0
    a = rows[top, 0]
    if not abs(a) > 0.0:
        return False
    for other in (middle, bottom):
        factor = rows[other, 0] / a
        for j in range(1, 4):
            rows[other, j] -= factor * rows[top, j]
    if abs(rows[bottom, 1]) > abs(rows[middle, 1]):
        middle, bottom = bottom, middle
    if not abs(rows[middle, 1]) > 0.0:
        return False
    factor = rows[bottom, 1] / rows[middle, 1]
    rows[bottom, 2] -= factor * rows[middle, 2]
    rows[bottom, 3] -= factor * rows[middle, 3]
    if not abs(rows[bottom, 2]) > 0.0:
        return False
    third = rows[bottom, 3] / rows[bottom, 2]
    second = (rows[middle, 3] - rows[middle, 2] * third) / rows[middle, 1]
    first = (rows[top, 3] - (rows[top, 1] * second + rows[top, 2] * third)) / a
    out[0], out[1], out[2] = first, second, third
    return math.isfinite(first) and math.isfinite(second) and math.isfinite(third)


@kernel(IN_1D)
def _largest_magnitude(values: FloatArray) -> float:
    largest = 0.0
    for value in values:
        largest = max(largest, abs(value))
    return largest


@kernel(IN_2D, F64, BOOL, OUT_1D)
def step(g: FloatArray, damping: float, free: bool, out: FloatArray) -> bool:
    """The damped Newton step ``(H + λ diag(JᵀJ)) s = −Jᵀr`` over (cx, cy) or, ``free``,
    (cx, cy, R), into ``out``; False if the system is singular or the step not finite."""
    a = g[0, 0] + g[1, 4] + damping * (g[0, 0] + _TINY)
    b = g[0, 1] - g[0, 4]
    c = g[0, 1] - g[1, 3]
    d = g[1, 1] + g[0, 3] + damping * (g[1, 1] + _TINY)
    if not free:
        return _solve_2x2(a, b, c, d, g[0, 2], g[1, 2], out)
    rows = np.empty((3, 4))
    rows[0, 0], rows[0, 1], rows[0, 2], rows[0, 3] = a, b, g[0, 5], g[0, 2]
    rows[1, 0], rows[1, 1], rows[1, 2], rows[1, 3] = c, d, g[1, 5], g[1, 2]
    rows[2, 0], rows[2, 1] = g[0, 5], g[1, 5]
    rows[2, 2], rows[2, 3] = g[5, 5] + damping * (g[5, 5] + _TINY), g[2, 5]
    return _solve_3x3(rows, out)


@kernel(IN_1D, IN_1D, IN_1D, F64, I64)
def minimise(xs: FloatArray, ys: FloatArray, start: FloatArray, radius_m: float,
             max_iterations: int) -> tuple[FloatArray, FloatArray, bool]:  # fmt: skip
    """Levenberg–Marquardt on the exact Hessian from ``start``: (x, the sums at x,
    converged).

    ``start`` is (cx, cy) for a fit of the given ``radius_m``, (cx, cy, R) for a free one
    (``radius_m`` unused). Converged means the next step is below 1e-12 of the
    coordinates' size (checked before it is taken: at the minimum, rounding alone can
    make it look uphill). A singular or non-finite system ends the search unconverged.
    """
    free = start.shape[0] == 3
    x = start.copy()
    moved = np.empty_like(x)
    delta = np.empty_like(x)
    current = np.empty((6, 6))
    trial = np.empty((6, 6))
    finite = terms(xs, ys, x[0], x[1], x[2] if free else radius_m, current)
    damping = 1e-6
    for _ in range(max_iterations):
        if not finite:
            return x, current, False
        tolerance = STEP_TOLERANCE * (_largest_magnitude(x) + 1.0)
        cost = current[2, 2]
        while True:
            if step(current, damping, free, delta):
                if _largest_magnitude(delta) <= tolerance:
                    return x, current, True
                for i in range(x.shape[0]):
                    moved[i] = x[i] + delta[i]
                ok = terms(xs, ys, moved[0], moved[1], moved[2] if free else radius_m, trial)
                # Rounding may make the last tiny step look a hair uphill: allow for it.
                if ok and not trial[2, 2] > cost * ROUNDING:
                    break
            damping *= 10.0
            if damping > 1e16:
                return x, current, False
        x, moved = moved, x
        current, trial = trial, current
        finite = True
        damping = max(damping * 0.01, 1e-12)
    return x, current, False


@kernel(F64, F64, F64)
def normal_variance(sigma_m: float, floor_sigma_m: float, cos_incidence: float) -> float:
    """`ScannerModel.normal_variance` of one point (a test holds the two together)."""
    variance = sigma_m * cos_incidence
    variance *= variance
    variance += floor_sigma_m**2
    lowest = (1e-3 * sigma_m) ** 2
    return variance if floor_sigma_m**2 >= lowest else max(variance, lowest)


@kernel(IN_2D, IN_2D)
def _sandwich(outer: FloatArray, middle: FloatArray) -> FloatArray:
    """``A M A`` in loops: a 2x2 or 3x3 product is a few dozen operations, and BLAS would
    round it differently on different CPUs."""
    size = outer.shape[0]
    left = np.zeros((size, size))
    for i in range(size):
        for k in range(size):
            for j in range(size):
                left[i, j] += outer[i, k] * middle[k, j]
    result = np.zeros((size, size))
    for i in range(size):
        for k in range(size):
            for j in range(size):
                result[i, j] += left[i, k] * outer[k, j]
    return result


@kernel(IN_2D, OUT_2D)
def _inverse_symmetric(m: FloatArray, out: FloatArray) -> bool:
    """The inverse of a symmetric 2x2 or 3x3 ``m`` by cofactors into ``out``; False if
    singular."""
    if m.shape[0] == 2:
        a, b, d = m[0, 0], m[0, 1], m[1, 1]
        det = a * d - b * b
        if not (det != 0.0 and math.isfinite(det)):
            return False
        out[0, 0], out[0, 1], out[1, 0], out[1, 1] = d / det, -b / det, -b / det, a / det
        return True
    a, b, c, e, f, i = m[0, 0], m[0, 1], m[0, 2], m[1, 1], m[1, 2], m[2, 2]
    co_a, co_b, co_c = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * co_a + b * co_b + c * co_c
    if not (det != 0.0 and math.isfinite(det)):
        return False
    co_e, co_f, co_i = a * i - c * c, b * c - a * f, a * e - b * b
    out[0, 0], out[0, 1], out[0, 2] = co_a / det, co_b / det, co_c / det
    out[1, 0], out[1, 1], out[1, 2] = co_b / det, co_e / det, co_f / det
    out[2, 0], out[2, 1], out[2, 2] = co_c / det, co_f / det, co_i / det
    return True


@kernel(IN_1D, IN_1D, F64, F64, IN_1D, F64, IN_2D, F64, F64)
def covariance(xs: FloatArray, ys: FloatArray, origin_x_m: float, origin_y_m: float,
               x: FloatArray, radius_m: float, g: FloatArray, sigma_m: float,
               floor_sigma_m: float) -> tuple[FloatArray, bool]:  # fmt: skip
    """The first-order sandwich ``(JᵀJ)⁻¹ Jᵀ diag(σ_i²) J (JᵀJ)⁻¹`` over (cx, cy) or, for
    a free ``x`` (cx, cy, R), over all three, at ``x`` where the sums ``g`` were taken;
    each residual's variance from its beam's incidence on the circle (the beam from the
    scanner at ``origin``). False unless ``JᵀJ`` is invertible and the result finite."""
    size = x.shape[0]
    used = np.empty(3)
    used[2] = 1.0
    middle = np.zeros((size, size))
    for k in range(xs.shape[0]):
        dx = xs[k] - x[0]
        dy = ys[k] - x[1]
        distance = math.hypot(dx, dy)
        inverse = 1.0 / distance if distance > 0.0 else 1.0
        used[0] = dx * inverse
        used[1] = dy * inverse
        bx = xs[k] - origin_x_m
        by = ys[k] - origin_y_m
        length = math.hypot(bx, by)
        divisor = length if length > 0.0 else 1.0  # a point on the scanner has no beam
        weight = normal_variance(sigma_m, floor_sigma_m, (bx * used[0] + by * used[1]) / divisor)
        for i in range(size):
            weighted = used[i] * weight
            for j in range(size):
                middle[i, j] += weighted * used[j]
    normal = np.empty((size, size))
    index = (0, 1, 5)
    for i in range(size):
        for j in range(size):
            normal[i, j] = g[index[i], index[j]]
    outer = np.empty((size, size))
    if not _inverse_symmetric(normal, outer):
        return outer, False
    result = _sandwich(outer, middle)
    finite = True
    for i in range(size):
        for j in range(i, size):
            value = 0.5 * (result[i, j] + result[j, i])
            result[i, j] = value
            result[j, i] = value
            finite = finite and math.isfinite(value)
    return result, finite


@kernel(IN_2D)
def positive_definite_free(g: FloatArray) -> bool:
    """Whether the free fit's Hessian in the sums ``g`` is (Sylvester's criterion on its
    symmetric part)."""
    a, e, i = g[0, 0] + g[1, 4], g[1, 1] + g[0, 3], g[5, 5]
    b = g[0, 1] - 0.5 * (g[0, 4] + g[1, 3])
    c, f = g[0, 5], g[1, 5]
    return bool(
        a > 0.0
        and a * e - b * b > 0.0
        and a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) > 0.0
    )


@kernel(IN_1D, IN_1D, F64, F64, IN_1D, IN_2D, F64, F64, F64, F64)
def surely_agrees(xs: FloatArray, ys: FloatArray, origin_x_m: float, origin_y_m: float,
                  known: FloatArray, g_known: FloatArray, sigma_m: float, floor_sigma_m: float,
                  tolerance_m: float, sigmas: float) -> bool:  # fmt: skip
    """Whether the free radius surely agrees with the known one, ``known`` (cx, cy, R) a
    known-radius fit of the points with the sums ``g_known`` there (its last terms are
    the free fit's first: the same residuals); `circles.free_radius_mismatch` says why
    this settles most arcs. False means: not settled here, run the full free fit."""
    x = known.copy()
    moved = np.empty(3)
    delta = np.empty(3)
    current = g_known.copy()
    trial = np.empty((6, 6))
    for _ in range(8):
        for i in range(6):
            for j in range(6):
                if not math.isfinite(current[i, j]):
                    return False
        if not step(current, 0.0, True, delta):
            return False
        size = _largest_magnitude(delta)
        if size <= 1e-5 * (_largest_magnitude(x) + 1.0):
            if not positive_definite_free(current):
                return False
            result, ok = covariance(
                xs, ys, origin_x_m, origin_y_m, x, x[2], current, sigma_m, floor_sigma_m
            )
            if not ok:
                return False
            sigma = math.sqrt(max(result[2, 2], 0.0))
            off = abs(x[2] + delta[2] - known[2]) + 10.0 * size
            return bool(off <= tolerance_m + sigmas * 0.98 * sigma)
        for i in range(3):
            moved[i] = x[i] + delta[i]
        if not (
            terms(xs, ys, moved[0], moved[1], moved[2], trial)
            and trial[2, 2] <= current[2, 2] * ROUNDING
        ):
            return False
        x, moved = moved, x
        current, trial = trial, current
    return False


# Outcomes of the kernels below; `circles` names them as `RejectReason`s.
OK, TOO_FEW, NON_FINITE, DEGENERATE, COLLINEAR, NOT_CONVERGED = 0, 1, 2, 3, 4, 5
_RESOLUTION = 1e-10  # a spread below this fraction of the coordinates is rounding


@kernel(IN_1D, IN_1D)
def taubin(xs: FloatArray, ys: FloatArray) -> tuple[int, float, float, float]:
    """Taubin's algebraic circle fit: (outcome, cx, cy, R).

    Minimises ``Σ (A z + B x + C y + D)²`` (``z = x² + y²``) subject to the mean squared
    gradient ``4A² z̄ + B² + C² = 1`` of centred data, where ``D = −A z̄`` drops out: the
    smallest generalised eigenvector of a 3x3 problem. Data are centred and scaled to
    unit rms radius first (so ``z̄ = 1``), so any unit conditions alike.
    """
    n = xs.shape[0]
    if n < 3:
        return TOO_FEW, 0.0, 0.0, 0.0
    mean_x = mean_y = 0.0
    for k in range(n):
        if not (math.isfinite(xs[k]) and math.isfinite(ys[k])):
            return NON_FINITE, 0.0, 0.0, 0.0
        mean_x += xs[k]
        mean_y += ys[k]
    mean_x /= n
    mean_y /= n
    spread = 0.0
    for k in range(n):
        spread += (xs[k] - mean_x) ** 2 + (ys[k] - mean_y) ** 2
    scale = math.sqrt(spread / n)
    magnitude = max(abs(mean_x), abs(mean_y))
    if not (scale > _RESOLUTION * magnitude and scale > 0.0 and math.isfinite(scale)):
        return DEGENERATE, 0.0, 0.0, 0.0
    columns = np.empty((n, 3))
    for k in range(n):
        u, v = (xs[k] - mean_x) / scale, (ys[k] - mean_y) / scale
        columns[k, 0], columns[k, 1], columns[k, 2] = u * u + v * v, u, v
    z_mean = 0.0
    for k in range(n):
        z_mean += columns[k, 0]
    z_mean /= n
    half = np.array([0.5, 1.0, 1.0])
    symmetric = np.zeros((3, 3))
    for k in range(n):
        columns[k, 0] -= z_mean
        for i in range(3):
            for j in range(3):
                symmetric[i, j] += columns[k, i] * columns[k, j]
    # T = diag(4 z̄, 1, 1), z̄ = 1: solve T^-1/2 K T^-1/2 b = η b, then a = T^-1/2 b.
    for i in range(3):
        for j in range(3):
            symmetric[i, j] *= half[i] * half[j] / n
            if not math.isfinite(symmetric[i, j]):
                return NON_FINITE, 0.0, 0.0, 0.0
    _, vectors = np.linalg.eigh(symmetric)
    a, b, c = vectors[0, 0] * half[0], vectors[1, 0] * half[1], vectors[2, 0] * half[2]
    if not abs(a) > 1e-9:
        return COLLINEAR, 0.0, 0.0, 0.0
    cx = mean_x - scale * b / (2.0 * a)
    cy = mean_y - scale * c / (2.0 * a)
    radius = scale / (2.0 * abs(a))
    if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(radius)):
        return NON_FINITE, 0.0, 0.0, 0.0
    return OK, cx, cy, radius


@kernel(IN_1D, IN_1D, F64, F64, F64, F64, F64, BOOL, I64)
def known_radius_fit(xs: FloatArray, ys: FloatArray, origin_x_m: float, origin_y_m: float,
                     radius_m: float, start_x_m: float, start_y_m: float, has_start: bool,
                     max_iterations: int) -> tuple[int, FloatArray, FloatArray]:  # fmt: skip
    """The known-radius search (outcome, centre, the sums there), from ``start`` if
    ``has_start`` (a refit after dropping a point starts from the previous centre), else
    or then from the arc's middle point pushed back along its beam by the radius, then
    from Taubin's centre."""
    n = xs.shape[0]
    if n < 2:
        return TOO_FEW, np.zeros(2), np.zeros((6, 6))
    for k in range(n):
        if not (math.isfinite(xs[k]) and math.isfinite(ys[k])):
            return NON_FINITE, np.zeros(2), np.zeros((6, 6))
    guess = np.empty(2)
    if has_start:
        guess[0], guess[1] = start_x_m, start_y_m
        x, sums, converged = minimise(xs, ys, guess, radius_m, max_iterations)
        if converged:
            return OK, x, sums
    mx, my = xs[n // 2], ys[n // 2]
    bx, by = mx - origin_x_m, my - origin_y_m
    length = math.hypot(bx, by)
    if length > 0.0:
        guess[0], guess[1] = mx + radius_m * bx / length, my + radius_m * by / length
        x, sums, converged = minimise(xs, ys, guess, radius_m, max_iterations)
        if converged:
            return OK, x, sums
    outcome, guess[0], guess[1], _ = taubin(xs, ys)
    if outcome == OK:
        x, sums, converged = minimise(xs, ys, guess, radius_m, max_iterations)
        if converged:
            return OK, x, sums
    return NOT_CONVERGED, guess, np.zeros((6, 6))


@kernel(IN_1D, IN_1D, F64, F64, IN_1D, F64, IN_2D, F64, F64)
def fit_figures(xs: FloatArray, ys: FloatArray, origin_x_m: float, origin_y_m: float,
                x: FloatArray, radius_m: float, g: FloatArray, sigma_m: float,
                floor_sigma_m: float) -> tuple[bool, FloatArray, FloatArray, float]:  # fmt: skip
    """What a converged fit reports at ``x`` (sums ``g``): (the centre determined, its
    `covariance`, the residuals, their rms)."""
    centre, determined = covariance(
        xs, ys, origin_x_m, origin_y_m, x, radius_m, g, sigma_m, floor_sigma_m
    )
    return (
        determined,
        centre,
        residuals(xs, ys, x[0], x[1], radius_m),
        math.sqrt(g[2, 2] / xs.shape[0]),
    )


@kernel(IN_1D, IN_1D, F64, F64, F64, I64, I64, F64, F64, F64)
def trimmed_arc(xs: FloatArray, ys: FloatArray, origin_x_m: float, origin_y_m: float,
                radius_m: float, max_iterations: int, min_points: int, edge_limit_m: float,
                sigma_m: float, floor_sigma_m: float
                ) -> tuple[int, int, int, FloatArray, FloatArray, FloatArray, float,
                           float]:  # fmt: skip
    """The known-radius fit of an arc, an end point farther off the circle than
    ``edge_limit_m`` dropped (the farther end first) and the rest refitted from there,
    while more than ``min_points`` remain: (outcome, first, stop of the points kept,
    centre, its covariance, the sums there, residual rms, the points' mean range).

    Why: a mixed echo at an end, the beam's footprint straddling the cylinder's edge,
    pulls the centre off (`cylinders`)."""
    first, stop = 0, xs.shape[0]
    has_start, start_x, start_y = False, 0.0, 0.0
    while True:
        part_x, part_y = xs[first:stop], ys[first:stop]
        outcome, x, sums = known_radius_fit(
            part_x, part_y, origin_x_m, origin_y_m, radius_m, start_x, start_y, has_start,
            max_iterations,
        )  # fmt: skip
        if outcome != OK:
            return outcome, first, stop, x, np.zeros((2, 2)), sums, 0.0, 0.0
        determined, centre, fitted, rms = fit_figures(
            part_x, part_y, origin_x_m, origin_y_m, x, radius_m, sums, sigma_m, floor_sigma_m
        )
        if not determined:
            return DEGENERATE, first, stop, x, centre, sums, 0.0, 0.0
        if not (math.isfinite(rms) and math.isfinite(x[0]) and math.isfinite(x[1])):
            return NON_FINITE, first, stop, x, centre, sums, rms, 0.0
        end_first, end_last = abs(fitted[0]), abs(fitted[fitted.shape[0] - 1])
        if stop - first <= min_points or max(end_first, end_last) <= edge_limit_m:
            break
        if end_first >= end_last:
            first += 1
        else:
            stop -= 1
        has_start, start_x, start_y = True, x[0], x[1]
    total = 0.0
    for k in range(first, stop):
        total += math.hypot(xs[k] - origin_x_m, ys[k] - origin_y_m)
    return OK, first, stop, x, centre, sums, rms, total / (stop - first)


def coordinates(xy_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    return np.ascontiguousarray(xy_m[:, 0]), np.ascontiguousarray(xy_m[:, 1])
