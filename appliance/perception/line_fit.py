"""The weighted total-least-squares line and its covariance, for boards and walls.

**Fit.** Weighted total least squares in Hessian normal form. A point's range error lies
along its beam, so its offset from the line has variance ``σ_r² (n·u_i)² + σ_floor²``
(``n`` the line normal, ``u_i`` the beam direction): points seen obliquely are better
along the normal than points seen head-on. The weights depend on ``n``, so the fit is
iterated to its fixed point (Pfister et al. 2003 do the same). With weights ``w_i``
fixed, the line passes through the weighted centroid ``p̄`` and its normal is the minor
axis of the weighted scatter matrix, in closed form ``α = ½ atan2(−2 Sxy, Syy − Sxx)``.

**Covariance, derived.** The estimate solves ``Σ w_i e_i ∂e_i/∂θ = 0`` for
``e_i = x_i cos α + y_i sin α − r``, ``θ = (r, α)``, ``∂e_i/∂θ = (−1, d_i)`` with
``d_i = t·p_i`` the coordinate along the line (``t = (−sin α, cos α)``). To first
order (terms in ``e_i`` have zero mean) and with ``w_i = 1/var e_i`` the sandwich
collapses to ``C = (Σ w_i g_i g_iᵀ)⁻¹``. Inverting the 2x2 with ``W = Σ w_i``,
``d̄ = Σ w_i d_i / W`` and ``S = Σ w_i (d_i − d̄)²``::

    var α = 1/S,   cov(r, α) = d̄/S,   var r = 1/W + d̄²/S

which reads: the offset at the centroid is known to ``1/W``, the angle to ``1/S``, and
``r`` inherits the angle error through the lever arm ``d̄`` from the foot of the normal
to the centroid (``dr/dα = t·p̄ = d̄``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from appliance.perception.line_kernels import irls, residual_figures, rough_line
from appliance.perception.types import FitRejection, FloatArray, RejectReason, ScannerModel


@dataclass(frozen=True, eq=False)
class LineFit:
    """A fitted line before it becomes a feature: Hessian form, covariance, residuals."""

    r_m: float
    alpha_rad: float
    covariance: FloatArray  # 2x2 over (r_m, alpha_rad)
    rms_m: float
    max_residual_m: float
    n_points: int
    chi_square: float  # Σ (residual / its σ)²


def moment_columns(q: FloatArray) -> FloatArray:
    """Columns whose weighted sums are every moment a line fit needs: 1, x, y, x², y², xy."""
    columns = np.empty((q.shape[0], 6))
    columns[:, 0] = 1.0
    x, y = q[:, 0], q[:, 1]
    columns[:, 1] = x  # column by column: numpy's loops over 2-wide rows are slow
    columns[:, 2] = y
    np.multiply(x, x, out=columns[:, 3])
    np.multiply(y, y, out=columns[:, 4])
    np.multiply(x, y, out=columns[:, 5])
    return columns


def column_sums(rows: FloatArray) -> FloatArray:
    """``np.add.reduce(rows, axis=0)`` to the last bit (both add the rows one after the
    other): the last running sum, which numpy works out three times faster when the
    rows are a few numbers wide."""
    if rows.shape[0] == 0:
        return np.zeros(rows.shape[1:])
    sums: FloatArray = np.add.accumulate(rows, axis=0)[-1]
    return sums


class RoughLine(NamedTuple):
    """A line from weighted moment sums, with what its covariance and tests need."""

    r_m: float
    alpha_rad: float
    spread: float  # Σ w (d - d̄)²: the weighted spread along the line
    along_m: float  # d̄ = t·p̄: the weighted centroid's coordinate along the line
    total: float  # Σ w
    chi_square: float  # Σ w e²: the weighted spread across it, the residuals' sum


def line_from_sums(sums: FloatArray, shift: FloatArray) -> RoughLine | None:
    """The weighted TLS line from moment sums of points moved by ``-shift``; None when
    the points have no direction."""
    return line_from_list(sums.tolist(), float(shift[0]), float(shift[1]))


def line_from_list(sums: list[float], shift_x: float, shift_y: float) -> RoughLine | None:
    """`line_from_sums` of the sums as floats (1, x, y, x², y², xy) and the shift."""
    total, sx, sy, sxx, syy, sxy = sums
    found, *line = rough_line(total, sx, sy, sxx, syy, sxy, shift_x, shift_y)
    return RoughLine(*line) if found else None


def tls_line(xy_m: FloatArray, weights: FloatArray | None = None) -> tuple[float, float] | None:
    """(r, α) of the (weighted) total-least-squares line, or None if the points have no
    direction (fewer than two, coincident, or so far out that rounding ate the spread)."""
    if xy_m.shape[0] < 2:
        return None
    with np.errstate(all="ignore"):
        shift = xy_m.mean(axis=0)
        q = xy_m - shift
        w = np.ones(xy_m.shape[0]) if weights is None else weights
        line = line_from_sums(w @ moment_columns(q), shift)
    return None if line is None else (line.r_m, line.alpha_rad)


def fit_line(
    xy_m: FloatArray,
    directions: FloatArray | None,
    scanner: ScannerModel,
    max_iterations: int = 20,
    alpha_start_rad: float | None = None,
) -> LineFit | FitRejection:
    """Weighted TLS line through the points, iterated to its fixed point.

    ``directions`` (N, 2) are the unit beam directions (the range error's direction);
    None means isotropic noise of ``σ_r`` (plus the floor), i.e. the plain TLS line.
    ``alpha_start_rad`` (a rough line's α) saves the unweighted first pass. Never raises
    and never returns nan: anything unfit is a `FitRejection`.
    """
    n = int(xy_m.shape[0])
    if n < 2:
        return FitRejection(RejectReason.TOO_FEW_POINTS, f"{n} point(s)")
    with np.errstate(all="ignore"):
        shift = np.add.reduce(xy_m, axis=0) / n
        shift_x, shift_y = shift.tolist()
        if not math.isfinite(shift_x + shift_y):  # a nan or inf, or a sum overflowed
            return FitRejection(RejectReason.NON_FINITE)
        q = xy_m - shift
        moments = moment_columns(q)
        alpha = alpha_start_rad
        if alpha is None and directions is not None:
            unweighted = line_from_list(np.add.reduce(moments, axis=0).tolist(), shift_x, shift_y)
            alpha = None if unweighted is None else unweighted.alpha_rad
        return fit_line_moments(
            q, moments, (shift_x, shift_y), directions, scanner, max_iterations, alpha
        )


def fit_line_moments(
    q: FloatArray,
    moments: FloatArray,
    shift_xy_m: tuple[float, float],
    directions: FloatArray | None,
    scanner: ScannerModel,
    max_iterations: int,
    alpha_start_rad: float | None,
) -> LineFit | FitRejection:
    """`fit_line` of points given as their offsets ``q`` from ``shift_xy_m`` and their
    `moment_columns` (a caller that has them for a whole cluster passes a piece's rows);
    numpy's floating-point warnings are the caller's to silence."""
    n = int(q.shape[0])
    if directions is None:
        weights = np.full(n, 1.0 / (scanner.sigma_m**2 + scanner.floor_sigma_m**2))
        line = line_from_list(column_sums(weights[:, None] * moments).tolist(), *shift_xy_m)
        if line is None:
            return FitRejection(RejectReason.DEGENERATE, "no direction in the points")
        return _finish_line_fit(q, *shift_xy_m, line, weights)
    found, weights, *fields = irls(
        moments,
        np.ascontiguousarray(directions),
        0.0 if alpha_start_rad is None else alpha_start_rad,
        scanner.sigma_m,
        scanner.floor_sigma_m,
        *shift_xy_m,
        max(max_iterations, 1),
    )
    if not found:
        return FitRejection(RejectReason.DEGENERATE, "no direction in the points")
    return _finish_line_fit(q, *shift_xy_m, RoughLine(*fields), weights)


def _finish_line_fit(
    q: FloatArray, shift_x: float, shift_y: float, line: RoughLine, weights: FloatArray
) -> LineFit | FitRejection:
    """Covariance (derived in the module docstring) and residuals of a fitted line."""
    if not (line.spread > 0.0 and math.isfinite(line.spread)):
        return FitRejection(RejectReason.DEGENERATE, "no extent along the line")
    rms, worst, chi_square = residual_figures(
        q, weights, line.r_m, line.alpha_rad, shift_x, shift_y
    )
    var_alpha = 1.0 / line.spread
    lever = line.along_m
    var_r = 1.0 / line.total + lever * lever * var_alpha
    cov_r_alpha = lever * var_alpha
    finite = math.isfinite(var_r) and math.isfinite(cov_r_alpha) and math.isfinite(var_alpha)
    if not (finite and math.isfinite(rms + chi_square + line.r_m)):
        return FitRejection(RejectReason.NON_FINITE, "the fit overflowed")
    covariance = np.array([[var_r, cov_r_alpha], [cov_r_alpha, var_alpha]])
    return LineFit(line.r_m, line.alpha_rad, covariance, rms, worst, int(q.shape[0]), chi_square)
