"""The EKF's algebra in floats (``ekf_floats``) is the plain numpy algebra, to rounding.

Random but well-conditioned inputs (a covariance built as ``A Aᵀ`` plus a floor, a
Jacobian of the sizes the filter's models give): the float results must agree with
numpy's products, ``inv`` and ``solve`` to 1e-9 of the largest entry involved (rounding
in a 3x3 Joseph form of condition up to ~1e6 is below that by orders of magnitude).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.localization.ekf_floats import joseph_update, nis_2d, propagate

SEEDS = st.integers(min_value=0, max_value=2**32 - 1)


def _covariance(rng: np.random.Generator, size: int, scale: float) -> np.ndarray:
    a = rng.normal(0.0, scale, (size, size))
    return a @ a.T + np.eye(size) * scale * scale * 1e-3


def _close(got: np.ndarray, expected: np.ndarray) -> bool:
    return bool(np.abs(got - expected).max() <= 1e-9 * max(np.abs(expected).max(), 1e-300))


@settings(max_examples=300, deadline=None)
@given(SEEDS)
def test_joseph_update_is_the_plain_joseph_form(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p = _covariance(rng, 3, rng.uniform(1e-3, 1.0))
    r = _covariance(rng, 2, rng.uniform(1e-3, 0.1))
    h = rng.normal(0.0, 1.0, (2, 3))
    x = rng.normal(0.0, 5.0, 3)
    y = rng.normal(0.0, 0.1, 2)
    updated = joseph_update(x.tolist(), p.tolist(), h.tolist(), r.tolist(), (y[0], y[1]))
    assert updated is not None
    s = h @ p @ h.T + r
    k = p @ h.T @ np.linalg.inv(s)
    i_kh = np.eye(3) - k @ h
    expected_p = i_kh @ p @ i_kh.T + k @ r @ k.T
    expected_p = 0.5 * (expected_p + expected_p.T)
    assert _close(np.array(updated[0]), x + k @ y)
    assert _close(np.array(updated[1]), expected_p)
    assert nis_2d(h.tolist(), p.tolist(), r.tolist(), y[0], y[1]) == pytest.approx(
        float(y @ np.linalg.solve(s, y)), rel=1e-9
    )


@settings(max_examples=300, deadline=None)
@given(SEEDS)
def test_propagate_is_the_plain_products(seed: int) -> None:
    rng = np.random.default_rng(seed)
    p, q = _covariance(rng, 3, 0.1), _covariance(rng, 3, 0.01)
    j_pose, j_delta = rng.normal(0.0, 1.0, (3, 3)), rng.normal(0.0, 1.0, (3, 3))
    got = np.array(propagate(p.tolist(), j_pose.tolist(), j_delta.tolist(), q.tolist()))
    assert _close(got, j_pose @ p @ j_pose.T + j_delta @ q @ j_delta.T)


def test_a_singular_innovation_covariance_gives_none() -> None:
    zero = [[0.0, 0.0, 0.0]] * 3
    h = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    assert joseph_update([0.0, 0.0, 0.0], zero, h, [[0.0, 0.0], [0.0, 0.0]], (0.1, 0.1)) is None
    with pytest.raises(ZeroDivisionError):
        nis_2d(h, zero, [[0.0, 0.0], [0.0, 0.0]], 0.1, 0.1)
