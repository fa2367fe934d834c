"""The initial pose's agreement gate against scipy's chi-square quantile."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2

from appliance.localization.initial_pose import chi2_3dof_cdf, chi2_3dof_quantile


@given(st.floats(min_value=1e-6, max_value=1.0 - 1e-9))
def test_the_quantile_is_scipys(probability: float) -> None:
    assert chi2_3dof_quantile(probability) == pytest.approx(
        float(chi2.ppf(probability, 3)), rel=1e-9, abs=1e-12
    )


@given(st.floats(min_value=0.0, max_value=200.0))
def test_the_cdf_is_scipys(x: float) -> None:
    assert chi2_3dof_cdf(x) == pytest.approx(float(chi2.cdf(x, 3)), abs=1e-12)


@pytest.mark.parametrize("probability", [0.0, 1.0, -0.1, float("nan")])
def test_a_probability_outside_the_open_interval_is_refused(probability: float) -> None:
    with pytest.raises(ValueError, match="probability"):
        chi2_3dof_quantile(probability)
