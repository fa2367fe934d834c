"""The pedal-map fit recovers the simulated vehicle's throttle and brake response from
throttle and brake sweeps run on ``appliance.sim.vehicle.step``."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import isotonic_regression

from calibration.pedal_map import (
    REASONS,
    PedalMap,
    PedalMapAccumulator,
    PedalMapParams,
    PedalMapResult,
    fit_pedal_map,
)
from calibration.pedal_map_cells import CellEstimate, assemble_map, isotonic, local_slope
from tests.unit.calibration.synthetic import PEDAL_VEHICLE, PedalSweep, pedal_sweep, true_accel_mps2

FIGURE = 0.05  # within 5 % of the actuator's full scale (1 m/s² throttle, 3 m/s² brake)


def fit(sweep: PedalSweep, params: PedalMapParams | None = None) -> PedalMapResult:
    return fit_pedal_map(*_columns(sweep), params)


def worst_error_of_full_scale(result: PedalMapResult) -> dict[str, float]:
    """Each map's largest error over its known cells (measured or bridged), as a fraction
    of the pedal's full scale, against the vehicle's own acceleration."""
    worst = {}
    for name, pedal_map, full_scale in (
        ("throttle", result.throttle, PEDAL_VEHICLE.max_accel_mps2),
        ("brake", result.brake, PEDAL_VEHICLE.max_decel_mps2),
    ):
        errors = [0.0]
        for (i, j), value in np.ndenumerate(pedal_map.accel_mps2):
            if np.isfinite(value):
                level, speed = pedal_map.pedal_pct[i], pedal_map.speed_mps[j]
                pedals = (level, 0.0) if name == "throttle" else (0.0, level)
                errors.append(abs(value - true_accel_mps2(*pedals, speed)) / full_scale)
        worst[name] = max(errors)
    return worst


SWEEPS = {seed: pedal_sweep(seed, spikes=10) for seed in (0, 1)}


@pytest.mark.parametrize("seed", sorted(SWEEPS))
def test_recovers_both_maps_within_the_figure(seed: int) -> None:
    result = fit(SWEEPS[seed])
    assert result.verdict.accepted, result.verdict.reasons
    worst = worst_error_of_full_scale(result)
    assert worst["throttle"] < FIGURE and worst["brake"] < FIGURE, worst
    assert result.rejected["speed_spike"] == 10
    # the sweep reaches every speed band with most throttle levels, and the hard brakes
    # only the low bands: the coverage says so
    assert np.all(result.throttle.levels_measured_per_band() >= 6)
    assert result.brake.measured[10, :].sum() < result.brake.measured[1, :].sum()
    assert np.all(result.brake.decel_mps2[np.isfinite(result.brake.decel_mps2)] > 0.0)


def test_without_settling_the_brake_map_misses_the_figure() -> None:
    """Why the settling time: cells filled while the brake is still building read low."""
    hasty = PedalMapParams(traction_settle_s=0.0, brake_settle_s=0.0)
    assert worst_error_of_full_scale(fit(SWEEPS[0], hasty))["brake"] > FIGURE


def test_maps_are_monotonic_in_the_pedal() -> None:
    result = fit(SWEEPS[1])
    _assert_monotonic(result.throttle, increasing=True)
    _assert_monotonic(result.brake, increasing=False)


def test_both_pedals_and_levels_off_the_grid_are_refused_with_their_reasons() -> None:
    t, speed, throttle, brake = (c.copy() for c in _columns(SWEEPS[0]))
    throttle[1000:1050], brake[1000:1050] = 30.0, 30.0
    coasting = np.flatnonzero((throttle == 0.0) & (brake == 0.0))[:20]
    brake[coasting] = 15.0  # between the grid's 10 and 20
    result = fit_pedal_map(t, speed, throttle, brake)
    assert result.rejected["both_pedals"] == 50
    assert result.rejected["off_grid"] == 20


def test_a_sweep_of_one_pedal_only_is_refused() -> None:
    sweep = SWEEPS[0]
    throttle_only = sweep.t_s < sweep.t_s[-1] / 2
    result = fit(PedalSweep(*(c[throttle_only] for c in _columns(sweep))))
    assert not result.verdict.accepted
    assert any(reason.startswith("brake: fewer than") for reason in result.verdict.reasons)


def test_the_accumulator_fills_its_grid_and_fits_as_the_batch_does() -> None:
    sweep = SWEEPS[0]
    accumulator = PedalMapAccumulator()
    assert accumulator.coverage().throttle_cells_full == 0
    full = []
    for i, row in enumerate(zip(*_columns(sweep), strict=True)):
        accumulator.update(*row)
        if i % 2000 == 0:
            full.append(accumulator.coverage().throttle_cells_full)
    assert full == sorted(full)
    coverage = accumulator.coverage()
    streamed, batch = accumulator.fit(), fit(sweep)
    assert np.all(coverage.throttle_counts >= batch.throttle.counts)
    assert np.all(coverage.brake_counts[batch.brake.measured] >= coverage.min_bin_samples)
    assert np.array_equal(streamed.brake.accel_mps2, batch.brake.accel_mps2, equal_nan=True)
    assert streamed.rejected == batch.rejected
    accumulator.reset()
    assert accumulator.coverage().brake_cells_full == 0
    with pytest.raises(ValueError, match="non-finite"):
        accumulator.update(0.0, np.nan, 0.0, 0.0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda c: (c[0], c[1][:-1], c[2], c[3]), "differ in length"),
        (lambda c: (c[0], c[1], c[2], np.full_like(c[3], np.inf)), "non-finite"),
        (lambda c: tuple(x[:4] for x in c), "too few samples"),
        (lambda c: (c[0] * 0.0, *c[1:]), "two samples at"),
        (lambda c: (c[0][:, None], *c[1:]), "one-dimensional"),
    ],
)
def test_malformed_input_raises_value_error(
    change: Callable[[tuple[np.ndarray, ...]], tuple[np.ndarray, ...]], message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        fit_pedal_map(*change(_columns(SHORT)))


def test_a_grid_that_does_not_increase_raises_value_error() -> None:
    with pytest.raises(ValueError, match="speed_band_edges_mps must be increasing"):
        fit(SHORT, PedalMapParams(speed_band_edges_mps=(1.0, 1.0)))
    with pytest.raises(ValueError, match="throttle_levels_pct"):
        PedalMapAccumulator(PedalMapParams(throttle_levels_pct=(20.0, 10.0)))


SHORT = pedal_sweep(2, levels=(30.0, 70.0))


@settings(max_examples=15)
@given(st.integers(0, 2**32 - 1))
def test_the_fit_does_not_depend_on_the_order_of_the_samples(seed: int) -> None:
    order = np.random.default_rng(seed).permutation(SHORT.t_s.size)
    shuffled = fit_pedal_map(*(c[order] for c in _columns(SHORT)))
    original = fit(SHORT)
    assert np.array_equal(
        shuffled.throttle.accel_mps2, original.throttle.accel_mps2, equal_nan=True
    )
    assert shuffled.rejected == original.rejected


@settings(max_examples=40)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(10, 600), min_bin=st.integers(1, 20))
def test_random_recordings_give_monotonic_maps_and_count_every_sample_once(
    seed: int, n: int, min_bin: int
) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 0.3, n))
    levels = np.array([0.0, 10.0, 25.0, 50.0, 100.0])
    throttle = np.repeat(rng.choice(levels, n // 20 + 1), 20)[:n]
    brake = np.repeat(rng.choice(levels, n // 20 + 1), 20)[:n] * (rng.random(n) < 0.5)
    speed = np.abs(np.cumsum(rng.normal(0.0, 0.3, n))) + rng.normal(0.0, 0.05, n)
    params = PedalMapParams(min_bin_samples=min_bin, traction_settle_s=0.5, brake_settle_s=0.2)
    result = fit_pedal_map(t, speed, throttle, brake, params)
    assert set(result.rejected) == set(REASONS)
    assert result.accepted + sum(result.rejected.values()) == n
    _assert_monotonic(result.throttle, increasing=True)
    _assert_monotonic(result.brake, increasing=False)


@settings(max_examples=50)
@given(
    values=st.lists(st.floats(-5.0, 5.0), min_size=1, max_size=12),
    seed=st.integers(0, 2**32 - 1),
)
def test_isotonic_matches_scipy(values: list[float], seed: int) -> None:
    y = np.asarray(values)
    w = np.random.default_rng(seed).uniform(0.5, 50.0, y.size)
    expected = isotonic_regression(y, weights=w).x
    assert np.allclose(isotonic(y, w), expected, atol=1e-9)


@settings(max_examples=50)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 60))
def test_local_slope_matches_polyfit(seed: int, n: int) -> None:
    rng = np.random.default_rng(seed)
    t = 1000.0 + np.cumsum(rng.uniform(0.01, 0.2, n))
    y = rng.normal(0.0, 1.0, n)
    use = rng.random(n) < 0.8
    low, high = np.array([0]), np.array([n])
    slope = local_slope(t, y, low, high, use)[0]
    if np.count_nonzero(use) >= 2:
        assert slope == pytest.approx(np.polyfit(t[use], y[use], 1)[0], rel=1e-6, abs=1e-9)
    else:
        assert slope == 0.0


def _assert_monotonic(pedal_map: PedalMap, increasing: bool) -> None:
    for band in range(pedal_map.accel_mps2.shape[1]):
        column = pedal_map.accel_mps2[:, band]
        steps = np.diff(column[np.isfinite(column)])
        assert np.all(steps >= -1e-12 if increasing else steps <= 1e-12)


def _columns(sweep: PedalSweep) -> tuple[np.ndarray, ...]:
    return sweep.t_s, sweep.speed_mps, sweep.throttle_pct, sweep.brake_pct


def test_a_level_missing_in_a_band_is_carried_from_its_nearest_band_along_the_slope() -> None:
    """A throttle with a dead band: accel = 2.0 max(0, (p - 10) / 90)^1.5 - 0.1 v. The 20 %
    level is measured in bands 0 and 2, not 1; coasting and 40 % in all three. The carry
    along the map's slope gives the truth; a line from coasting to 40 % would not."""
    levels = (0.0, 20.0, 40.0)
    edges = (0.5, 1.5, 2.5, 3.5)
    speeds = (1.0, 2.0, 3.0)

    def truth(pct: float, speed: float) -> float:
        return 2.0 * max(0.0, (pct - 10.0) / 90.0) ** 1.5 - 0.1 * speed

    estimates = {}
    for level, pct in enumerate(levels):
        for band, speed in enumerate(speeds):
            if (level, band) != (1, 1):
                estimates[level * 3 + band] = CellEstimate(truth(pct, speed), 20, np.zeros(20))
    pedal_map = assemble_map(levels, edges, (3, 3), estimates, True, -0.1)
    assert pedal_map.filled[1, 1] and not pedal_map.measured[1, 1]
    assert pedal_map.accel_mps2[1, 1] == pytest.approx(truth(20.0, 2.0), abs=1e-12)
    line = 0.5 * (truth(0.0, 2.0) + truth(40.0, 2.0))
    assert abs(line - truth(20.0, 2.0)) > 0.1  # what the old line through it gave
    # A level measured nowhere else is still interpolated along the pedal, between its
    # band's measured neighbours.
    del estimates[1 * 3 + 0], estimates[1 * 3 + 2]
    alone = assemble_map(levels, edges, (3, 3), estimates, True, -0.1)
    assert alone.accel_mps2[1, 1] == pytest.approx(line, abs=1e-12)
