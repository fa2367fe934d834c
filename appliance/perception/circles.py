"""Cylindrical landmarks: circle fits to short arcs, and the checks that make one a landmark.

**Fits.** The landmark's radius is known (Qian et al.'s launcher: one size of pipe), so
the centre is fitted alone: an orthogonal-distance fit (residual ``|p_i − c| − R``) on
the two centre coordinates, started from the arc's middle point pushed back along its
beam by ``R`` (Taubin's algebraic fit is the second start). With two unknowns instead of
three, seven noisy points at 10 m still pin the centre, where a free radius wanders by
centimetres. The full three-parameter geometric fit, started from Taubin (never from
Kåsa's fit, which shrinks short arcs), checks the radius when the arc has points enough
to say something. The solver (`circle_search`) is Levenberg–Marquardt on the exact
Hessian (``JᵀJ`` plus the residual curvature ``Σ r_i (I − n_i n_iᵀ)/|p_i − c|``):
quadratic convergence in a handful of steps, and the damping turns it into gradient
descent far from a minimum. The radius check (`free_radius_mismatch`) needs only to know
on which side of its allowance the free radius ends: most arcs settle that a few steps
before the free fit has converged, and skip the rest of it.

**Covariance.** The fit is unweighted, but the noise is not isotropic: a point's range
error lies along its beam, so its residual has variance ``σ_r² (u_i·n_i)² + σ_floor²``
(``n_i`` the radial direction at the point): large where the beam meets the cylinder
head-on, small at the edges where it grazes. The centre's covariance is therefore the
first-order sandwich ``(JᵀJ)⁻¹ Jᵀ diag(σ_i²) J (JᵀJ)⁻¹`` at the solution, which is
``σ² (JᵀJ)⁻¹`` when every ``σ_i = σ``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from appliance.perception.circle_search import (
    coordinates,
    covariance,
    minimise,
    residuals,
    surely_agrees,
    terms,
)
from appliance.perception.types import (
    FitRejection,
    FloatArray,
    RejectReason,
    ScannerModel,
)

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
    # The points (contiguous coordinates), the scanner's position and the search's sums
    # at the solution: a refit of the same points starts from there.
    _xs: FloatArray = field(repr=False)
    _ys: FloatArray = field(repr=False)
    _origin_xy_m: tuple[float, float] = field(repr=False)
    _sums: FloatArray = field(repr=False)

    @property
    def mean_range_m(self) -> float:
        """The mean distance of the fitted points from the scanner."""
        ox, oy = self._origin_xy_m
        return float(np.hypot(self._xs - ox, self._ys - oy).mean())


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


def _finish_fit(
    xs: FloatArray,
    ys: FloatArray,
    origin_xy_m: tuple[float, float],
    x: FloatArray,
    sums: FloatArray,
    radius_m: float | None,
    scanner: ScannerModel,
) -> CircleFit | FitRejection:
    radius = float(x[2]) if radius_m is None else radius_m
    centre, determined = covariance(
        xs, ys, *origin_xy_m, x, radius, sums, scanner.sigma_m, scanner.floor_sigma_m
    )
    if not determined:
        return FitRejection(RejectReason.DEGENERATE, "the centre is not determined")
    radius_sigma = 0.0 if radius_m is not None else math.sqrt(max(float(centre[2, 2]), 0.0))
    rms = math.sqrt(float(sums[2, 2]) / xs.shape[0])
    if not (math.isfinite(rms) and math.isfinite(radius_sigma) and np.isfinite(x).all()):
        return FitRejection(RejectReason.NON_FINITE)
    return CircleFit(
        float(x[0]),
        float(x[1]),
        radius,
        centre[:2, :2].copy(),
        radius_sigma,
        rms,
        int(xs.shape[0]),
        residuals(xs, ys, float(x[0]), float(x[1]), radius),
        xs,
        ys,
        origin_xy_m,
        sums,
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
        if not np.logical_and.reduce(np.isfinite(xy_m), axis=None):
            return FitRejection(RejectReason.NON_FINITE)
        mx, my = xy_m[n // 2].tolist()
        bx, by = mx - origin_xy_m[0], my - origin_xy_m[1]
        length = math.hypot(bx, by)
        starts: list[list[float] | None] = [] if start is None else [list(start)]
        if length > 0.0:
            starts.append([mx + radius_m * bx / length, my + radius_m * by / length])
        starts.append(None)  # Taubin's centre, computed only if the others fail
        xs, ys = coordinates(xy_m)
        for guess in starts:
            if guess is None:
                algebraic = taubin_circle(xy_m)
                if isinstance(algebraic, FitRejection):
                    break
                guess = list(algebraic[:2])
            centre, sums, converged = minimise(
                xs, ys, np.array(guess, dtype=np.float64), radius_m, max_iterations
            )
            if converged:
                return _finish_fit(xs, ys, origin_xy_m, centre, sums, radius_m, scanner)
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
        xs, ys = coordinates(xy_m)
        x, sums, converged = minimise(
            xs, ys, np.array(start, dtype=np.float64), math.nan, max_iterations
        )
        if not (converged and x[2] > 0.0):
            return FitRejection(RejectReason.NOT_CONVERGED)
        return _finish_fit(xs, ys, origin_xy_m, x, sums, None, scanner)


def free_radius_mismatch(
    xy_m: FloatArray,
    known: CircleFit,
    origin_xy_m: tuple[float, float],
    scanner: ScannerModel,
    tolerance_m: float,
    sigmas: float,
    max_iterations: int = 50,
) -> float | None:
    """The free radius of the points when it disagrees with ``known``'s (a known-radius
    fit of the same points) by more than ``tolerance_m`` plus ``sigmas`` of its σ, else
    None (also when the free fit, started from ``known``, does not converge).

    Most arcs agree by a wide margin, and that is settled before the fit has converged:
    a few Newton steps from ``known`` reach a point of positive-definite Hessian whose
    next step is below 1e-5 of the coordinates (so the minimum is within ten such steps:
    the convergence is quadratic there), and if the radius there plus that margin is
    inside the allowance computed there less 2 % (the σ moves by far less over so short
    a way), the fit would agree (`circle_search.surely_agrees`). Anything else is decided
    by the full fit.
    """
    with np.errstate(all="ignore"):
        if known._xs.shape[0] == xy_m.shape[0] and known._origin_xy_m == origin_xy_m:
            xs, ys, sums = known._xs, known._ys, known._sums  # the same points, fitted
        else:
            xs, ys = coordinates(xy_m)
            sums = None
        centre = np.array([known.cx_m, known.cy_m, known.radius_m])
        if sums is None:
            sums = np.empty((6, 6))
            terms(xs, ys, known.cx_m, known.cy_m, known.radius_m, sums)
        if surely_agrees(
            xs, ys, *origin_xy_m, centre, sums, scanner.sigma_m, scanner.floor_sigma_m,
            tolerance_m, sigmas,
        ):  # fmt: skip
            return None
    free = fit_circle_free(
        xy_m, origin_xy_m, scanner, max_iterations, start=(known.cx_m, known.cy_m, known.radius_m)
    )
    if isinstance(free, FitRejection):
        return None
    allowed = tolerance_m + sigmas * free.radius_sigma_m
    return free.radius_m if abs(free.radius_m - known.radius_m) > allowed else None
