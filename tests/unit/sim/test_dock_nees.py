"""`dbw sim dock`'s NEES, in floats, is the plain ``eᵀ P⁻¹ e`` by numpy's solve, to rounding."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.sim.dock_run import _nees
from drivers.geometry import Pose2D


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_nees_is_numpys(seed: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, rng.uniform(1e-3, 0.3), (3, 3))
    covariance = a @ a.T + np.eye(3) * 1e-6
    estimate = Pose2D(*rng.normal(0.0, 3.0, 3))
    truth = Pose2D(*rng.normal(0.0, 3.0, 3))
    error = np.array(
        [
            estimate.x_m - truth.x_m,
            estimate.y_m - truth.y_m,
            math.remainder(estimate.yaw_rad - truth.yaw_rad, math.tau),
        ]
    )
    expected = float(error @ np.linalg.solve(covariance, error))
    assert _nees(estimate, covariance, truth) == pytest.approx(expected, rel=1e-7)


def test_a_singular_covariance_gives_nan() -> None:
    assert math.isnan(_nees(Pose2D(1.0, 0.0, 0.0), np.zeros((3, 3)), Pose2D(0.0, 0.0, 0.0)))
