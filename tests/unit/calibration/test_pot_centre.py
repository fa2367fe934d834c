"""The pot-centre fit finds the simulated pot's straight-ahead reading from straight driving."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from calibration.pot_centre import (
    REASONS,
    PotCentreAccumulator,
    PotCentreParams,
    PotCentreResult,
    fit_pot_centre,
)
from tests.unit.calibration.synthetic import (
    COUNTS_PER_TYRE_DEG,
    MAPPING,
    StraightDrive,
    straight_drive,
)

FIGURE_TYRE_DEG = 0.1  # the centre within 0.1° of tyre angle


def fit(drive: StraightDrive) -> PotCentreResult:
    return fit_pot_centre(*_columns(drive), COUNTS_PER_TYRE_DEG, drive.steer_rate_rad_per_s)


def error_tyre_deg(centre_counts: float | None) -> float:
    assert centre_counts is not None
    return abs(centre_counts - MAPPING.centre_counts) / COUNTS_PER_TYRE_DEG


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_finds_the_centre_within_the_figure_and_drops_the_crowned_leg(seed: int) -> None:
    result = fit(straight_drive(seed, legs=4, crowned_leg=2))
    assert result.verdict.accepted, result.verdict.reasons
    assert error_tyre_deg(result.centre_counts) < FIGURE_TYRE_DEG
    crowned = [s for s in result.segments if 50.0 <= s.start_t_s < 75.0]
    assert [s.used for s in crowned] == [False]
    assert result.rejected["outlier_segment"] == crowned[0].samples
    assert result.segments_used == 3
    assert result.spread_tyre_deg < result.params.max_spread_tyre_deg


def test_a_plain_mean_would_be_biased_by_the_settling_after_a_lane_change() -> None:
    """Why the curvature correction: the legs after a lane change curve gently while
    every sample passes the yaw-rate gate, and their plain means miss the figure."""
    result = fit_pot_centre(*_columns(straight_drive(0, legs=3)), COUNTS_PER_TYRE_DEG)
    settling = [s for s in result.segments if s.start_t_s > 20.0]
    assert settling
    for segment in settling:
        assert error_tyre_deg(segment.mean_counts) > FIGURE_TYRE_DEG
        assert error_tyre_deg(segment.centre_counts) < FIGURE_TYRE_DEG / 2


def test_too_few_segments_and_too_little_distance_are_refused() -> None:
    result = fit(straight_drive(0, legs=1, leg_s=20.0))
    assert not result.verdict.accepted
    reasons = " ".join(result.verdict.reasons)
    assert "1 straight segment(s)" in reasons
    assert "driven straight" in reasons


def test_driving_too_slowly_is_counted_and_refused() -> None:
    drive = straight_drive(0, speed_mps=0.5)
    result = fit(drive)
    assert result.rejected["slow"] > 0.9 * drive.t_s.size
    assert not result.verdict.accepted


def test_rail_readings_and_a_bad_fix_are_counted_under_their_reasons() -> None:
    drive = straight_drive(0)
    pot = drive.pot_counts.copy()
    pot[100:110] = 4095.0
    fix_ok = np.ones_like(pot)
    fix_ok[200:260] = 0.0
    result = fit_pot_centre(
        drive.t_s,
        pot,
        drive.yaw_rate_rad_per_s,
        drive.speed_mps,
        COUNTS_PER_TYRE_DEG,
        drive.steer_rate_rad_per_s,
        fix_ok,
    )
    assert result.rejected["pot_out_of_range"] == 10
    assert result.rejected["fix_quality"] == 60
    assert error_tyre_deg(result.centre_counts) < FIGURE_TYRE_DEG


def test_the_accumulator_fills_up_and_fits_as_the_batch_does() -> None:
    drive = straight_drive(1, crowned_leg=2)
    accumulator = PotCentreAccumulator()
    assert accumulator.coverage().segments == 0
    seen = []
    for i, row in enumerate(zip(*_columns(drive), drive.steer_rate_rad_per_s, strict=True)):
        accumulator.update(*row)
        if i % 250 == 0:
            seen.append(accumulator.coverage().segments)
    assert seen == sorted(seen) and seen[-1] >= 3
    assert accumulator.coverage().complete
    streamed = accumulator.fit(COUNTS_PER_TYRE_DEG)
    batch = fit(drive)
    assert streamed.centre_counts == pytest.approx(batch.centre_counts, abs=1e-9)
    assert streamed.rejected == batch.rejected
    accumulator.reset()
    assert accumulator.coverage().segments == 0
    with pytest.raises(ValueError, match="too few samples"):
        accumulator.fit(COUNTS_PER_TYRE_DEG)


def test_the_accumulator_refuses_nan() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        PotCentreAccumulator().update(0.0, float("nan"), 0.0, 3.0)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda c: (c[0][:-1], *c[1:]), "differ in length"),
        (lambda c: (c[0], np.full_like(c[1], np.nan), *c[2:]), "non-finite"),
        (lambda c: (c[0].reshape(-1, 2), *c[1:]), "one-dimensional"),
        (lambda c: tuple(x[:5] for x in c), "too few samples"),
        (lambda c: (np.zeros_like(c[0]), *c[1:]), "two samples at"),
        (lambda c: (c[0], ["a"] * c[1].size, *c[2:]), "not an array of numbers"),
    ],
)
def test_malformed_input_raises_value_error(
    change: Callable[[tuple[np.ndarray, ...]], tuple[object, ...]], message: str
) -> None:
    columns = change(_columns(straight_drive(0, legs=1, leg_s=4.0)))
    with pytest.raises(ValueError, match=message):
        fit_pot_centre(*columns, COUNTS_PER_TYRE_DEG)


def test_a_zero_slope_is_refused() -> None:
    with pytest.raises(ValueError, match="counts_per_tyre_deg"):
        fit_pot_centre(*_columns(straight_drive(0, legs=1, leg_s=4.0)), 0.0)


DRIVE = straight_drive(3, legs=3, crowned_leg=1)


@settings(max_examples=25)
@given(st.integers(0, 2**32 - 1))
def test_the_fit_does_not_depend_on_the_order_of_the_samples(seed: int) -> None:
    order = np.random.default_rng(seed).permutation(DRIVE.t_s.size)
    columns = [c[order] for c in _columns(DRIVE)]
    shuffled = fit_pot_centre(*columns, COUNTS_PER_TYRE_DEG, DRIVE.steer_rate_rad_per_s[order])
    original = fit(DRIVE)
    assert shuffled.centre_counts == original.centre_counts
    assert shuffled.rejected == original.rejected


@settings(max_examples=60)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(10, 400),
    max_yaw=st.floats(0.001, 0.5),
    min_segment_s=st.floats(0.0, 5.0),
)
def test_every_sample_is_accepted_or_refused_for_one_reason(
    seed: int, n: int, max_yaw: float, min_segment_s: float
) -> None:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.01, 0.8, n))
    pot = rng.choice([0.0, 2131.0, 4095.0], n, p=[0.05, 0.9, 0.05]) + rng.normal(0, 3, n)
    yaw = rng.normal(0.0, 0.05, n)
    speed = rng.uniform(0.0, 4.0, n)
    params = PotCentreParams(
        max_yaw_rate_rad_per_s=max_yaw, min_segment_s=min_segment_s, min_segment_m=0.0
    )
    fix = rng.integers(0, 2, n)
    result = fit_pot_centre(t, pot, yaw, speed, 56.5, rng.normal(0, 0.2, n), fix, params)
    assert set(result.rejected) == set(REASONS)
    assert result.accepted + sum(result.rejected.values()) == n
    assert sum(s.samples for s in result.segments if s.used) == result.accepted
    assert result.verdict.accepted == (not result.verdict.reasons)


def _columns(drive: StraightDrive) -> tuple[np.ndarray, ...]:
    return drive.t_s, drive.pot_counts, drive.yaw_rate_rad_per_s, drive.speed_mps
