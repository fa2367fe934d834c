"""The least-squares search behind the circle fits (`circles`), in plain floats where
numpy would cost more than the arithmetic.

The residual of point ``p_i`` is ``r_i = |p_i − c| − R``, over ``x = (cx, cy)`` with ``R``
given or ``x = (cx, cy, R)``. One matrix product of the rows ``[n_x, n_y, r, c n_x, c n_y,
1]`` (``n`` the radial unit vector, ``c = r / |p − c|``) gives every sum the search needs:
the gradient ``Jᵀr``, the normal matrix ``JᵀJ`` and the exact Hessian ``JᵀJ + Σ c (I − n
nᵀ)`` (``J = −[n_x, n_y (, 1)]``). The 2x2/3x3 algebra on those sums is done in floats:
these fits run on a few dozen points, and the search is Levenberg–Marquardt on the exact
Hessian (quadratic convergence in a handful of steps; the damping turns it into gradient
descent far from a minimum).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from appliance.perception.types import FloatArray, ScannerModel

STEP_TOLERANCE = 1e-12
ROUNDING = 1.0 + 1e-14


class Evaluation(NamedTuple):
    """The residuals' terms at one point of the search: the rows ``[n_x, n_y, r, c n_x,
    c n_y, 1]`` (``n`` the radial unit vector, ``r`` the residual ``|p − c| − R``,
    ``c = r / |p − c|``), one column per point, and all their pairwise sums: one matrix
    product gives every sum the gradient, the exact Hessian and the cost need."""

    rows: FloatArray  # (6, n)
    sums: list[list[float]]  # rows @ rows.T
    finite: bool


def evaluate(xs: FloatArray, ys: FloatArray, x: list[float], radius_m: float) -> Evaluation:
    """The terms at ``x``; the caller has silenced numpy's floating-point warnings.

    A dozen numpy calls on a few dozen points, each costing more than its arithmetic:
    the intermediate arrays are written into the rows themselves.
    """
    rows = np.empty((6, xs.shape[0]))
    dx = np.subtract(xs, x[0], out=rows[0])
    dy = np.subtract(ys, x[1], out=rows[1])
    distance = np.hypot(dx, dy)
    inverse = 1.0 / distance
    residuals = np.subtract(distance, radius_m, out=rows[2])
    dx *= inverse
    dy *= inverse
    inverse *= residuals
    np.multiply(dx, inverse, out=rows[3])  # two 1-D products cost less than one of 2-D
    np.multiply(dy, inverse, out=rows[4])
    rows[5] = 1.0
    sums: list[list[float]] = (rows @ rows.T).tolist()
    # Every sum is finite when the diagonal is (Cauchy–Schwarz).
    if not math.isfinite(sums[0][0] + sums[1][1] + sums[2][2] + sums[3][3] + sums[4][4]):
        return _evaluate_with_centre_points(xs, ys, x, radius_m)
    return Evaluation(rows, sums, True)


def _evaluate_with_centre_points(
    xs: FloatArray, ys: FloatArray, x: list[float], radius_m: float
) -> Evaluation:
    """`_evaluate` when some sum is not finite: a point on the centre has no radial
    direction (its ``n`` is taken as 0, its residual stays ``−R``), and anything else
    not finite is reported as such."""
    rows = np.empty((6, xs.shape[0]))
    dx, dy = xs - x[0], ys - x[1]
    distance = np.hypot(dx, dy)
    inverse = 1.0 / np.where(distance > 0.0, distance, 1.0)
    rows[0], rows[1] = dx * inverse, dy * inverse
    rows[2] = distance - radius_m
    rows[3:5] = rows[0:2] * (rows[2] * inverse)
    rows[5] = 1.0
    sums = rows @ rows.T
    return Evaluation(rows, sums.tolist(), bool(np.isfinite(sums).all()))


# The exact Hessian is JᵀJ + Σ c (I − n nᵀ) with J = −[n_x, n_y (, 1)], the gradient Jᵀr:
# in the sums g, JᵀJ is g[i][j] over i, j in (0, 1 (, 5)), Jᵀr is −g[i][2], and the
# curvature adds g[1][4] and g[0][3] on the diagonal, −g[0][4] and −g[1][3] off it.


def step_known_radius(g: list[list[float]], damping: float) -> list[float] | None:
    """The damped Newton step over (cx, cy): ``(H + λ diag(JᵀJ)) s = −Jᵀr``."""
    g0, g1 = g[0], g[1]
    return _solve_2x2(
        g0[0] + g1[4] + damping * (g0[0] + 1e-300),
        g0[1] - g0[4],
        g0[1] - g1[3],
        g1[1] + g0[3] + damping * (g1[1] + 1e-300),
        g0[2],
        g1[2],
    )


def step_free(g: list[list[float]], damping: float) -> list[float] | None:
    """The damped Newton step over (cx, cy, R)."""
    g0, g1, g5 = g[0], g[1], g[5]
    return _solve_3x3(
        [g0[0] + g1[4] + damping * (g0[0] + 1e-300), g0[1] - g0[4], g0[5], g0[2]],
        [g0[1] - g1[3], g1[1] + g0[3] + damping * (g1[1] + 1e-300), g1[5], g1[2]],
        [g0[5], g1[5], g5[5] + damping * (g5[5] + 1e-300), g[2][5]],
    )


def _solve_2x2(a: float, b: float, c: float, d: float, u: float, v: float) -> list[float] | None:
    """``[[a, b], [c, d]] s = [u, v]`` by Gaussian elimination with partial pivoting;
    None if singular or not finite."""
    if abs(c) > abs(a):
        a, b, u, c, d, v = c, d, v, a, b, u
    if not abs(a) > 0.0:
        return None
    factor = c / a
    d -= factor * b
    v -= factor * u
    if not abs(d) > 0.0:
        return None
    second = v / d
    first = (u - b * second) / a
    return [first, second] if math.isfinite(first) and math.isfinite(second) else None


def _solve_3x3(r0: list[float], r1: list[float], r2: list[float]) -> list[float] | None:
    """The 3x3 system of the augmented rows ``[a, b, c, u]``, as `_solve_2x2`."""
    if abs(r1[0]) > abs(r0[0]) and abs(r1[0]) >= abs(r2[0]):
        r0, r1 = r1, r0
    elif abs(r2[0]) > abs(r0[0]):
        r0, r2 = r2, r0
    if not abs(r0[0]) > 0.0:
        return None
    a, b, c, u = r0
    for row in (r1, r2):
        factor = row[0] / a
        row[1] -= factor * b
        row[2] -= factor * c
        row[3] -= factor * u
    if abs(r2[1]) > abs(r1[1]):
        r1, r2 = r2, r1
    if not abs(r1[1]) > 0.0:
        return None
    factor = r2[1] / r1[1]
    r2[2] -= factor * r1[2]
    r2[3] -= factor * r1[3]
    if not abs(r2[2]) > 0.0:
        return None
    third = r2[3] / r2[2]
    second = (r1[3] - r1[2] * third) / r1[1]
    first = (u - (b * second + c * third)) / a
    solution = [first, second, third]
    return solution if all(math.isfinite(v) for v in solution) else None


def minimise(
    xs: FloatArray, ys: FloatArray, start: list[float], radius_m: float | None, max_iterations: int
) -> tuple[list[float], Evaluation, bool]:
    """Levenberg–Marquardt on the exact Hessian from ``start``: (x, its terms, converged).

    ``xs``, ``ys`` are the points' coordinates (contiguous); numpy's floating-point
    warnings are the caller's to silence. Converged means the next step is below 1e-12
    of the coordinates' size (checked before it is taken: at the minimum, rounding
    alone can make it look uphill). Never raises: a singular or non-finite system ends
    the search unconverged.
    """
    step_of = step_free if radius_m is None else step_known_radius
    x = [float(v) for v in start]
    current = evaluate(xs, ys, x, x[2] if radius_m is None else radius_m)
    damping = 1e-6
    for _ in range(max_iterations):
        if not current.finite:
            return x, current, False
        tolerance = STEP_TOLERANCE * (max(map(abs, x)) + 1.0)
        cost = current.sums[2][2]
        while True:
            step = step_of(current.sums, damping)
            if step is not None:
                if max(map(abs, step)) <= tolerance:
                    return x, current, True
                moved = [a + b for a, b in zip(x, step, strict=True)]
                trial = evaluate(xs, ys, moved, moved[2] if radius_m is None else radius_m)
                # Rounding may make the last tiny step look a hair uphill: allow for it.
                if trial.finite and not trial.sums[2][2] > cost * ROUNDING:
                    break
            damping *= 10.0
            if damping > 1e16:
                return x, current, False
        x, current = moved, trial
        damping = max(damping * 0.01, 1e-12)
    return x, current, False


class Beams(NamedTuple):
    """The fitted points as coordinates (contiguous) and their beams from the scanner:
    the same at every step of a search, and for both fits of one arc (the known radius
    and the free radius' check), so worked out once."""

    xs: FloatArray
    ys: FloatArray
    bx: FloatArray  # the beam: the point less the scanner's position
    by: FloatArray
    length: FloatArray  # its length: the point's distance from the scanner
    divisor: FloatArray  # the length, 1 for a point on the scanner (it has no beam)
    origin_xy_m: tuple[float, float]


def beams(xs: FloatArray, ys: FloatArray, origin_xy_m: tuple[float, float]) -> Beams:
    """`Beams` of the points ``xs``, ``ys`` seen from ``origin_xy_m``."""
    bx, by = xs - origin_xy_m[0], ys - origin_xy_m[1]
    length = np.hypot(bx, by)
    # A point has a beam unless it is on the scanner (or not finite): the usual case costs
    # one minimum, not a copy.
    if length.shape[0] and np.minimum.reduce(length) > 0.0:
        divisor = length
    else:
        divisor = np.where(length > 0.0, length, 1.0)
    return Beams(xs, ys, bx, by, length, divisor, origin_xy_m)


def centre_covariance(
    points: Beams, terms: Evaluation, free: bool, scanner: ScannerModel
) -> FloatArray | None:
    """The first-order sandwich ``(JᵀJ)⁻¹ Jᵀ diag(σ_i²) J (JᵀJ)⁻¹`` over (cx, cy (, R)),
    with each residual's variance from its beam's incidence on the circle; None unless
    ``JᵀJ`` is invertible and the result finite."""
    radial = terms.rows
    cos_incidence = (points.bx * radial[0] + points.by * radial[1]) / points.divisor
    used = terms.rows[[0, 1, 5]] if free else terms.rows[0:2]
    middle = (used * scanner.normal_variance(cos_incidence)) @ used.T
    g0, g1, g5 = terms.sums[0], terms.sums[1], terms.sums[5]
    if not free:
        return _sandwich_2x2(_inverse_2x2(g0[0], g0[1], g1[1]), middle.tolist())
    inverse = _inverse_3x3(g0[0], g0[1], g0[5], g1[1], g1[5], g5[5])
    if inverse is None:
        return None
    outer = np.array(inverse)
    covariance: FloatArray = outer @ middle @ outer
    covariance = 0.5 * (covariance + covariance.T)
    return covariance if np.isfinite(covariance).all() else None


def radius_variance(points: Beams, terms: Evaluation, scanner: ScannerModel) -> float | None:
    """The free fit's ``var R``: the last diagonal entry of `centre_covariance`, with its
    3x3 sandwich in floats (numpy's products of 3x3 matrices cost more than their
    arithmetic). It only decides whether a free radius surely agrees
    (`circles.free_radius_mismatch`), a test with a 2 % margin on σ, which products
    rounded differently move by parts in 10¹⁶; None where `centre_covariance` is."""
    radial = terms.rows
    cos_incidence = (points.bx * radial[0] + points.by * radial[1]) / points.divisor
    used = terms.rows[[0, 1, 5]]
    middle = ((used * scanner.normal_variance(cos_incidence)) @ used.T).tolist()
    g0, g1, g5 = terms.sums[0], terms.sums[1], terms.sums[5]
    inverse = _inverse_3x3(g0[0], g0[1], g0[5], g1[1], g1[5], g5[5])
    if inverse is None:
        return None
    if not all(map(math.isfinite, (*middle[0], *middle[1], *middle[2], *inverse[0],
                                   *inverse[1], *inverse[2]))):  # fmt: skip
        return None
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = middle
    k0, k1, k2 = inverse[2]  # the last row of the symmetric inverse: its last column
    variance = (
        k0 * (m00 * k0 + m01 * k1 + m02 * k2)
        + k1 * (m10 * k0 + m11 * k1 + m12 * k2)
        + k2 * (m20 * k0 + m21 * k1 + m22 * k2)
    )
    return variance if math.isfinite(variance) else None


def _sandwich_2x2(
    inverse: list[list[float]] | None, middle: list[list[float]]
) -> FloatArray | None:
    """``A M A`` (symmetrised) for the 2x2 case, in floats; None unless finite."""
    if inverse is None:
        return None
    (a, b), (_, d) = inverse
    (p, q), (r, s) = middle
    row0, row1 = (a * p + b * r, a * q + b * s), (b * p + d * r, b * q + d * s)
    xx, yy = row0[0] * a + row0[1] * b, row1[0] * b + row1[1] * d
    xy = 0.5 * ((row0[0] * b + row0[1] * d) + (row1[0] * a + row1[1] * b))
    if not (math.isfinite(xx) and math.isfinite(yy) and math.isfinite(xy)):
        return None
    return np.array([[xx, xy], [xy, yy]])


def _inverse_2x2(a: float, b: float, d: float) -> list[list[float]] | None:
    """The inverse of ``[[a, b], [b, d]]`` by cofactors; None if singular."""
    det = a * d - b * b
    if not (det != 0.0 and math.isfinite(det)):
        return None
    return [[d / det, -b / det], [-b / det, a / det]]


def _inverse_3x3(
    a: float, b: float, c: float, e: float, f: float, i: float
) -> list[list[float]] | None:
    """The inverse of the symmetric ``[[a, b, c], [b, e, f], [c, f, i]]``; None if singular."""
    co_a, co_b, co_c = e * i - f * f, c * f - b * i, b * f - c * e
    det = a * co_a + b * co_b + c * co_c
    if not (det != 0.0 and math.isfinite(det)):
        return None
    co_e, co_f, co_i = a * i - c * c, b * c - a * f, a * e - b * b
    return [
        [co_a / det, co_b / det, co_c / det],
        [co_b / det, co_e / det, co_f / det],
        [co_c / det, co_f / det, co_i / det],
    ]


def coordinates(xy_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    return np.ascontiguousarray(xy_m[:, 0]), np.ascontiguousarray(xy_m[:, 1])


def positive_definite_free(g: list[list[float]]) -> bool:
    """Whether the free fit's Hessian in the sums ``g`` is (Sylvester's criterion on its
    symmetric part)."""
    g0, g1, g5 = g[0], g[1], g[5]
    a, e, i = g0[0] + g1[4], g1[1] + g0[3], g5[5]
    b = g0[1] - 0.5 * (g0[4] + g1[3])
    c, f = g0[5], g1[5]
    return (
        a > 0.0
        and a * e - b * b > 0.0
        and a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) > 0.0
    )
