"""The simulated steering linkage: the constant ratio plus a cubic scaled to the lock."""

from __future__ import annotations

import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from appliance.sim.linkage import SteeringLinkage


@given(st.floats(-0.3, 0.3), st.floats(-9.42, 9.42), st.floats(-9.42, 9.42))
# Two wheel angles a denormal apart at the centre: both tyre angles round to zero (−0.0
# and 0.0, equal), so only "never decreasing" holds there (hypothesis seed 46).
@example(0.0, -5e-324, 0.0)
def test_odd_increasing_and_the_ratio_at_the_centre(cubic: float, a: float, b: float) -> None:
    linkage = SteeringLinkage(18.0, 9.42, cubic)
    assert linkage.tyre_rad(-a) == -linkage.tyre_rad(a)
    if a <= b:
        assert linkage.tyre_rad(a) <= linkage.tyre_rad(b)
    if b - a > 1e-12:  # any difference a linkage has: the tyre angles differ too
        assert linkage.tyre_rad(a) < linkage.tyre_rad(b)
    assert linkage.tyre_rad(1e-6) == pytest.approx(1e-6 / 18.0, rel=1e-9)


def test_the_cubic_is_its_share_at_the_lock() -> None:
    assert SteeringLinkage(18.0, 9.42, 0.06).tyre_rad(9.42) == pytest.approx(9.42 / 18 * 1.06)


@pytest.mark.parametrize("cubic", [-0.34, 1.0])
def test_a_linkage_that_folds_before_the_lock_is_refused(cubic: float) -> None:
    with pytest.raises(ValueError, match="fold"):
        SteeringLinkage(18.0, 9.42, cubic)
