"""The pot map's two branches: one polynomial, the backlash between them.

The encoder sits half the coupling's play ahead of the wheel in the direction it last
moved, so the pauses sweeping up and those sweeping down lie on two copies of one curve,
a constant encoder angle apart at equal pot counts: that gap is the backlash. Rather than
interpolate one branch at the other's pot readings (a chord between half-turn pauses
misses the curve by a third of the play near a lock), both are fitted at once, by linear
least squares: ``encoder = offset + half_backlash * direction + sum(c_k * d**k)`` with
``d = counts - centre`` and odd k. The polynomial is then the map through the mid-branch
points, the wheel itself; ``offset`` is the encoder's reading with the wheels straight
(a relative encoder's zero is wherever it was powered up).

The centre is the pot-centre step's, or, without it, the reading where the map's encoder
angle is zero, found by refitting about it until it stops moving. One round of outlier
pauses goes (a residual beyond ``outlier_sigmas`` robust σ and ``min_outlier_rad``), then
the degree is lowered until the polynomial is monotonic over the valid range, the
calibration file's own condition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from calibration.fit_checks import BoolArray, FloatArray, mad_sigma
from calibration.pot_map_pauses import Pause

POT_FULL_SCALE_COUNTS: Final = 4095  # 12-bit ADC


@dataclass(frozen=True)
class BranchParams:
    powers: tuple[int, ...] = (1, 3, 5, 7, 9)
    outlier_sigmas: float = 5.0
    min_outlier_rad: float = 0.02  # below this a pause is never an outlier
    # Readings this far past the outermost pause are still valid: the pot's noise at a
    # lock (0.8 counts rms) must not read as a broken pot.
    valid_margin_counts: float = 5.0


@dataclass(frozen=True)
class BranchFit:
    centre_counts: float | None
    powers: tuple[int, ...]
    coeffs: tuple[float, ...]
    offset_rad: float
    half_backlash_rad: float
    half_backlash_se_rad: float
    residuals_rad: FloatArray  # of the pauses used
    outliers: BoolArray  # over every pause
    valid_counts: tuple[int, int]
    monotonic: bool


@dataclass(frozen=True)
class _Solution:
    offset_rad: float
    half_backlash_rad: float
    half_backlash_se_rad: float
    coeffs: tuple[float, ...]
    residuals_rad: FloatArray


def fit_branches(pauses: list[Pause], centre: float | None, p: BranchParams) -> BranchFit | None:
    """Outliers out, the centre found if not given, then the highest monotonic degree."""
    used = np.array([q.used for q in pauses], dtype=np.bool_)
    pot = np.array([q.pot_counts for q in pauses])
    encoder = np.array([q.encoder_rad for q in pauses])
    side = np.array([float(q.direction) for q in pauses])
    if np.count_nonzero(used) < 4:  # a line and the backlash need at least that
        return None
    # Fewer terms than positions swept, with room to spare: each position is visited
    # once each way, and a polynomial through every point swings between them.
    positions = min(
        int(np.count_nonzero(used & (side > 0))), int(np.count_nonzero(used & (side < 0)))
    )
    powers = p.powers[: max(1, positions - 3)]
    provisional = (
        centre if centre is not None else float(pot[used][np.argmin(np.abs(encoder[used]))])
    )
    first = _solve(pot[used], encoder[used], side[used], provisional, powers)
    limit = max(p.outlier_sigmas * mad_sigma(first.residuals_rad), p.min_outlier_rad)
    outliers = np.zeros(len(pauses), dtype=np.bool_)
    outliers[np.flatnonzero(used)[np.abs(first.residuals_rad) > limit]] = True
    keep = used & ~outliers
    pot, encoder, side = pot[keep], encoder[keep], side[keep]
    low, high = float(pot.min()), float(pot.max())
    valid = (
        max(0, math.floor(low - p.valid_margin_counts)),
        min(POT_FULL_SCALE_COUNTS, math.ceil(high + p.valid_margin_counts)),
    )
    for count in range(len(powers), 0, -1):
        trial = powers[:count]
        at = centre if centre is not None else _encoder_zero(pot, encoder, side, provisional, trial)
        if at is None:
            return BranchFit(
                None, trial, (), 0.0, 0.0, 0.0, first.residuals_rad, outliers, valid, False
            )
        solution = _solve(pot, encoder, side, at, trial)
        offsets = np.linspace(valid[0] - at, valid[1] - at, 512)
        signs = np.sign(_slope(solution.coeffs, offsets))
        monotonic = bool(np.all(signs == signs[0]) and signs[0] != 0.0)
        if monotonic or count == 1:
            return BranchFit(
                at,
                trial,
                solution.coeffs,
                solution.offset_rad,
                solution.half_backlash_rad,
                solution.half_backlash_se_rad,
                solution.residuals_rad,
                outliers,
                valid,
                monotonic,
            )
    return None  # unreachable: the loop returns at count 1


def _solve(
    pot: FloatArray, encoder: FloatArray, side: FloatArray, centre: float, powers: tuple[int, ...]
) -> _Solution:
    """encoder ~ offset + half_backlash * side + sum(c_k * (pot - centre)**k), least squares.

    Fitted in ``d / max|d|`` (d**9 of a thousand counts is singular); the residuals are
    the backlash-corrected (mid-branch) points' distances from the map, in wheel rad.
    """
    offset = pot - centre
    scale = float(np.max(np.abs(offset))) or 1.0
    both_ways = bool(np.any(side > 0) and np.any(side < 0))
    sides = [side] if both_ways else []  # one way only: no gap to measure
    columns = [np.ones_like(offset), *sides, *[(offset / scale) ** k for k in powers]]
    design = np.column_stack(columns)
    solution, *_ = np.linalg.lstsq(design, encoder, rcond=None)
    residuals = encoder - design @ solution
    dof = encoder.size - design.shape[1]
    variance = float(residuals @ residuals) / dof if dof > 0 else 0.0
    covariance = variance * np.linalg.pinv(design.T @ design)
    first_power = 1 + len(sides)
    coeffs = [0.0] * max(powers)
    for k, value in zip(powers, solution[first_power:], strict=True):
        coeffs[k - 1] = float(value) / scale**k
    return _Solution(
        offset_rad=float(solution[0]),
        half_backlash_rad=float(solution[1]) if both_ways else math.nan,
        half_backlash_se_rad=math.sqrt(max(0.0, float(covariance[1, 1])))
        if both_ways
        else math.nan,
        coeffs=tuple(coeffs),
        residuals_rad=residuals,
    )


def _encoder_zero(
    pot: FloatArray, encoder: FloatArray, side: FloatArray, start: float, powers: tuple[int, ...]
) -> float | None:
    """The reading where the fitted map's encoder angle is zero, refined a few times
    (the odd polynomial is centred on it); None if it lies outside the measured pots."""
    centre = start
    grid = np.linspace(float(pot.min()), float(pot.max()), 4096)
    for _ in range(5):
        fit = _solve(pot, encoder, side, centre, powers)
        values = fit.offset_rad + _value(fit.coeffs, grid - centre)
        crossings = np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))
        if crossings.size != 1:
            return None
        i = int(crossings[0])
        root = float(grid[i] - values[i] * (grid[i + 1] - grid[i]) / (values[i + 1] - values[i]))
        if abs(root - centre) < 1e-3:
            return root
        centre = root
    return centre


def _value(coeffs: tuple[float, ...], offsets: FloatArray) -> FloatArray:
    return np.asarray(np.polynomial.polynomial.polyval(offsets, (0.0, *coeffs)), np.float64)


def _slope(coeffs: tuple[float, ...], offsets: FloatArray) -> FloatArray:
    derivative = [(i + 1) * c for i, c in enumerate(coeffs)]
    return np.asarray(np.polynomial.polynomial.polyval(offsets, derivative), np.float64)
