"""The palm tree's wheel-to-tyre map in the calibration file: validated, and inverted."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.config.calibration import Calibration
from appliance.config.calibration_file import parse_calibration
from tests.unit.config.test_calibration_file import calfile_text, problems_of

# A linkage that turns the tyre 6 % further than the ratio at a wheel angle of 9.4 rad.
C1 = 1.0 / 18.0
C3 = 0.06 * C1 / 9.4**2
MAP = {"steering.wheel_to_tyre_coeffs": f"[{C1!r}, 0.0, {C3!r}]"}


def mapped() -> Calibration:
    return Calibration.from_file(parse_calibration(calfile_text(MAP), "sim"))


def test_without_a_map_the_ratio_converts_both_ways() -> None:
    cal = Calibration.from_file(parse_calibration(calfile_text(), "sim"))
    assert cal.wheel_to_tyre_coeffs is None
    assert cal.tyre_rad_from_wheel(1.8) == pytest.approx(0.1)
    assert cal.wheel_rad_from_tyre(0.1) == pytest.approx(1.8)


def test_the_map_rules_where_there_is_one() -> None:
    cal = mapped()
    wheel = 9.0
    assert cal.tyre_rad_from_wheel(wheel) == pytest.approx(C1 * wheel + C3 * wheel**3, rel=1e-12)
    low, high = cal.valid_wheel_range_rad
    assert cal.valid_tyre_range_rad == (cal.tyre_rad_from_wheel(low), cal.tyre_rad_from_wheel(high))


@given(st.floats(-0.6, 0.6))
def test_wheel_from_tyre_inverts_the_map_and_runs_on_past_the_range(tyre_rad: float) -> None:
    cal = mapped()
    wheel = cal.wheel_rad_from_tyre(tyre_rad)
    low, high = cal.valid_wheel_range_rad
    if low <= wheel <= high:
        assert cal.tyre_rad_from_wheel(wheel) == pytest.approx(tyre_rad, abs=1e-12)
    else:  # beyond the measured range: the end slope, never folding back
        assert (wheel > high) == (tyre_rad > 0.0)
    if abs(tyre_rad) > 1e-9:  # the bisection resolves 30 rad / 2**50
        assert math.copysign(1.0, wheel) == math.copysign(1.0, tyre_rad)


def test_a_map_whose_slope_disagrees_with_the_ratio_is_refused() -> None:
    problems = problems_of(calfile_text({"steering.wheel_to_tyre_coeffs": f"[{C1 * 1.01!r}]"}))
    assert "1 / steering_ratio" in " ".join(problems.values()), problems


def test_a_map_that_folds_inside_the_pots_range_is_refused() -> None:
    folding = {"steering.wheel_to_tyre_coeffs": f"[{C1!r}, 0.0, {-C1 / 9.0**2!r}]"}
    problems = problems_of(calfile_text(folding))
    assert "not strictly increasing" in " ".join(problems.values()), problems


def test_too_many_coefficients_are_refused() -> None:
    problems = problems_of(
        calfile_text({"steering.wheel_to_tyre_coeffs": f"[{C1!r}" + ", 0.0" * 7 + "]"})
    )
    assert any("wheel_to_tyre_coeffs" in field for field in problems), problems


@pytest.mark.parametrize("tyre_rad", [math.nan, math.inf, -math.inf])
def test_a_non_finite_tyre_angle_gives_no_finite_wheel_angle(tyre_rad: float) -> None:
    assert not math.isfinite(mapped().wheel_rad_from_tyre(tyre_rad))
