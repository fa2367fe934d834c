"""The EKF's algebra in floats (``ekf_floats``, the board's motion) is the plain numpy
algebra, to rounding.

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

from appliance.localization.board_motion import (
    BoardEnd,
    BoardMotionParams,
    BoardSighting,
    motion_between,
)
from appliance.localization.compound import wrap_angle_rad
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


def _plain_motion(older: BoardSighting, newer: BoardSighting, params: BoardMotionParams):  # type: ignore[no-untyped-def]
    """`motion_between` with numpy arrays throughout: the straightforward reading."""
    dt_s = newer.t_s - older.t_s
    dyaw = wrap_angle_rad(older.alpha_rad - newer.alpha_rad)
    normal = np.array([np.cos(older.alpha_rad), np.sin(older.alpha_rad)])
    direction = np.array([-normal[1], normal[0]])
    var_normal = older.covariance[0, 0] + newer.covariance[0, 0]
    var_yaw = older.covariance[1, 1] + newer.covariance[1, 1]
    turn = np.array([[np.cos(dyaw), -np.sin(dyaw)], [np.sin(dyaw), np.cos(dyaw)]])
    estimates, variances = [], []
    for a, b in ((older.low_end, newer.low_end), (older.high_end, newer.high_end)):
        if a is not None and b is not None:
            apart = np.array([a.x_m, a.y_m]) - turn @ np.array([b.x_m, b.y_m])
            estimates.append(direction @ apart)
            variances.append(a.sigma_m**2 + b.sigma_m**2 + (b.x_m**2 + b.y_m**2) * var_yaw)
    if estimates:
        weights = 1.0 / np.array(variances)
        along, var_along = weights @ estimates / weights.sum(), 1.0 / weights.sum()
    else:
        along, var_along = 0.0, (params.unknown_along_sigma_mps * dt_s) ** 2
    translation = normal * (older.r_m - newer.r_m) + direction * along
    basis = np.column_stack((normal, direction))
    block = basis @ np.diag([var_normal, var_along]) @ basis.T
    covariance = np.zeros((3, 3))
    covariance[:2, :2], covariance[2, 2] = block, var_yaw
    return np.append(translation, dyaw) / dt_s, covariance / dt_s**2


def _sighting(rng: np.random.Generator, t_s: float) -> BoardSighting:
    def end() -> BoardEnd | None:
        if rng.random() < 0.3:
            return None
        return BoardEnd(*rng.normal(0.0, 2.0, 2), rng.uniform(0.005, 0.05))

    a = rng.normal(0.0, 0.01, (2, 2))
    cov = a @ a.T + np.diag([1e-6, 1e-8])
    return BoardSighting(t_s, rng.uniform(0.5, 10.0), rng.normal(0.0, 0.3), cov, end(), end())


@settings(max_examples=300, deadline=None)
@given(SEEDS)
def test_board_motion_in_floats_is_the_plain_array_computation(seed: int) -> None:
    rng = np.random.default_rng(seed)
    params = BoardMotionParams()
    older = _sighting(rng, 0.0)
    newer = _sighting(rng, rng.uniform(0.01, 0.3))
    found = motion_between(older, newer, params)
    assert found is not None
    velocity, covariance = _plain_motion(older, newer, params)
    assert _close(found.velocity, velocity)
    assert _close(found.covariance, covariance)
    assert found.correlation_time_s == newer.t_s - older.t_s
