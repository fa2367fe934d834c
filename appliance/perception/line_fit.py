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

from appliance.perception.jit import F64, I64, IN_1D, IN_2D, OUT_1D, kernel
from appliance.perception.types import FitRejection, FloatArray, RejectReason, ScannerModel

_IRLS_TOLERANCE = 1e-12
_RESOLUTION = 1e-10  # a spread below this fraction of the coordinates is rounding


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


@kernel(F64)
def wrap_angle(angle_rad: float) -> float:
    """The angle in (−π, π]."""
    wrapped = math.atan2(math.sin(angle_rad), math.cos(angle_rad))
    return math.pi if wrapped <= -math.pi else wrapped


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
    found, *line = _rough_line(total, sx, sy, sxx, syy, sxy, shift_x, shift_y)
    return RoughLine(*line) if found else None


@kernel(F64, F64, F64, F64, F64, F64, F64, F64)
def _rough_line(total: float, sx: float, sy: float, sxx: float, syy: float, sxy: float,
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


@kernel(IN_2D, F64, F64, F64, OUT_1D)
def _weights(directions: FloatArray, alpha: float, sigma_m: float, floor_sigma_m: float,
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
def _weighted_sums(weights: FloatArray, moments: FloatArray, out: FloatArray) -> None:
    """``weights @ moments`` into ``out``, the points added in order."""
    for j in range(6):
        out[j] = 0.0
    for k in range(moments.shape[0]):
        w = weights[k]
        for j in range(6):
            out[j] += w * moments[k, j]


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
    found, weights, *fields = _irls(
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


@kernel(IN_2D, IN_2D, F64, F64, F64, F64, F64, I64)
def _irls(moments: FloatArray, directions: FloatArray, alpha_start_rad: float, sigma_m: float,
          floor_sigma_m: float, shift_x: float, shift_y: float, iterations: int
          ) -> tuple[bool, FloatArray, float, float, float, float, float, float]:  # fmt: skip
    """The weighted line iterated to its fixed point: (found, the weights it ends with,
    then `RoughLine`'s fields). Each pass fits the line with the weights of the last
    pass's normal; it stops when a pass moves the line by no more than rounding."""
    weights = np.empty(moments.shape[0])
    sums = np.empty(6)
    _weights(directions, alpha_start_rad, sigma_m, floor_sigma_m, weights)
    found = False
    r = alpha = spread = along = total = across = 0.0
    for iteration in range(iterations):
        _weighted_sums(weights, moments, sums)
        previous_r, previous_alpha = r, alpha
        found, r, alpha, spread, along, total, across = _rough_line(
            sums[0], sums[1], sums[2], sums[3], sums[4], sums[5], shift_x, shift_y
        )
        if not found:
            break
        if iteration > 0:
            change = max(abs(r - previous_r), abs(wrap_angle(alpha - previous_alpha)))
            if change <= _IRLS_TOLERANCE * (1.0 + r):
                break  # the weights this line was fitted with are its own, to rounding
        _weights(directions, alpha, sigma_m, floor_sigma_m, weights)
    return found, weights, r, alpha, spread, along, total, across


def _finish_line_fit(
    q: FloatArray, shift_x: float, shift_y: float, line: RoughLine, weights: FloatArray
) -> LineFit | FitRejection:
    """Covariance (derived in the module docstring) and residuals of a fitted line."""
    if not (line.spread > 0.0 and math.isfinite(line.spread)):
        return FitRejection(RejectReason.DEGENERATE, "no extent along the line")
    rms, worst, chi_square = _residual_figures(
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


@kernel(IN_2D, IN_1D, F64, F64, F64, F64)
def _residual_figures(q: FloatArray, weights: FloatArray, r_m: float, alpha_rad: float,
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
