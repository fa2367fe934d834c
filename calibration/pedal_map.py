"""Throttle and brake maps: pedal command and speed to the acceleration the vehicle gets.

On the ``pedals`` speed path (the Husky) the speed loop turns a wanted acceleration into
throttle and brake percentages; how much acceleration a percentage gives, at what speed,
is the vehicle's (engine, gearbox, cable pre-tension, brake), so it is measured:
throttle held at steps from standstill, brake held at steps from speed, as Dataspeed's
throttle and brake sweeps and Autoware's accel_brake_map_calibrator do (pedal × speed
grid, a sample counted in a cell only when the pedal is steady and the speed is above a
threshold, cells filling up as the maneuver runs).

The method (:func:`fit_pedal_map`):

1. Acceleration from speed, by a local linear fit over ``derivative_window_s`` centred
   on each sample (a Savitzky–Golay first derivative that also takes uneven sampling):
   a two-point difference of GNSS speed amplifies its noise by the sample rate. A speed
   jump (``speed_spike_mps`` from the median of its neighbours) is left out of every
   window and refused itself: one jump would otherwise bend a second of derivatives,
   too many for a cell's outlier test when a hard brake crosses the cell in a third of
   a second.
2. A sample counts only when its whole derivative window saw one steady pedal command
   that had already been held long enough when the window opened: the traction and the
   brake answer a step with lags (0.4 s and 0.3 s in the simulated vehicle), and four
   lags leave under 2 % of the step: ``traction_settle_s`` after a hold that has the
   throttle pressed or follows one that had, else ``brake_settle_s`` (a brake step from
   a coast need not wait for the engine). And only when the window stays above
   ``min_speed_mps``, because a braked vehicle stops and its deceleration with it. A
   hard brake leaves little time at speed: its cells fill only below the speed it was
   applied at less the settling (at 3 m/s² and 1.2 s, 4 m/s less).
   Both pedals pressed at once is refused; both released is coasting, the 0 % column of
   both maps (the same physics).
3. Samples go to the nearest pedal level of the grid (refused beyond ``pedal_tol_pct``)
   and to a speed band. A cell with fewer than ``min_bin_samples`` stays empty (six
   samples at 20 Hz: a hard brake crosses a 1 m/s band in a third of a second). In each
   cell samples further than ``outlier_sigmas`` robust σ from the median are dropped (a
   GNSS speed jump spoils every window it falls in). The cell's value is its median read
   at the band's centre along one slope in speed, pooled over every cell of the map
   (each about its own means), so a cell's value does not depend on where in its band the
   sweep spent its time; a slope per cell would be fitted over a few tenths of a m/s and
   add more noise than it removes. (One slope for all levels: what changes with speed
   inside a band is mostly drag and rolling resistance, the same for every pedal.)
4. Per band, the cells are made monotonic in the pedal (more throttle never gives less
   acceleration, more brake never less deceleration) by weighted isotonic regression
   (pool adjacent violators, weights the cells' sample counts); the largest change it
   made is reported, since a big one means the data contradict the map. Empty cells
   between measured ones are filled (and marked): a level measured in another band is
   carried from the nearest such band along the map's speed slope, one measured nowhere
   is interpolated along the pedal, both kept monotonic in the band. Outside the measured
   cells the map stays NaN: an acceleration nobody measured is not extrapolated.
5. The verdict: every speed band with at least ``min_levels_per_band`` measured levels in
   each map (fewer cannot show the map's shape), the samples' residual rms about their
   cells' lines under ``max_residual_rms_mps2``, and the monotonic adjustment under
   ``max_monotonic_adjustment_mps2``. Assumed: a flat, level road (a grade adds g·sin θ
   to every cell).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Final

import numpy as np
import numpy.typing as npt

from calibration.fit_checks import (
    BoolArray,
    FloatArray,
    IntArray,
    Verdict,
    mad_sigma,
    sample_columns,
    tally,
    time_order,
)
from calibration.pedal_map_cells import (
    CellEstimate,
    PedalMap,
    assemble_map,
    cell_estimate,
    local_slope,
    pooled_slope,
    spikes,
)

METHOD: Final = (
    "local linear derivative of speed; samples with a steady pedal past the actuator lag, "
    "above a minimum speed; nearest pedal level x speed band; per cell outliers dropped "
    "and a line in speed read at the band centre; weighted isotonic regression in the "
    "pedal per band (calibration.pedal_map)"
)
MIN_SAMPLES: Final = 10
LEVELS: Final = tuple(float(x) for x in range(0, 101, 10))
REASONS: Final = (
    "speed_spike",
    "both_pedals",
    "off_grid",
    "settling",
    "window_cut",
    "slow",
    "out_of_bands",
    "sparse_cell",
    "outlier",
)


@dataclass(frozen=True)
class PedalMapParams:
    throttle_levels_pct: tuple[float, ...] = LEVELS
    brake_levels_pct: tuple[float, ...] = LEVELS
    speed_band_edges_mps: tuple[float, ...] = (0.5, 1.5, 2.5, 3.5, 4.5, 5.5)
    pedal_tol_pct: float = 2.0
    pedal_deadband_pct: float = 0.5  # at or below: released
    steady_pct: float = 0.5  # a pedal change larger than this restarts the settling
    max_gap_s: float = 0.5  # a gap in the samples also restarts it
    traction_settle_s: float = 1.6  # four traction lags
    brake_settle_s: float = 1.2  # four brake lags
    derivative_window_s: float = 1.0
    speed_spike_mps: float = 0.2  # six times a GNSS/INS speed's noise
    spike_half_width: int = 5
    min_speed_mps: float = 0.3
    min_bin_samples: int = 6
    outlier_sigmas: float = 4.0
    min_outlier_mps2: float = 0.05
    min_levels_per_band: int = 3
    max_residual_rms_mps2: float = 0.15
    max_monotonic_adjustment_mps2: float = 0.1


@dataclass(frozen=True)
class PedalMapResult:
    throttle: PedalMap
    brake: PedalMap
    residual_rms_mps2: float  # the samples used, about their cells' lines
    residual_max_mps2: float
    samples: int
    accepted: int
    rejected: dict[str, int]
    method: str
    verdict: Verdict
    params: PedalMapParams = field(repr=False)


@dataclass(frozen=True)
class PedalCoverage:
    """Samples per cell so far: the grid filling up (levels × bands for each pedal)."""

    throttle_counts: IntArray
    brake_counts: IntArray
    min_bin_samples: int

    @property
    def throttle_cells_full(self) -> int:
        return int(np.count_nonzero(self.throttle_counts >= self.min_bin_samples))

    @property
    def brake_cells_full(self) -> int:
        return int(np.count_nonzero(self.brake_counts >= self.min_bin_samples))


@dataclass(frozen=True)
class _Gated:
    accel: FloatArray
    speed: FloatArray
    reasons: list[tuple[str, BoolArray]]
    throttle_cell: IntArray  # flat cell index per sample, -1: not in the throttle map
    brake_cell: IntArray


def fit_pedal_map(
    t_s: npt.ArrayLike,
    speed_mps: npt.ArrayLike,
    throttle_pct: npt.ArrayLike,
    brake_pct: npt.ArrayLike,
    params: PedalMapParams | None = None,
) -> PedalMapResult:
    """Throttle and brake maps from pedal sweeps; ValueError on malformed input."""
    p = params or PedalMapParams()
    _check_params(p)
    gated = _gate(_columns(t_s, speed_mps, throttle_pct, brake_pct, MIN_SAMPLES), p)
    kept, _ = tally(gated.accel.size, gated.reasons)
    n = gated.accel.size
    # A coasting sample is in both maps: it is refused only if neither map used it.
    sparse, outlier, used_any = (np.zeros(n, dtype=np.bool_) for _ in range(3))
    residuals = np.full(n, np.nan)
    maps: list[PedalMap] = []
    for cells, levels, increasing in (
        (gated.throttle_cell, p.throttle_levels_pct, True),
        (gated.brake_cell, p.brake_levels_pct, False),
    ):
        shape = (len(levels), len(p.speed_band_edges_mps) - 1)
        groups: dict[int, IntArray] = {}
        for cell in np.unique(cells[kept & (cells >= 0)]).tolist():
            members = np.flatnonzero(kept & (cells == cell))
            if members.size < p.min_bin_samples:
                sparse[members] = True
                continue
            accel = gated.accel[members]
            limit = max(p.outlier_sigmas * mad_sigma(accel), p.min_outlier_mps2)
            far = np.abs(accel - np.median(accel)) > limit
            outlier[members[far]] = True
            groups[cell] = members[~far]
        slope = pooled_slope(gated.speed, gated.accel, list(groups.values()))
        estimates: dict[int, CellEstimate] = {}
        for cell, inliers in groups.items():
            band = cell % shape[1]
            centre = 0.5 * (p.speed_band_edges_mps[band] + p.speed_band_edges_mps[band + 1])
            estimates[cell] = cell_estimate(
                gated.speed[inliers], gated.accel[inliers], centre, slope
            )
            used_any[inliers] = True
            residuals[inliers] = estimates[cell].residuals
        maps.append(
            assemble_map(levels, p.speed_band_edges_mps, shape, estimates, increasing, slope)
        )
    kept, rejected = tally(
        n, [*gated.reasons, ("sparse_cell", sparse & ~used_any), ("outlier", outlier & ~used_any)]
    )
    used = residuals[kept & np.isfinite(residuals)]
    throttle, brake = maps
    return PedalMapResult(
        throttle=throttle,
        brake=brake,
        residual_rms_mps2=float(np.sqrt(np.mean(used**2))) if used.size else 0.0,
        residual_max_mps2=float(np.max(np.abs(used))) if used.size else 0.0,
        samples=n,
        accepted=int(np.count_nonzero(kept)),
        rejected=rejected,
        method=METHOD,
        verdict=_verdict(throttle, brake, used, p),
        params=p,
    )


class PedalMapAccumulator:
    """Samples as they arrive; ``coverage()`` shows the grid filling, ``fit()`` at the end."""

    def __init__(self, params: PedalMapParams | None = None) -> None:
        self.params = params or PedalMapParams()
        _check_params(self.params)
        self._rows: list[tuple[float, float, float, float]] = []

    def reset(self) -> None:
        self._rows.clear()

    def update(self, t_s: float, speed_mps: float, throttle_pct: float, brake_pct: float) -> None:
        row = (float(t_s), float(speed_mps), float(throttle_pct), float(brake_pct))
        if not all(np.isfinite(row)):
            raise ValueError(f"non-finite sample {row}: drop it upstream, do not send NaN")
        self._rows.append(row)

    def coverage(self) -> PedalCoverage:
        p = self.params
        shape = (len(p.throttle_levels_pct), len(p.speed_band_edges_mps) - 1)
        brake_shape = (len(p.brake_levels_pct), shape[1])
        throttle_counts = np.zeros(shape[0] * shape[1], dtype=np.intp)
        brake_counts = np.zeros(brake_shape[0] * brake_shape[1], dtype=np.intp)
        if len(self._rows) >= 2:
            t, speed, throttle, brake = np.asarray(self._rows).T
            gated = _gate(_columns(t, speed, throttle, brake, 0), p)
            kept, _ = tally(t.size, gated.reasons)
            np.add.at(throttle_counts, gated.throttle_cell[kept & (gated.throttle_cell >= 0)], 1)
            np.add.at(brake_counts, gated.brake_cell[kept & (gated.brake_cell >= 0)], 1)
        return PedalCoverage(
            throttle_counts.reshape(shape), brake_counts.reshape(brake_shape), p.min_bin_samples
        )

    def fit(self) -> PedalMapResult:
        data = np.asarray(self._rows).T if self._rows else np.zeros((4, 0))
        return fit_pedal_map(data[0], data[1], data[2], data[3], self.params)


def _check_params(p: PedalMapParams) -> None:
    for name in ("throttle_levels_pct", "brake_levels_pct", "speed_band_edges_mps"):
        values = np.asarray(getattr(p, name), dtype=np.float64)
        if values.size < (2 if name == "speed_band_edges_mps" else 1) or np.any(
            np.diff(values) <= 0.0
        ):
            raise ValueError(f"{name} must be increasing (got {values.tolist()})")


def _columns(
    t_s: npt.ArrayLike,
    speed_mps: npt.ArrayLike,
    throttle_pct: npt.ArrayLike,
    brake_pct: npt.ArrayLike,
    min_samples: int,
) -> dict[str, FloatArray]:
    columns = {"t_s": t_s, "speed_mps": speed_mps, "throttle_pct": throttle_pct}
    return time_order(sample_columns({**columns, "brake_pct": brake_pct}, min_samples))


def _gate(cols: dict[str, FloatArray], p: PedalMapParams) -> _Gated:
    """Each sample's acceleration, the reasons to refuse it, and its cell in each map."""
    t, speed = cols["t_s"], cols["speed_mps"]
    throttle, brake = cols["throttle_pct"], cols["brake_pct"]
    half = 0.5 * p.derivative_window_s
    low = np.searchsorted(t, t - half, side="left")
    high = np.searchsorted(t, t + half, side="right")
    jumps = spikes(speed, p.spike_half_width, p.speed_spike_mps)
    accel = local_slope(t, speed, low, high, ~jumps)
    changed = (np.abs(np.diff(throttle)) > p.steady_pct) | (np.abs(np.diff(brake)) > p.steady_pct)
    breaks = np.flatnonzero(changed | (np.diff(t) > p.max_gap_s)) + 1
    hold = np.zeros(t.size, dtype=np.intp)
    hold[breaks] = 1
    hold = np.cumsum(hold)
    starts = np.concatenate(([0], breaks))
    ends = np.concatenate((breaks, [t.size])) - 1
    since = t - t[starts[hold]]
    until = t[ends[hold]] - t
    traction = throttle > p.pedal_deadband_pct
    engine = traction[starts] | traction[np.maximum(starts - 1, 0)]
    settle = np.where(engine, p.traction_settle_s, p.brake_settle_s)[hold]
    stopped = np.concatenate(([0], np.cumsum(np.abs(speed) < p.min_speed_mps)))
    slow = (stopped[high] - stopped[low]) > 0
    pressed_t, pressed_b = traction, brake > p.pedal_deadband_pct
    edges = np.asarray(p.speed_band_edges_mps)
    band = np.searchsorted(edges, np.abs(speed), side="right") - 1
    bands = edges.size - 1
    outside = (band < 0) | (band >= bands)
    t_level, t_off = _nearest(throttle, p.throttle_levels_pct, p.pedal_tol_pct)
    b_level, b_off = _nearest(brake, p.brake_levels_pct, p.pedal_tol_pct)
    coasting = ~pressed_t & ~pressed_b
    off_grid = np.where(pressed_b, b_off, t_off) | (coasting & (t_off | b_off))
    throttle_cell = np.where(~pressed_b & ~outside & ~t_off, t_level * bands + band, -1)
    brake_cell = np.where((pressed_b | coasting) & ~outside & ~b_off, b_level * bands + band, -1)
    reasons: list[tuple[str, BoolArray]] = [
        ("speed_spike", jumps),
        ("both_pedals", pressed_t & pressed_b),
        ("off_grid", off_grid),
        ("settling", since < settle + half),
        ("window_cut", until < half),
        ("slow", slow),
        ("out_of_bands", outside),
    ]
    return _Gated(accel, np.abs(speed), reasons, throttle_cell, brake_cell)


def _nearest(
    pedal: FloatArray, levels: tuple[float, ...], tol: float
) -> tuple[IntArray, BoolArray]:
    grid = np.asarray(levels)
    index = np.argmin(np.abs(pedal[:, None] - grid[None, :]), axis=1)
    return index.astype(np.intp), np.abs(pedal - grid[index]) > tol


def _verdict(
    throttle: PedalMap, brake: PedalMap, residuals: FloatArray, p: PedalMapParams
) -> Verdict:
    reasons: list[str] = []
    for name, pedal_map in (("throttle", throttle), ("brake", brake)):
        per_band = pedal_map.levels_measured_per_band()
        thin = [
            f"{pedal_map.speed_mps[i]:g} m/s ({count})"
            for i, count in enumerate(per_band)
            if count < p.min_levels_per_band
        ]
        if thin:
            reasons.append(
                f"{name}: fewer than {p.min_levels_per_band} pedal levels measured in the "
                f"band(s) at {', '.join(thin)}"
            )
        if pedal_map.monotonic_adjustment_max_mps2 > p.max_monotonic_adjustment_mps2:
            reasons.append(
                f"{name}: making the map monotonic moved a cell by "
                f"{pedal_map.monotonic_adjustment_max_mps2:.3f} m/s², more than "
                f"{p.max_monotonic_adjustment_mps2} (a grade, wind, or a slipping cable?)"
            )
    rms = float(np.sqrt(np.mean(residuals**2))) if residuals.size else 0.0
    if rms > p.max_residual_rms_mps2:
        reasons.append(
            f"samples scatter {rms:.3f} m/s² rms about their cells, more than "
            f"{p.max_residual_rms_mps2}"
        )
    return Verdict.from_reasons(reasons)
