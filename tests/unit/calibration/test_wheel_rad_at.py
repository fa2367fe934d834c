"""The pot map's evaluation: a float through Horner's rule gives numpy's polyval to the bit."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from calibration.pot_map import wheel_rad_at

coefficient = st.floats(min_value=-1.0, max_value=1.0).map(lambda c: c * 1e-3)
counts = st.floats(min_value=-4095.0, max_value=4095.0)


@given(st.lists(coefficient, min_size=1, max_size=9), counts)
def test_a_float_gives_polyvals_bits(coeffs: list[float], offset_counts: float) -> None:
    expected = float(np.polynomial.polynomial.polyval(offset_counts, (0.0, *coeffs)))
    assert wheel_rad_at(coeffs, offset_counts) == expected


@given(st.lists(coefficient, min_size=1, max_size=9), st.lists(counts, min_size=1, max_size=20))
def test_an_array_gives_each_floats_value(coeffs: list[float], offsets: list[float]) -> None:
    values = wheel_rad_at(coeffs, np.array(offsets))
    assert [float(v) for v in values] == [wheel_rad_at(coeffs, o) for o in offsets]


def test_a_nan_reading_is_nan() -> None:
    assert math.isnan(wheel_rad_at((0.001, 1e-9), math.nan))
