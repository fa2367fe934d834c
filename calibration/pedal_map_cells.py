"""The pedal maps' arithmetic: a windowed derivative, cell values, isotonic regression,
and a map assembled from its cells.

Apart from :mod:`calibration.pedal_map` so that module reads as the method: what counts
as a sample, which cell it goes to, what makes a map acceptable.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.fit_checks import BoolArray, FloatArray, IntArray


def local_slope(
    t: FloatArray, y: FloatArray, low: IntArray, high: IntArray, use: BoolArray
) -> FloatArray:
    """Least squares slope of ``y`` against ``t`` over each window [low, high), using only
    the samples where ``use`` is True.

    Prefix sums make it O(n) for any window and any spacing; times are taken from the
    first sample so their squares do not swamp the window's own spread. A window with
    fewer than two samples, or all at one time, gets 0 (callers refuse those samples).
    """
    x = t - t[0]
    w = use.astype(np.float64)
    columns = (w, w * x, w * y, w * x * x, w * x * y)
    sums = [np.concatenate(([0.0], np.cumsum(v))) for v in columns]
    count, sx, sy, sxx, sxy = (s[high] - s[low] for s in sums)
    spread = count * sxx - sx * sx
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (count * sxy - sx * sy) / spread
    return np.where((count >= 2) & (spread > 1e-12 * np.maximum(count * sxx, 1e-300)), slope, 0.0)


def spikes(y: FloatArray, half_width: int, threshold: float) -> BoolArray:
    """Samples further than ``threshold`` from the median of their 2·half_width + 1
    neighbours (a Hampel filter: along a steady ramp the median is the middle sample,
    so only a jump stands out)."""
    if y.size < 2 * half_width + 1:
        return np.zeros(y.size, dtype=np.bool_)
    padded = np.pad(y, half_width, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, 2 * half_width + 1)
    return np.asarray(np.abs(y - np.median(windows, axis=1)) > threshold)


@dataclass(frozen=True)
class CellEstimate:
    value_mps2: float  # at the band's centre speed
    count: int  # samples used
    residuals: FloatArray  # of the samples used, about the cell's line


def pooled_slope(speed: FloatArray, accel: FloatArray, groups: list[IntArray]) -> float:
    """Least squares slope of acceleration against speed, each group about its own means
    (0 when no group has any spread in speed)."""
    covariance = variance = 0.0
    for members in groups:
        dv = speed[members] - speed[members].mean()
        covariance += float(np.dot(dv, accel[members] - accel[members].mean()))
        variance += float(np.dot(dv, dv))
    return covariance / variance if variance > 0.0 else 0.0


def cell_estimate(
    speed: FloatArray, accel: FloatArray, centre_mps: float, slope: float
) -> CellEstimate:
    """One cell's value at ``centre_mps``: the median of its samples moved along ``slope``."""
    moved = accel - slope * (speed - centre_mps)
    value = float(np.median(moved))
    return CellEstimate(value, int(accel.size), moved - value)


def isotonic(values: FloatArray, weights: FloatArray) -> FloatArray:
    """The non-decreasing sequence nearest ``values`` in weighted least squares (pool
    adjacent violators: merge neighbouring blocks into their weighted mean while a block
    sits above the next)."""
    means: list[float] = []
    masses: list[float] = []
    sizes: list[int] = []
    for value, weight in zip(values.tolist(), np.maximum(weights, 1e-12).tolist(), strict=True):
        means.append(value)
        masses.append(weight)
        sizes.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            mass = masses[-2] + masses[-1]
            mean = (means[-2] * masses[-2] + means[-1] * masses[-1]) / mass
            size = sizes[-2] + sizes[-1]
            del means[-1], masses[-1], sizes[-1]
            means[-1], masses[-1], sizes[-1] = mean, mass, size
    return np.repeat(np.asarray(means, dtype=np.float64), sizes)


@dataclass(frozen=True)
class PedalMap:
    """One pedal's map: ``accel_mps2[level, band]``, NaN where not measured or bridged."""

    pedal_pct: FloatArray
    speed_mps: FloatArray  # the bands' centres, where each cell's value is read
    accel_mps2: FloatArray  # signed: the brake's cells are negative
    counts: IntArray  # samples used per cell: the coverage
    measured: BoolArray
    filled: BoolArray  # interpolated between measured cells of the band
    cell_residual_rms_mps2: FloatArray
    monotonic_adjustment_max_mps2: float
    speed_slope_per_s: float  # d(accel)/d(speed) within a band, pooled over the cells

    @property
    def decel_mps2(self) -> FloatArray:
        """Deceleration, positive (the brake map's natural sign)."""
        return -self.accel_mps2

    def levels_measured_per_band(self) -> IntArray:
        return np.asarray(self.measured.sum(axis=0), dtype=np.intp)


def _fill_band(
    accel: FloatArray,
    measured: BoolArray,
    grid: FloatArray,
    speeds: FloatArray,
    band: int,
    slope: float,
    increasing: bool,
) -> None:
    """Fill the band's empty cells between its measured ones, in place.

    A level measured in another band is carried over from the nearest such band along the
    map's speed slope (what changes with speed is drag and rolling resistance, the same for
    every pedal: the slope is pooled over the map), kept between the band's measured
    neighbours so the band stays monotonic. Only a level measured in no band is
    interpolated along the pedal: a pedal's answer is not a line through its dead band,
    and a line from coasting to the next level overstates a low throttle by up to 10 % of
    the map's span (measured on the simulated Husky's shaped pedals).
    """
    rows = np.flatnonzero(measured[:, band])
    if rows.size == 0:
        return
    sign = 1.0 if increasing else -1.0  # in sign x accel every band rises with the pedal
    for level in range(rows[0] + 1, rows[-1]):
        if measured[level, band]:
            continue
        others = np.flatnonzero(measured[level, :])
        if others.size:
            nearest = others[np.argmin(np.abs(speeds[others] - speeds[band]))]
            value = accel[level, nearest] + slope * (speeds[band] - speeds[nearest])
        else:
            value = np.interp(grid[level], grid[rows], accel[rows, band])
        # Between the cell below (measured or just filled) and the next measured above.
        low = sign * accel[level - 1, band]
        high = sign * accel[rows[rows > level][0], band]
        accel[level, band] = sign * min(max(sign * value, low), high)


def assemble_map(
    levels: tuple[float, ...],
    band_edges_mps: tuple[float, ...],
    shape: tuple[int, int],
    estimates: dict[int, CellEstimate],
    increasing: bool,
    slope: float,
) -> PedalMap:
    """One pedal's map from its cells: monotonic per band by weighted isotonic regression,
    gaps between measured cells of a band interpolated, nothing extrapolated."""
    raw = np.full(shape, np.nan)
    counts = np.zeros(shape, dtype=np.intp)
    rms = np.full(shape, np.nan)
    for cell, estimate in estimates.items():
        raw.flat[cell] = estimate.value_mps2
        counts.flat[cell] = estimate.count
        rms.flat[cell] = float(np.sqrt(np.mean(estimate.residuals**2)))
    measured = np.isfinite(raw)
    accel = raw.copy()
    grid = np.asarray(levels)
    adjustment = 0.0
    for band in range(shape[1]):
        rows = np.flatnonzero(measured[:, band])
        if rows.size == 0:
            continue
        sign = 1.0 if increasing else -1.0  # the brake's acceleration falls with the pedal
        fitted = sign * isotonic(sign * raw[rows, band], counts[rows, band].astype(np.float64))
        adjustment = max(adjustment, float(np.max(np.abs(fitted - raw[rows, band]))))
        accel[rows, band] = fitted
    edges = np.asarray(band_edges_mps)
    speeds = 0.5 * (edges[:-1] + edges[1:])
    for band in range(shape[1]):
        _fill_band(accel, measured, grid, speeds, band, slope, increasing)
    return PedalMap(
        pedal_pct=grid,
        speed_mps=speeds,
        accel_mps2=accel,
        counts=counts,
        measured=measured,
        filled=np.isfinite(accel) & ~measured,
        cell_residual_rms_mps2=rms,
        monotonic_adjustment_max_mps2=adjustment,
        speed_slope_per_s=slope,
    )
