"""The pot map's two branches: one polynomial, the backlash between them.

The encoder sits half the coupling's play from the wheel, on the side it last moved
(ahead where the servo turns the wheel, behind where hands turn it and drag the servo),
so the points sweeping up and those sweeping down lie on two copies of one curve, a
constant encoder angle apart at equal pot counts: that gap is the backlash. Rather than
interpolate one branch at the other's pot readings (a chord between half-turn rests
misses the curve by a third of the play near a lock), both are fitted at once, by linear
least squares: ``encoder = offset + half_backlash * direction + sum(c_k * d**k)`` with
``d = counts - centre``. The polynomial is then the map through the mid-branch points,
the wheel itself; ``offset`` is the encoder's reading with the wheels straight (a
relative encoder's zero is wherever it was powered up).

The points are the rests (:mod:`calibration.pot_map_pauses`), each weighted by the
samples it averages, and the motion samples (:mod:`calibration.pot_map_motion`), one
each. How many terms they can carry is counted, not assumed: points closer than
``position_spacing_rad`` are one position. Where the points leave no gap wider than
``even_powers_max_gap_rad`` (the motion samples fill the sweep), every power up to the
ninth, fewer than the positions with room to spare: a general polynomial, so a centre a
few counts off only moves the map's zero, where an odd one about it would also bend.
Else only odd powers about the centre (the shape of a pot on a column), as many as the
distances from the centre the points cover, since a point and its mirror pin the same
term: half-turn rests alone on a wheel of three turns each way lie at three distances.

The centre is the pot-centre step's, or, without it, the reading where the map fitted
about it reads encoder zero (a fixed point, found by the secant method; none found, no
centre). One round of outliers goes (a residual, on one sample's scale, beyond
``outlier_sigmas`` robust σ and beyond ``min_outlier_rad``), then the degree is lowered
until the polynomial is monotonic over the valid range, the calibration file's own
condition.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from calibration.fit_checks import BoolArray, FloatArray, mad_sigma

POT_FULL_SCALE_COUNTS: Final = 4095  # 12-bit ADC
# Secant steps to the map's zero before it counts as not found: where there is one they
# reach it in a handful (a general polynomial's zero does not move with the centre at all).
ENCODER_ZERO_REFITS: Final = 12


@dataclass(frozen=True)
class BranchParams:
    powers: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8, 9)
    # Points closer than this are one position (the two directions' rests at one place,
    # a backlash apart; neighbouring motion samples).
    position_spacing_rad: float = 0.5
    # Even powers only where no gap between the points is wider: between rests half a
    # turn apart they would swing.
    even_powers_max_gap_rad: float = 0.5
    outlier_sigmas: float = 5.0
    min_outlier_rad: float = 0.02  # below this a point is never an outlier
    # Readings this far past the outermost point are still valid: the pot's noise at a
    # lock (0.8 counts rms) must not read as a broken pot.
    valid_margin_counts: float = 5.0


@dataclass(frozen=True)
class BranchPoints:
    """The points to fit: rests (each a mean of ``weight`` samples) and motion samples."""

    pot_counts: FloatArray
    encoder_rad: FloatArray
    direction: FloatArray  # +1: the encoder last moved up, -1: down
    weight: FloatArray  # the samples each point averages: its pot noise is 1/sqrt of that
    used: BoolArray


@dataclass(frozen=True)
class BranchFit:
    centre_counts: float | None
    powers: tuple[int, ...]
    coeffs: tuple[float, ...]
    offset_rad: float
    half_backlash_rad: float
    half_backlash_se_rad: float
    residuals_rad: FloatArray  # over every point: its encoder less the fit's
    kept: BoolArray  # used, and not an outlier
    outliers: BoolArray  # over every point
    positions: int  # distinct positions the kept points cover
    valid_counts: tuple[int, int]
    monotonic: bool


@dataclass(frozen=True)
class _Solution:
    offset_rad: float
    half_backlash_rad: float
    half_backlash_se_rad: float
    coeffs: tuple[float, ...]


def fit_branches(points: BranchPoints, centre: float | None, p: BranchParams) -> BranchFit | None:
    """Outliers out, the centre found if not given, then the highest monotonic degree."""
    used = points.used
    if np.count_nonzero(used) < 4:  # a line and the backlash need at least that
        return None
    pot, encoder = points.pot_counts, points.encoder_rad
    guess = float(pot[used][np.argmin(np.abs(encoder[used]))]) if centre is None else centre
    near = float(encoder[used][np.argmin(np.abs(pot[used] - guess))])
    powers = _powers(encoder[used], near, p)
    provisional = centre
    if provisional is None:  # the point nearest encoder zero, then the map's zero about it
        found = _encoder_zero(points, used, guess, powers)
        provisional = guess if found is None else found
    first = _solve(points, used, provisional, powers)
    residuals = encoder - _predict(first, points, provisional)
    scaled = residuals * np.sqrt(points.weight)  # on one sample's scale, rest or motion
    limit = p.outlier_sigmas * mad_sigma(scaled[used])
    outliers = used & (np.abs(scaled) > limit) & (np.abs(residuals) > p.min_outlier_rad)
    kept = used & ~outliers
    positions = distinct_positions(encoder[kept], p.position_spacing_rad)
    powers = _powers(encoder[kept], first.offset_rad, p)
    low, high = float(pot[kept].min()), float(pot[kept].max())
    valid = (
        max(0, math.floor(low - p.valid_margin_counts)),
        min(POT_FULL_SCALE_COUNTS, math.ceil(high + p.valid_margin_counts)),
    )
    for count in range(len(powers), 0, -1):
        trial = powers[:count]
        at = centre if centre is not None else _encoder_zero(points, kept, provisional, trial)
        if at is None:
            return BranchFit(
                None, trial, (), 0.0, 0.0, 0.0, residuals, kept, outliers, positions, valid, False
            )
        solution = _solve(points, kept, at, trial)
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
                encoder - _predict(solution, points, at),
                kept,
                outliers,
                positions,
                valid,
                monotonic,
            )
    return None  # unreachable: the loop returns at count 1


def distinct_positions(encoder_rad: FloatArray, spacing_rad: float) -> int:
    """How many positions at least ``spacing_rad`` apart the points cover (each a new
    one once it lies that far past where the last began)."""
    count, last = 0, -math.inf
    for value in np.sort(encoder_rad).tolist():
        if value - last >= spacing_rad:
            count, last = count + 1, value
    return count


def _powers(encoder_rad: FloatArray, at_centre_rad: float, p: BranchParams) -> tuple[int, ...]:
    """As many terms as the points can pin. Where they leave no gap, every power, fewer
    than the positions with room to spare. Else the odd ones about the centre, one per
    distance from it the points cover: a point and its mirror pin the same term (the
    half-turn rests of a wheel with three turns each way lie at 0, ±π, ±2π, ±3π, which
    is three distances, not seven positions)."""
    gaps = np.diff(np.sort(encoder_rad))
    if gaps.size > 0 and float(gaps.max()) <= p.even_powers_max_gap_rad:
        return p.powers[: max(1, distinct_positions(encoder_rad, p.position_spacing_rad) - 3)]
    odd = tuple(k for k in p.powers if k % 2)
    distances = np.abs(encoder_rad - at_centre_rad)
    distances = distances[distances >= p.position_spacing_rad / 2.0]
    return odd[: max(1, distinct_positions(distances, p.position_spacing_rad))]


def _solve(
    points: BranchPoints, mask: BoolArray, centre: float, powers: tuple[int, ...]
) -> _Solution:
    """encoder ~ offset + half_backlash * side + sum(c_k * (pot - centre)**k) over the
    ``mask``'s points, least squares weighted by the samples each point averages.

    Fitted in ``d / max|d|`` (d**9 of a thousand counts is singular).
    """
    side = points.direction[mask]
    both_ways = bool(np.any(side > 0) and np.any(side < 0))
    design, scale = _design(points.pot_counts[mask], side, centre, powers, both_ways)
    root_weight = np.sqrt(points.weight[mask])
    weighted = design * root_weight[:, None]
    target = points.encoder_rad[mask] * root_weight
    solution, *_ = np.linalg.lstsq(weighted, target, rcond=None)
    residuals = target - weighted @ solution
    dof = target.size - design.shape[1]
    variance = float(residuals @ residuals) / dof if dof > 0 else 0.0
    covariance = variance * np.linalg.pinv(weighted.T @ weighted)
    first_power = 2 if both_ways else 1
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
    )


def _design(
    pot: FloatArray, side: FloatArray, centre: float, powers: tuple[int, ...], both_ways: bool
) -> tuple[FloatArray, float]:
    offset = pot - centre
    scale = float(np.max(np.abs(offset))) or 1.0
    sides = [side] if both_ways else []  # one way only: no gap to measure
    columns = [np.ones_like(offset), *sides, *[(offset / scale) ** k for k in powers]]
    return np.column_stack(columns), scale


def _predict(solution: _Solution, points: BranchPoints, centre: float) -> FloatArray:
    """The encoder angle the fit expects at every point (NaN backlash: none added)."""
    gap = 0.0 if math.isnan(solution.half_backlash_rad) else solution.half_backlash_rad
    map_rad = _value(solution.coeffs, points.pot_counts - centre)
    return solution.offset_rad + gap * points.direction + map_rad


def _encoder_zero(
    points: BranchPoints, mask: BoolArray, start: float, powers: tuple[int, ...]
) -> float | None:
    """The reading where the map fitted about it reads encoder zero (an odd polynomial
    is centred on it): the fixed point of "refit about the centre, take the map's zero";
    None if the map reads zero nowhere in the measured pots, or no fixed point is found.

    Found by the secant method on (the map's zero − the centre), not by refitting about
    each zero in turn: that iteration swings about the fixed point, its step −0.4 to −0.7
    times the last on the simulated vehicle's sweeps, so five refits left it a few tenths
    of a count off; and where the points do not fill the sweep and the pot rails before
    both locks it can swing outwards into a cycle (found by the property test: 1888 ->
    2130 -> 2008 -> 2144 -> 2073 counts, the truth 2131). Where it stopped then was taken
    for the centre: a map 7.5° of tyre angle off, accepted.
    """
    pot = points.pot_counts[mask]
    grid = np.linspace(float(pot.min()), float(pot.max()), 4096)

    def moved(centre: float) -> float | None:
        """The map's zero less the centre it was fitted about."""
        fit = _solve(points, mask, centre, powers)
        values = fit.offset_rad + _value(fit.coeffs, grid - centre)
        crossings = np.flatnonzero(np.sign(values[:-1]) != np.sign(values[1:]))
        if crossings.size != 1:
            return None
        i = int(crossings[0])
        root = float(grid[i] - values[i] * (grid[i + 1] - grid[i]) / (values[i + 1] - values[i]))
        return root - centre

    before, moved_before = start, moved(start)
    if moved_before is None:
        return None
    centre = start + moved_before  # the first refit's zero
    for _ in range(ENCODER_ZERO_REFITS):
        step = moved(centre)
        if step is None:
            return None
        if abs(step) < 1e-3:
            return centre + step
        slope = (step - moved_before) / (centre - before) if centre != before else 0.0
        before, moved_before = centre, step
        # The secant's step where the difference has a slope to divide by, else a refit's.
        centre = centre - step / slope if slope != 0.0 else centre + step
        if not math.isfinite(centre):
            return None
    return None


def _value(coeffs: tuple[float, ...], offsets: FloatArray) -> FloatArray:
    return np.asarray(np.polynomial.polynomial.polyval(offsets, (0.0, *coeffs)), np.float64)


def _slope(coeffs: tuple[float, ...], offsets: FloatArray) -> FloatArray:
    derivative = [(i + 1) * c for i, c in enumerate(coeffs)]
    return np.asarray(np.polynomial.polynomial.polyval(offsets, derivative), np.float64)
