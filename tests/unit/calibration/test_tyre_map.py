"""The wheel to tyre map: a polynomial without a constant, checked for monotonicity."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.tyre_map import TyreMap, fit_tyre_map

WHEEL = np.linspace(-9.4, 9.4, 9)
DENSE = np.linspace(-9.4, 9.4, 401)


def linkage(wheel: np.ndarray) -> np.ndarray:
    """Stanley et al.'s eq. 4 shape, 1:18 at the centre."""
    return np.asarray(np.arcsin(2.0 * np.sin(wheel / 36.0)))


def test_exact_on_an_odd_polynomial() -> None:
    truth = TyreMap((1 / 18, 0.0, 2e-5, 0.0, -1e-7), -9.4, 9.4)
    fit = fit_tyre_map(WHEEL, truth.tyre_rad(WHEEL), np.full(9, 1e-3))
    assert fit.tyre_map.coeffs == pytest.approx(truth.coeffs, rel=1e-9, abs=1e-15)
    assert fit.residual_max_deg < 1e-9
    assert fit.monotonic
    assert fit.tyre_map.centre_ratio == pytest.approx(18.0)
    assert (fit.tyre_map.wheel_min_rad, fit.tyre_map.wheel_max_rad) == (-9.4, 9.4)


def test_a_linkage_is_followed_where_the_steering_ratio_is_not() -> None:
    fit = fit_tyre_map(WHEEL, linkage(WHEEL), np.full(9, math.radians(0.05)))
    assert math.degrees(np.max(np.abs(DENSE / 18.0 - linkage(DENSE)))) > 1.0
    assert math.degrees(np.max(np.abs(fit.tyre_map.tyre_rad(DENSE) - linkage(DENSE)))) < 0.01


def test_even_powers_follow_a_lopsided_linkage() -> None:
    tyre = linkage(WHEEL) + 2e-4 * WHEEL**2
    odd = fit_tyre_map(WHEEL, tyre, np.full(9, 1e-3))
    both = fit_tyre_map(WHEEL, tyre, np.full(9, 1e-3), powers=(1, 2, 3, 5))
    assert odd.residual_max_deg > 0.5
    assert both.residual_max_deg < 0.01
    assert both.monotonic


def test_a_fold_is_not_monotonic() -> None:
    tyre = np.sin(WHEEL / 4.0) * 0.5  # turns back past 6.3 rad
    fit = fit_tyre_map(WHEEL, tyre, np.full(9, 1e-3), powers=(1, 3, 5, 7))
    assert not fit.monotonic


def test_weights_follow_the_sigmas() -> None:
    tyre = WHEEL / 18.0
    tyre[0] += 0.01  # one bad point, declared bad
    sigma = np.full(9, 1e-4)
    sigma[0] = 1.0
    fit = fit_tyre_map(WHEEL, tyre, sigma, powers=(1,))
    assert fit.tyre_map.coeffs[0] == pytest.approx(1 / 18.0, rel=1e-3)


@pytest.mark.parametrize(
    ("powers", "n", "message"),
    [
        ((1, 3, 5), 3, "at least 4"),
        ((0, 1), 9, "positive"),
        ((1, 1), 9, "distinct"),
        ((), 9, "powers must be"),
    ],
)
def test_bad_requests_raise_value_error(powers: tuple[int, ...], n: int, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        fit_tyre_map(WHEEL[:n], WHEEL[:n] / 18, np.ones(n), powers=powers)


@pytest.mark.parametrize(
    ("wheel", "tyre", "sigma", "message"),
    [
        (np.zeros(5), np.zeros(5), np.ones(5), "all wheel angles are zero"),
        (WHEEL, WHEEL / 18, -np.ones(9), "negative"),
        (WHEEL, WHEEL[:8] / 18, np.ones(9), "differ in length"),
        (WHEEL, np.full(9, math.inf), np.ones(9), "non-finite"),
    ],
)
def test_garbage_raises_value_error(
    wheel: np.ndarray, tyre: np.ndarray, sigma: np.ndarray, message: str
) -> None:
    with pytest.raises(ValueError, match=message):
        fit_tyre_map(wheel, tyre, sigma)
