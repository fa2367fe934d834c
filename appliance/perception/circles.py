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

from appliance.perception import circle_search as search
from appliance.perception.circle_search import (
    coordinates,
    fit_figures,
    known_radius_fit,
    minimise,
    surely_agrees,
    taubin,
    terms,
)
from appliance.perception.types import (
    FitRejection,
    FloatArray,
    RejectReason,
    ScannerModel,
)


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


# The kernels' outcomes as the reasons a fit reports.
REASONS = {
    search.TOO_FEW: RejectReason.TOO_FEW_POINTS,
    search.NON_FINITE: RejectReason.NON_FINITE,
    search.DEGENERATE: RejectReason.DEGENERATE,
    search.COLLINEAR: RejectReason.COLLINEAR,
    search.NOT_CONVERGED: RejectReason.NOT_CONVERGED,
}
_DETAILS = {
    search.DEGENERATE: "coincident points",
    search.COLLINEAR: "the points lie on a line",
}


def taubin_circle(xy_m: FloatArray) -> tuple[float, float, float] | FitRejection:
    """Taubin's algebraic circle fit (`circle_search.taubin`): (cx, cy, R), or why
    there is none."""
    if xy_m.shape[0] < 3:
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{xy_m.shape[0]} point(s)")
    outcome, cx, cy, radius = taubin(*coordinates(xy_m))
    if outcome != search.OK:
        return FitRejection(REASONS[outcome], _DETAILS.get(outcome, ""))
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
    determined, centre, fitted, rms = fit_figures(
        xs, ys, *origin_xy_m, x, radius, sums, scanner.sigma_m, scanner.floor_sigma_m
    )
    if not determined:
        return FitRejection(RejectReason.DEGENERATE, "the centre is not determined")
    radius_sigma = 0.0 if radius_m is not None else math.sqrt(max(float(centre[2, 2]), 0.0))
    cx, cy = float(x[0]), float(x[1])
    if not all(map(math.isfinite, (rms, radius_sigma, cx, cy, radius))):
        return FitRejection(RejectReason.NON_FINITE)
    return CircleFit(
        cx,
        cy,
        radius,
        centre[:2, :2],
        radius_sigma,
        rms,
        int(xs.shape[0]),
        fitted,
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
    (a refit after dropping a point starts from the previous centre), then the middle
    point pushed back along its beam, then Taubin's centre. Never raises.
    """
    n = int(xy_m.shape[0])
    if n < 2:
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{n} point(s)")
    xs, ys = coordinates(xy_m)
    sx, sy = (0.0, 0.0) if start is None else start
    outcome, centre, sums = known_radius_fit(
        xs, ys, *origin_xy_m, radius_m, sx, sy, start is not None, max_iterations
    )
    if outcome != search.OK:
        return FitRejection(REASONS[outcome])
    return _finish_fit(xs, ys, origin_xy_m, centre, sums, radius_m, scanner)


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
    if known._xs.shape[0] == xy_m.shape[0] and known._origin_xy_m == origin_xy_m:
        xs, ys, sums = known._xs, known._ys, known._sums  # the same points, fitted
    else:
        xs, ys = coordinates(xy_m)
        sums = np.empty((6, 6))
        terms(xs, ys, known.cx_m, known.cy_m, known.radius_m, sums)
    centre = (known.cx_m, known.cy_m, known.radius_m)
    return free_radius_mismatch_xy(
        xs, ys, centre, sums, origin_xy_m, scanner, tolerance_m, sigmas, max_iterations
    )


def free_radius_mismatch_xy(
    xs: FloatArray,
    ys: FloatArray,
    known: tuple[float, float, float],
    sums: FloatArray,
    origin_xy_m: tuple[float, float],
    scanner: ScannerModel,
    tolerance_m: float,
    sigmas: float,
    max_iterations: int = 50,
) -> float | None:
    """`free_radius_mismatch` of the points as coordinate arrays, ``known`` (cx, cy, R)
    their known-radius fit and ``sums`` its search's sums there."""
    if surely_agrees(
        xs, ys, *origin_xy_m, np.array(known), sums, scanner.sigma_m, scanner.floor_sigma_m,
        tolerance_m, sigmas,
    ):  # fmt: skip
        return None
    free = fit_circle_free(
        np.column_stack((xs, ys)), origin_xy_m, scanner, max_iterations, start=known
    )
    if isinstance(free, FitRejection):
        return None
    allowed = tolerance_m + sigmas * free.radius_sigma_m
    return free.radius_m if abs(free.radius_m - known[2]) > allowed else None
