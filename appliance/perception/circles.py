"""Cylindrical landmarks: circle fits to short arcs, and the checks that make one a landmark.

**Fits.** The landmark's radius is known (Qian et al.'s launcher: one size of pipe), so
the centre is fitted alone: an orthogonal-distance fit (residual ``|p_i − c| − R``) on
the two centre coordinates, started from the arc's middle point pushed back along its
beam by ``R`` (Taubin's algebraic fit is the second start). With two unknowns instead of
three, seven noisy points at 10 m still pin the centre, where a free radius wanders by
centimetres. The full three-parameter geometric fit, started from Taubin (never from
Kåsa's fit, which shrinks short arcs), checks the radius when the arc has points enough
to say something. The solver is Levenberg–Marquardt on the exact Hessian (``JᵀJ`` plus
the residual curvature ``Σ r_i (I − n_i n_iᵀ)/|p_i − c|``): quadratic convergence in a
handful of steps, and the damping turns it into gradient descent far from a minimum.

**Covariance.** The fit is unweighted, but the noise is not isotropic: a point's range
error lies along its beam, so its residual has variance ``σ_r² (u_i·n_i)² + σ_floor²``
(``n_i`` the radial direction at the point): large where the beam meets the cylinder
head-on, small at the edges where it grazes. The centre's covariance is therefore the
first-order sandwich ``(JᵀJ)⁻¹ Jᵀ diag(σ_i²) J (JᵀJ)⁻¹`` at the solution, which is
``σ² (JᵀJ)⁻¹`` when every ``σ_i = σ``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.perception.types import (
    FitRejection,
    FloatArray,
    RejectReason,
    ScannerModel,
)

_STEP_TOLERANCE = 1e-12
_ROUNDING = 1.0 + 1e-14
# A spread below this fraction of the coordinates is rounding, not geometry.
_RESOLUTION = 1e-10


@dataclass(frozen=True, eq=False)
class CircleFit:
    """A fitted circle: centre, radius, the centre's covariance, the radius' σ (0 when
    the radius was given), residual rms and how many points it used."""

    cx_m: float
    cy_m: float
    radius_m: float
    covariance: FloatArray  # 2x2 over (cx_m, cy_m)
    radius_sigma_m: float
    rms_m: float
    n_points: int
    residuals_m: FloatArray


def taubin_circle(xy_m: FloatArray) -> tuple[float, float, float] | FitRejection:
    """Taubin's algebraic circle fit: (cx, cy, R), or why there is none.

    Minimises ``Σ (A z + B x + C y + D)²`` (``z = x² + y²``) subject to the mean
    squared gradient ``4A² z̄ + B² + C² = 1`` of centred data, where ``D = −A z̄``
    drops out: the smallest generalised eigenvector of a 3x3 problem. Data are centred
    and scaled to unit rms radius first (so ``z̄ = 1``), so any unit conditions alike.
    """
    n = int(xy_m.shape[0])
    if n < 3:
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{n} point(s)")
    with np.errstate(all="ignore"):
        if not np.isfinite(xy_m).all():
            return FitRejection(RejectReason.NON_FINITE)
        centroid = xy_m.mean(axis=0)
        offsets = xy_m - centroid
        scale = math.sqrt(float(np.mean(np.sum(offsets * offsets, axis=1))))
        magnitude = float(np.max(np.abs(centroid)))
        if not (scale > _RESOLUTION * magnitude and scale > 0.0 and math.isfinite(scale)):
            return FitRejection(RejectReason.DEGENERATE, "coincident points")
        u = offsets / scale
        z = np.sum(u * u, axis=1)
        columns = np.stack([z - z.mean(), u[:, 0], u[:, 1]], axis=1)
        moments = columns.T @ columns / n
        # T = diag(4 z̄, 1, 1), z̄ = 1: solve T^-1/2 K T^-1/2 b = η b, then a = T^-1/2 b.
        half = np.array([0.5, 1.0, 1.0])
        symmetric = moments * np.outer(half, half)
        if not np.isfinite(symmetric).all():
            return FitRejection(RejectReason.NON_FINITE)
        _, vectors = np.linalg.eigh(symmetric)
        a, b, c = vectors[:, 0] * half
        if not abs(a) > 1e-9:
            return FitRejection(RejectReason.COLLINEAR, "the points lie on a line")
        cx = float(centroid[0] - scale * b / (2.0 * a))
        cy = float(centroid[1] - scale * c / (2.0 * a))
        radius = float(scale / (2.0 * abs(a)))
    if not all(math.isfinite(v) for v in (cx, cy, radius)):
        return FitRejection(RejectReason.NON_FINITE)
    return cx, cy, radius


class _Terms:
    """Residuals, gradient and exact Hessian of ``½ Σ (|p_i − c| − R)²`` at
    ``x = (cx, cy)`` with ``R`` given, or ``x = (cx, cy, R)``.

    One matrix product of the columns ``[n_x, n_y, r, c n_x, c n_y, 1]`` (``n`` the
    radial unit vector, ``r`` the residual, ``c = r / |p − c|``) gives every sum needed,
    and the 2x2/3x3 algebra is done in plain floats: these fits run on a few dozen
    points, where each numpy call costs more than its arithmetic.
    """

    def __init__(self, xy_m: FloatArray, x: list[float], radius_m: float | None) -> None:
        offsets = xy_m - np.array(x[:2])
        distance = np.hypot(offsets[:, 0], offsets[:, 1])
        inverse = 1.0 / np.where(distance > 0.0, distance, 1.0)
        columns = np.empty((xy_m.shape[0], 6))
        np.multiply(offsets, inverse[:, np.newaxis], out=columns[:, 0:2])
        np.subtract(distance, x[2] if radius_m is None else radius_m, out=columns[:, 2])
        np.multiply(columns[:, 0:2], (columns[:, 2] * inverse)[:, np.newaxis], out=columns[:, 3:5])
        columns[:, 5] = 1.0
        self.columns = columns
        sums = columns.T @ columns
        self.finite = bool(np.isfinite(sums).all())
        g = sums.tolist()
        self.cost: float = g[2][2]
        # J = -[n_x, n_y (, 1)]: gradient Jᵀr, normal matrix JᵀJ, Hessian JᵀJ + Σ c (I − n nᵀ).
        self.gradient = [-g[0][2], -g[1][2]]
        self.normal = [[g[0][0], g[0][1]], [g[0][1], g[1][1]]]
        if radius_m is None:
            self.gradient.append(-g[2][5])
            self.normal[0].append(g[0][5])
            self.normal[1].append(g[1][5])
            self.normal.append([g[0][5], g[1][5], g[5][5]])
        self.hessian = [row[:] for row in self.normal]
        self.hessian[0][0] += g[1][4]
        self.hessian[0][1] -= g[0][4]
        self.hessian[1][0] -= g[1][3]
        self.hessian[1][1] += g[0][3]

    @property
    def radial(self) -> FloatArray:
        radial: FloatArray = self.columns[:, 0:2]
        return radial

    @property
    def residuals(self) -> FloatArray:
        residuals: FloatArray = self.columns[:, 2]
        return residuals

    def jacobian(self, known_radius: bool) -> FloatArray:
        jacobian: FloatArray = (
            -self.columns[:, 0:2] if known_radius else -self.columns[:, [0, 1, 5]]
        )
        return jacobian


def _solve_small(matrix: list[list[float]], vector: list[float]) -> list[float] | None:
    """Gaussian elimination with partial pivoting for the 2x2/3x3 systems here; None if
    singular or not finite."""
    size = len(vector)
    rows = [[*matrix[i], vector[i]] for i in range(size)]
    for col in range(size):
        pivot = max(range(col, size), key=lambda r: abs(rows[r][col]))
        if not abs(rows[pivot][col]) > 0.0:
            return None
        rows[col], rows[pivot] = rows[pivot], rows[col]
        for r in range(col + 1, size):
            factor = rows[r][col] / rows[col][col]
            for c in range(col, size + 1):
                rows[r][c] -= factor * rows[col][c]
    solution = [0.0] * size
    for r in range(size - 1, -1, -1):
        tail = sum(rows[r][c] * solution[c] for c in range(r + 1, size))
        solution[r] = (rows[r][size] - tail) / rows[r][r]
    return solution if all(math.isfinite(v) for v in solution) else None


def minimise_circle(
    xy_m: FloatArray, start: FloatArray, radius_m: float | None, max_iterations: int
) -> tuple[FloatArray, _Terms, bool]:
    """Levenberg–Marquardt on the exact Hessian from ``start``: (x, its terms, converged).

    Converged means the next step is below 1e-12 of the coordinates' size (checked
    before it is taken: at the minimum, rounding alone can make it look uphill). Never
    raises: a singular or non-finite system ends the search unconverged.
    """
    x = [float(v) for v in start]
    terms = _Terms(xy_m, x, radius_m)
    damping = 1e-6
    for _ in range(max_iterations):
        if not terms.finite:
            return np.array(x), terms, False
        tolerance = _STEP_TOLERANCE * (max(abs(v) for v in x) + 1.0)
        minus_gradient = [-v for v in terms.gradient]
        accepted: tuple[list[float], _Terms] | None = None
        while accepted is None:
            damped = [row[:] for row in terms.hessian]
            for i, row in enumerate(damped):
                row[i] += damping * (terms.normal[i][i] + 1e-300)
            step = _solve_small(damped, minus_gradient)
            if step is not None and max(abs(v) for v in step) <= tolerance:
                return np.array(x), terms, True
            trial = None if step is None else _Terms(xy_m, _add(x, step), radius_m)
            # Rounding may make the last tiny step look a hair uphill: allow for that.
            uphill = trial is None or not trial.finite or trial.cost > terms.cost * _ROUNDING
            if step is not None and trial is not None and not uphill:
                accepted = (step, trial)
                continue
            damping *= 10.0
            if damping > 1e16:
                return np.array(x), terms, False
        x, terms = _add(x, accepted[0]), accepted[1]
        damping = max(damping * 0.01, 1e-12)
    return np.array(x), terms, False


def _add(x: list[float], step: list[float]) -> list[float]:
    return [a + b for a, b in zip(x, step, strict=True)]


def _sandwich(jacobian: FloatArray, variance: FloatArray) -> FloatArray | None:
    """First-order covariance of an unweighted least-squares estimate."""
    try:
        inverse = np.linalg.inv(jacobian.T @ jacobian)
    except np.linalg.LinAlgError:
        return None
    covariance: FloatArray = inverse @ (jacobian.T * variance) @ jacobian @ inverse
    covariance = 0.5 * (covariance + covariance.T)
    return covariance if np.isfinite(covariance).all() else None


def _finish_fit(
    xy_m: FloatArray,
    x: FloatArray,
    terms: _Terms,
    radius_m: float | None,
    origin_xy_m: tuple[float, float],
    scanner: ScannerModel,
) -> CircleFit | FitRejection:
    beams = xy_m - np.asarray(origin_xy_m)
    length = np.hypot(beams[:, 0], beams[:, 1])
    cos_incidence = np.sum(beams * terms.radial, axis=1) / np.where(length > 0.0, length, 1.0)
    covariance = _sandwich(
        terms.jacobian(radius_m is not None), scanner.normal_variance(cos_incidence)
    )
    if covariance is None:
        return FitRejection(RejectReason.DEGENERATE, "the centre is not determined")
    radius = float(x[2]) if radius_m is None else radius_m
    radius_sigma = 0.0 if radius_m is not None else math.sqrt(max(float(covariance[2, 2]), 0.0))
    rms = math.sqrt(terms.cost / xy_m.shape[0])
    if not (math.isfinite(rms) and math.isfinite(radius_sigma) and np.isfinite(x).all()):
        return FitRejection(RejectReason.NON_FINITE)
    return CircleFit(
        float(x[0]),
        float(x[1]),
        radius,
        covariance[:2, :2],
        radius_sigma,
        rms,
        int(xy_m.shape[0]),
        terms.residuals.copy(),
    )


def fit_circle_known_radius(
    xy_m: FloatArray,
    radius_m: float,
    origin_xy_m: tuple[float, float],
    scanner: ScannerModel,
    max_iterations: int = 50,
    start: tuple[float, float] | None = None,
) -> CircleFit | FitRejection:
    """Geometric fit of a circle of given radius: the centre and its covariance.

    ``origin_xy_m`` is the scanner's position in the points' frame: it gives each
    point's beam direction for the start and the covariance. ``start`` is tried first
    (a refit after dropping a point starts from the previous centre). Never raises.
    """
    n = int(xy_m.shape[0])
    if n < 2:
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{n} point(s)")
    with np.errstate(all="ignore"):
        if not np.isfinite(xy_m).all():
            return FitRejection(RejectReason.NON_FINITE)
        middle = xy_m[n // 2]
        beam = middle - np.asarray(origin_xy_m)
        length = math.hypot(float(beam[0]), float(beam[1]))
        starts: list[FloatArray | None] = (
            [] if start is None else [np.array(start, dtype=np.float64)]
        )
        if length > 0.0:
            starts.append(middle + radius_m * beam / length)
        starts.append(None)  # Taubin's centre, computed only if the others fail
        for guess in starts:
            if guess is None:
                algebraic = taubin_circle(xy_m)
                if isinstance(algebraic, FitRejection):
                    break
                guess = np.array(algebraic[:2])
            centre, terms, converged = minimise_circle(xy_m, guess, radius_m, max_iterations)
            if converged:
                return _finish_fit(xy_m, centre, terms, radius_m, origin_xy_m, scanner)
    return FitRejection(RejectReason.NOT_CONVERGED)


def fit_circle_free(
    xy_m: FloatArray,
    origin_xy_m: tuple[float, float],
    scanner: ScannerModel,
    max_iterations: int = 50,
    start: tuple[float, float, float] | None = None,
) -> CircleFit | FitRejection:
    """Geometric fit of centre and radius (three unknowns), started from Taubin's fit
    or from ``start`` (cx, cy, R), e.g. a known-radius fit of the same points."""
    if start is None:
        algebraic = taubin_circle(xy_m)
        if isinstance(algebraic, FitRejection):
            return algebraic
        start = algebraic
    if xy_m.shape[0] < 3:
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{xy_m.shape[0]} point(s)")
    with np.errstate(all="ignore"):
        if not np.isfinite(xy_m).all():
            return FitRejection(RejectReason.NON_FINITE)
        x, terms, converged = minimise_circle(xy_m, np.array(start), None, max_iterations)
        if not (converged and x[2] > 0.0):
            return FitRejection(RejectReason.NOT_CONVERGED)
        return _finish_fit(xy_m, x, terms, None, origin_xy_m, scanner)
