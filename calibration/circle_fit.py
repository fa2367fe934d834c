"""A circle through noisy points: Pratt's algebraic fit, then geometric least squares.

The circle is written as ``A (x² + y²) + B x + C y + D = 0`` with ``B² + C² - 4 A D = 1``
(Pratt's normalisation; Chernov & Lesort, "Least squares fitting of circles", 2005). Unlike
centre and radius, these parameters stay finite as the circle opens into a line (``A -> 0``),
which the palm tree needs: its middle arc is driven with the wheel straight ahead. The signed
geometric distance of a point is ``2 P / (1 + sqrt(1 + 4 A P))`` with ``P`` the left-hand
side, exact for circles and lines alike, and the curvature is ``2 A``.

1. Algebraic: minimise the sum of ``P²`` under the normalisation, a 4x4 generalised eigen
   problem. Exact on exact points, and a start close enough for the next step.
2. Geometric: ``scipy.optimize.least_squares`` over ``(A, D, θ)`` with ``B, C =
   sqrt(1 + 4 A D) (cos θ, sin θ)``, the normalisation built in, and a soft-L1 loss whose
   scale is a few fix sigmas, so a stray fix pulls the circle as little as it can.

Coordinates are shifted to one of the points (on the curve, so ``D`` stays near zero and the
parametrisation away from its one singularity, the origin at the centre of a full circle) and
scaled by their spread, so that metres of UTM-sized coordinates do not swamp the fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import scipy.optimize

from calibration.fit_inputs import FloatArray, positive, same_length, sample_array

_PRATT_CONSTRAINT = np.array(
    [[0.0, 0.0, 0.0, -2.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [-2.0, 0.0, 0.0, 0.0]]
)


@dataclass(frozen=True)
class CircleFit:
    """``A (x'² + y'²) + B x' + C y' + D = 0`` with ``x' = x - origin_x_m`` (metres)."""

    origin_x_m: float
    origin_y_m: float
    a_per_m: float
    b: float
    c: float
    d_m: float
    residuals_m: FloatArray  # signed distance of each point from the curve
    rms_m: float
    # Of (A [1/m], D [m], θ [rad]), from the Jacobian and the residual scatter; inf for
    # three points, which leave no scatter to judge by.
    covariance: FloatArray
    converged: bool
    method: str

    @property
    def curvature_per_m(self) -> float:
        """``2 A``: its sign follows the orientation of ``(B, C)``, not the direction of
        travel (:func:`signed_curvature_per_m` gives the sign a vehicle sees)."""
        return 2.0 * self.a_per_m

    @property
    def curvature_sigma_per_m(self) -> float:
        return 2.0 * math.sqrt(max(float(self.covariance[0, 0]), 0.0))

    @property
    def radius_m(self) -> float:
        return math.inf if self.a_per_m == 0.0 else 1.0 / abs(2.0 * self.a_per_m)

    @property
    def centre_m(self) -> tuple[float, float]:
        """The centre; infinite for a straight line."""
        if self.a_per_m == 0.0:
            return math.inf, math.inf
        return (
            self.origin_x_m - self.b / (2.0 * self.a_per_m),
            self.origin_y_m - self.c / (2.0 * self.a_per_m),
        )

    def unit_normals(self, x_m: FloatArray, y_m: FloatArray) -> tuple[FloatArray, FloatArray]:
        """The gradient of ``P`` at each point, normalised: away from the centre when A > 0."""
        gx = 2.0 * self.a_per_m * (x_m - self.origin_x_m) + self.b
        gy = 2.0 * self.a_per_m * (y_m - self.origin_y_m) + self.c
        norm = np.hypot(gx, gy)
        norm[norm == 0.0] = 1.0
        return gx / norm, gy / norm


def pratt_fit(x_m: FloatArray, y_m: FloatArray) -> tuple[float, float, float, float]:
    """``(A, B, C, D)`` minimising the algebraic distances, in the caller's coordinates.

    Call it with coordinates near the origin and of order one (``fit_circle`` does).
    """
    z = x_m * x_m + y_m * y_m
    design = np.stack([z, x_m, y_m, np.ones_like(x_m)], axis=1)
    moments = design.T @ design / x_m.size
    values, vectors = scipy.linalg.eig(moments, _PRATT_CONSTRAINT)
    best: tuple[float, FloatArray] | None = None
    scale = max(float(np.abs(moments).max()), 1e-300)
    for value, vector in zip(values, vectors.T, strict=True):
        if not np.isfinite(value) or value.real < -1e-9 * scale:
            continue
        candidate = np.real(vector)
        norm2 = float(candidate @ _PRATT_CONSTRAINT @ candidate)
        if norm2 <= 0.0:
            continue
        if best is None or value.real < best[0]:
            best = (float(value.real), candidate / math.sqrt(norm2))
    if best is None:
        raise ValueError("the points do not determine a circle or a line (all coincide?)")
    a, b, c, d = (float(v) for v in best[1])
    return a, b, c, d


def _distances(params: FloatArray, x: FloatArray, y: FloatArray) -> FloatArray:
    a, d, theta = params
    s = math.sqrt(max(1.0 + 4.0 * a * d, 0.0))
    p = a * (x * x + y * y) + s * math.cos(theta) * x + s * math.sin(theta) * y + d
    return np.asarray(2.0 * p / (1.0 + np.sqrt(np.maximum(1.0 + 4.0 * a * p, 0.0))))


def fit_circle(x_m: FloatArray, y_m: FloatArray, *, robust_scale_m: float = 0.05) -> CircleFit:
    """The circle (or line) through the points, in time order (see the module's method).

    ``robust_scale_m`` is where the soft-L1 loss turns from squares to absolute values: a
    few fix sigmas, so ordinary noise is weighed as least squares would and a stray point
    (a jump the segmentation missed) counts linearly. ValueError for fewer than 3 points,
    non-finite values or points that are all the same.
    """
    x_m = sample_array("x_m", x_m, min_samples=3)
    y_m = sample_array("y_m", y_m, min_samples=3)
    same_length({"x_m": x_m, "y_m": y_m})
    positive("robust_scale_m", robust_scale_m)
    mid = x_m.size // 2
    x0, y0 = float(x_m[mid]), float(y_m[mid])
    dx, dy = x_m - x0, y_m - y0
    spread = float(np.sqrt(np.mean(dx * dx + dy * dy)))
    if spread == 0.0:
        raise ValueError("the points are all the same: no circle or line through them")
    xs, ys = dx / spread, dy / spread
    a, b, c, d = pratt_fit(xs, ys)
    start = np.array([a, d, math.atan2(c, b)])
    result = scipy.optimize.least_squares(
        _distances,
        start,
        args=(xs, ys),
        loss="soft_l1",
        f_scale=robust_scale_m / spread,
        x_scale="jac",
        xtol=1e-12,
        ftol=1e-12,
        gtol=1e-12,
    )
    a, d, theta = (float(v) for v in result.x)
    s = math.sqrt(max(1.0 + 4.0 * a * d, 0.0))
    residuals = _distances(result.x, xs, ys) * spread
    dof = x_m.size - 3
    covariance = np.full((3, 3), math.inf)
    if dof > 0:
        jac = np.asarray(result.jac)
        variance = float(np.sum((residuals / spread) ** 2)) / dof
        unscale = np.diag([1.0 / spread, spread, 1.0])  # (A', D', θ) -> (A, D, θ)
        covariance = unscale @ np.linalg.pinv(jac.T @ jac) @ unscale * variance
    return CircleFit(
        origin_x_m=x0,
        origin_y_m=y0,
        a_per_m=a / spread,
        b=s * math.cos(theta),
        c=s * math.sin(theta),
        d_m=d * spread,
        residuals_m=residuals,
        rms_m=float(np.sqrt(np.mean(residuals**2))),
        covariance=covariance,
        converged=bool(result.success),
        method="Pratt algebraic start, geometric least squares (A, D, θ), soft-L1 loss",
    )


def signed_curvature_per_m(
    fit: CircleFit, x_m: FloatArray, y_m: FloatArray, heading_rad: FloatArray
) -> float:
    """Curvature, positive when the centre lies to the left of the headings (a left turn
    driven forward; reversing on the same circle keeps the sign, as the wheels do)."""
    nx, ny = fit.unit_normals(x_m, y_m)
    side = float(np.mean(np.cos(heading_rad) * ny - np.sin(heading_rad) * nx))
    return -fit.curvature_per_m * (1.0 if side >= 0.0 else -1.0)


def tangent_offsets_rad(
    fit: CircleFit, x_m: FloatArray, y_m: FloatArray, heading_rad: FloatArray
) -> FloatArray:
    """The angle from each heading to the curve's tangent at its point (the tangent taken
    in the heading's direction, so reversing gives the same angle): the sideslip there."""
    nx, ny = fit.unit_normals(x_m, y_m)
    tx, ty = -ny, nx
    hx, hy = np.cos(heading_rad), np.sin(heading_rad)
    flip = np.where(hx * tx + hy * ty < 0.0, -1.0, 1.0)
    tx, ty = tx * flip, ty * flip
    return np.asarray(np.arctan2(hx * ty - hy * tx, hx * tx + hy * ty))


def mean_tangent_offset_rad(
    fit: CircleFit, x_m: FloatArray, y_m: FloatArray, heading_rad: FloatArray
) -> tuple[float, float]:
    """The mean of :func:`tangent_offsets_rad` and its sigma.

    The sigma has two parts, added in quadrature: the scatter of the offsets about their
    mean (heading noise, and position noise along the curve), and the circle's own
    uncertainty, which turns every tangent the same way at once and so does not average
    out (the covariance carried through the mean by a numerical gradient).
    """
    offsets = tangent_offsets_rad(fit, x_m, y_m, heading_rad)
    mean = float(np.mean(offsets))
    scatter = float(np.var(offsets, ddof=1)) / offsets.size if offsets.size > 1 else math.inf
    if not np.all(np.isfinite(fit.covariance)):
        return mean, math.inf
    params = np.array([fit.a_per_m, fit.d_m, math.atan2(fit.c, fit.b)])
    steps = np.sqrt(np.maximum(np.diag(fit.covariance), 0.0)) * 1e-3 + 1e-12
    gradient = np.zeros(3)
    for i in range(3):
        shifted = []
        for sign in (1.0, -1.0):
            a, d, theta = params + sign * steps[i] * np.eye(3)[i]
            s = math.sqrt(max(1.0 + 4.0 * a * d, 0.0))
            moved = replace(fit, a_per_m=a, b=s * math.cos(theta), c=s * math.sin(theta), d_m=d)
            shifted.append(float(np.mean(tangent_offsets_rad(moved, x_m, y_m, heading_rad))))
        gradient[i] = (shifted[0] - shifted[1]) / (2.0 * steps[i])
    from_circle = float(gradient @ fit.covariance @ gradient)
    return mean, math.sqrt(scatter + max(from_circle, 0.0))


def arc_length_m(fit: CircleFit, x_m: FloatArray, y_m: FloatArray) -> float:
    """Length of the curve the points (in time order) cover: their angular span about the
    centre times the radius, or their span along the line when it is one."""
    nx0, ny0 = fit.unit_normals(np.array([fit.origin_x_m]), np.array([fit.origin_y_m]))
    kappa = abs(fit.curvature_per_m)
    towards = -1.0 if fit.a_per_m > 0.0 else 1.0  # the unit normal, turned to the centre
    mx, my = towards * float(nx0[0]), towards * float(ny0[0])
    dx, dy = x_m - fit.origin_x_m, y_m - fit.origin_y_m
    along = dx * -my + dy * mx
    inward = dx * mx + dy * my
    if kappa * float(np.max(np.hypot(dx, dy))) < 1e-9:
        return float(np.ptp(along))
    angles = np.unwrap(np.arctan2(kappa * along, 1.0 - kappa * inward))
    return float(np.ptp(angles)) / kappa
