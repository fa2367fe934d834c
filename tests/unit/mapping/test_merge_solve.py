"""Eqs. 1-2 of Kinouchi et al.: the closed form against a generic least-squares solver,
the global minimum, exact recovery, symmetry, refusals, the propagated covariance."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import assume, example, given
from hypothesis import strategies as st
from scipy.optimize import least_squares, minimize_scalar

from appliance.mapping.pallets import PalletKind
from appliance.mapping.transform_fit import (
    MergeRefusal,
    TransformFit,
    minimize_angle_rad,
    solve_transform,
)

TWO_PI = 2.0 * math.pi


def _rotate(xy: np.ndarray, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    result: np.ndarray = xy @ np.array([[c, -s], [s, c]]).T
    return result


def _problem(
    seed: int, n: int, yaw: float, noise_m: float = 0.0, noise_rad: float = 0.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vehicle pallets and the worker's, ``T = (3, −2, yaw)`` mapping the first onto the
    second, postures off by whole symmetry turns as a detector reports them."""
    rng = np.random.default_rng(seed)
    q = rng.uniform(-10.0, 10.0, (n, 2))
    psi = rng.uniform(-math.pi, math.pi, n)
    symmetry = rng.choice([PalletKind.JIS.symmetry_rad, PalletKind.EUR.symmetry_rad], n)
    p = _rotate(q, yaw) + np.array([3.0, -2.0]) + rng.normal(0.0, noise_m, (n, 2))
    phi = psi + yaw + rng.integers(-3, 4, n) * symmetry + rng.normal(0.0, noise_rad, n)
    return q, psi, p, phi, symmetry


def _exact_rotation_rad(q: np.ndarray, p: np.ndarray) -> float:
    """The rotation that best maps the points ``q`` onto ``p`` (least squares, no
    postures): atan2 of the centred points' cross and dot sums, in exact rational
    arithmetic, rounded once at the end."""
    qs = [[Fraction(float(v)) for v in row] for row in q]
    ps = [[Fraction(float(v)) for v in row] for row in p]
    qc = [sum(row[i] for row in qs) / len(qs) for i in (0, 1)]
    pc = [sum(row[i] for row in ps) / len(ps) for i in (0, 1)]
    cross = dot = Fraction(0)
    for (qx, qy), (px, py) in zip(qs, ps, strict=True):
        a, b, c, d = qx - qc[0], qy - qc[1], px - pc[0], py - pc[1]
        cross += a * d - b * c
        dot += a * c + b * d
    return math.atan2(float(cross), float(dot))


def _fit(*args: object, **kwargs: object) -> TransformFit:
    fit = solve_transform(*args, **kwargs)  # type: ignore[arg-type]
    assert isinstance(fit, TransformFit), fit
    return fit


@given(
    st.integers(0, 2**32 - 1),
    st.integers(2, 12),
    st.floats(-math.pi, math.pi),
    st.sampled_from([0.0, 0.01, 1.31, 50.0]),
)
@example(seed=4, n=4, yaw=-2.21484375, w=0.0)  # least_squares 1.2e-9 rad off, ours exact
def test_the_closed_form_is_scipys_least_squares(seed: int, n: int, yaw: float, w: float) -> None:
    """θ to 1e-8 rad, x and y to 1e-9 of the map's size (1e-8 m over ±10 m), and never a
    higher E. Why not 1e-9: least_squares stops where E's rounding (the residuals carry
    ~1e-15 m on 10 m coordinates) hides its progress, a few 1e-9 m and up to 1.2e-9 rad
    from the minimum over these problems' 10 m lever (seen: the example above, where
    the closed form is θ in exact rational arithmetic to the last bit); the closed form
    solves dE/dθ = 0 itself. Without the postures' term (w = 0) it is checked against
    that exact θ too."""
    q, psi, p, phi, symmetry = _problem(seed, n, yaw, 0.02, math.radians(1.0))
    # Well posed: the pallets spread (rms) over 3 m at least, not two a metre apart.
    assume(math.sqrt(float(np.mean(np.sum((q - q.mean(axis=0)) ** 2, axis=1)))) >= 3.0)
    fit = _fit(q, psi, p, phi, symmetry, w)
    # The representatives chosen independently of the solver: nearest the true turn.
    d = np.array(
        [
            -yaw + (a - b + yaw + s / 2) % s - s / 2
            for a, b, s in zip(psi, phi, symmetry, strict=True)
        ]
    )

    def residuals(x: np.ndarray) -> np.ndarray:
        e = _rotate(q, x[2]) + x[:2] - p
        return np.concatenate([e.ravel(), math.sqrt(w) * (x[2] + d)])

    start = np.array([3.0 + 0.3, -2.0 - 0.2, yaw + 0.1])
    reference = least_squares(residuals, start, ftol=1e-15, xtol=1e-15, gtol=1e-15).x
    x, y, theta = fit.vehicle_in_worker
    assert x == pytest.approx(reference[0], abs=1e-8)
    assert y == pytest.approx(reference[1], abs=1e-8)
    assert math.remainder(theta - reference[2], TWO_PI) == pytest.approx(0.0, abs=1e-8)
    if w == 0.0:
        exact = _exact_rotation_rad(q, p)
        assert math.remainder(theta - exact, TWO_PI) == pytest.approx(0.0, abs=1e-12)
    reference_cost = 0.5 * float(np.sum(residuals(reference) ** 2))
    assert fit.cost == pytest.approx(reference_cost, rel=1e-9)
    unwrapped = reference[2] + math.remainder(theta - reference[2], TWO_PI)  # d's branch
    ours_cost = 0.5 * float(np.sum(residuals(np.array([x, y, unwrapped])) ** 2))
    assert ours_cost <= reference_cost + 1e-14  # E's own rounding here: ~1e-15 m on 10 m


@pytest.mark.parametrize("yaw", [0.0, 1.0, 2.5, math.pi - 1e-3, -math.pi + 1e-3, -2.0])
@pytest.mark.parametrize("w", [0.0, 1.31])
def test_a_known_transform_is_recovered_from_noiseless_pairs(yaw: float, w: float) -> None:
    # |yaw| > π/2 makes β < 0: where the paper's arctan(α/β) would be half a turn off.
    q, psi, p, phi, symmetry = _problem(7, 6, yaw)
    fit = _fit(q, psi, p, phi, symmetry, w)
    assert fit.vehicle_in_worker.x_m == pytest.approx(3.0, abs=1e-9)
    assert fit.vehicle_in_worker.y_m == pytest.approx(-2.0, abs=1e-9)
    assert math.remainder(fit.vehicle_in_worker.yaw_rad - yaw, TWO_PI) == pytest.approx(
        0.0, abs=1e-12
    )
    assert fit.cost == pytest.approx(0.0, abs=1e-20)
    assert np.abs(fit.position_residuals_m).max() < 1e-9
    assert np.abs(fit.posture_residuals_rad).max() < 1e-9


@pytest.mark.parametrize(("kind", "turn"), [(PalletKind.JIS, 0.5), (PalletKind.EUR, 1.0)])
def test_a_posture_off_by_the_pallets_symmetry_gives_the_same_transform(
    kind: PalletKind, turn: float
) -> None:
    q, psi, p, phi, _ = _problem(3, 4, 0.4, 0.02, math.radians(1.0))
    symmetry = np.full(4, kind.symmetry_rad)
    phi = psi + 0.4 + np.random.default_rng(3).normal(0.0, 0.02, 4)
    before = _fit(q, psi, p, phi, symmetry, 1.31)
    turned = phi.copy()
    turned[1] += turn * math.pi  # +90° for a square pallet, +180° for a rectangle
    after = _fit(q, psi, p, turned, symmetry, 1.31)
    assert np.allclose(after.vehicle_in_worker, before.vehicle_in_worker, atol=1e-12)
    assert after.cost == pytest.approx(before.cost, rel=1e-9)


def test_a_posture_turned_by_less_than_the_symmetry_moves_the_transform() -> None:
    q, psi, p, _, _ = _problem(3, 4, 0.4)
    phi = psi + 0.4
    symmetry = np.full(4, PalletKind.EUR.symmetry_rad)
    turned = phi.copy()
    turned[1] += 0.5 * math.pi  # a rectangle turned a quarter is another posture
    before = _fit(q, psi, p, phi, symmetry, 1.31)
    after = _fit(q, psi, p, turned, symmetry, 1.31)
    assert abs(after.vehicle_in_worker.yaw_rad - before.vehicle_in_worker.yaw_rad) > 1e-3


def _grid_minimum(g: object, lo: float, hi: float, points: int = 200_001) -> float:
    """The least of ``g`` on a dense grid, refined in the neighbouring cells."""
    grid = np.linspace(lo, hi, points)
    values = g(grid)  # type: ignore[operator]
    k = int(np.argmin(values))
    step = grid[1] - grid[0]
    refined = minimize_scalar(
        g, bounds=(grid[k] - step, grid[k] + step), method="bounded", options={"xatol": 1e-13}
    )
    return float(min(refined.fun, values[k]))


@given(
    st.floats(0.1, 100.0),
    st.floats(-math.pi, math.pi),
    st.floats(0.001, 3.0),
    st.floats(-20.0, 20.0),
)
def test_the_angle_is_the_global_minimum(
    rho: float, gamma: float, w_over_rho: float, mean_d: float
) -> None:
    # w small next to ρ: f = ρ sin(θ + γ) + w (θ + d̄) has many roots over |θ + d̄| ≤ ρ/w.
    w = w_over_rho * rho

    def g(theta: np.ndarray) -> np.ndarray:
        result: np.ndarray = -rho * np.cos(theta + gamma) + 0.5 * w * (theta + mean_d) ** 2
        return result

    theta, _, _ = minimize_angle_rad(rho, gamma, w, mean_d)
    span = min(rho / w, 60.0)  # every root; past 60 rad the quadratic alone rules it out
    best = _grid_minimum(g, -mean_d - span, -mean_d + span)
    assert float(g(np.array(theta))) <= best + 1e-12 * rho


@given(st.integers(0, 2**32 - 1), st.integers(2, 8), st.floats(1e-4, 0.05))
def test_the_fit_is_the_global_minimum_of_e_over_theta(seed: int, n: int, w: float) -> None:
    q, psi, p, phi, symmetry = _problem(seed, n, 1.0, 0.5, 0.5)
    fit = _fit(q, psi, p, phi, symmetry, w)
    fit_theta = fit.vehicle_in_worker.yaw_rad  # wrapped; the residuals θ + d_i are not
    d = fit.posture_residuals_rad - fit_theta  # its representatives, for the wrapped θ

    def e(theta: np.ndarray) -> np.ndarray:
        theta = np.atleast_1d(theta)
        c, s = np.cos(theta)[:, None], np.sin(theta)[:, None]
        rq_x = c * q[:, 0] - s * q[:, 1]
        rq_y = s * q[:, 0] + c * q[:, 1]
        ex = rq_x - rq_x.mean(axis=1, keepdims=True) - (p[:, 0] - p[:, 0].mean())
        ey = rq_y - rq_y.mean(axis=1, keepdims=True) - (p[:, 1] - p[:, 1].mean())
        result: np.ndarray = 0.5 * (
            (ex**2 + ey**2).sum(axis=1) + w * ((theta[:, None] + d) ** 2).sum(axis=1)
        )
        return result if result.size > 1 else result[0]

    # Over θ wider than [-π, π) around the postures' angle: the global minimum is within π.
    best = _grid_minimum(e, -float(np.mean(d)) - 4.0, -float(np.mean(d)) + 4.0)
    found = float(e(np.array([fit_theta])))
    assert fit.cost == pytest.approx(found, rel=1e-9, abs=1e-12)
    assert fit.cost <= best + 1e-9 * max(1.0, best)


def test_small_w_with_many_roots_keeps_the_least_e() -> None:
    # ρ = 1, w = 0.01: f has roots every ~π over 100 rad; the least E is near −γ.
    theta, _, minima = minimize_angle_rad(1.0, 0.3, 0.01, 2.0)
    assert minima >= 1
    assert math.remainder(theta + 0.3, TWO_PI) == pytest.approx(0.0, abs=0.05)
    assert abs(theta + 0.3) < math.pi  # the copy of −γ nearest −d̄, not a far one


def test_with_w_zero_it_is_the_closed_form() -> None:
    assert minimize_angle_rad(2.0, 0.7, 0.0, 5.0)[0] == -0.7


finite = st.floats(-1e3, 1e3)
anything = st.one_of(finite, st.sampled_from([math.nan, math.inf, -math.inf, 0.0]))


@given(
    st.integers(0, 6),
    st.lists(anything, min_size=6 * 6, max_size=6 * 6),
    st.sampled_from([0.0, 1e-6, 1.31, -1.0, math.nan, math.inf]),
    st.booleans(),
    st.booleans(),
    st.integers(0, 3),
)
def test_any_input_gives_a_fit_or_a_refusal_never_an_exception(
    n: int, values: list[float], w: float, coincident: bool, wrong_shape: bool, min_pairs: int
) -> None:
    data = np.array(values).reshape(6, 6)
    q, p = data[:n, :2], data[:n, 2:4]
    if coincident:
        q = np.zeros((n, 2)) + data[0, 0]
    psi, phi = data[:n, 4], data[:n, 5]
    symmetry = np.full(n, math.pi)
    if wrong_shape:
        phi = data[: n + 1, 5]
    result = solve_transform(q, psi, p, phi, symmetry, w, min_pairs=min_pairs)
    assert isinstance(result, TransformFit | MergeRefusal)
    if isinstance(result, MergeRefusal):
        assert result.reason
    else:
        assert all(map(math.isfinite, result.vehicle_in_worker))
        assert np.isfinite(result.covariance).all() and math.isfinite(result.cost)


@pytest.mark.parametrize(
    ("args", "reason"),
    [
        ((np.zeros((1, 2)), [0.0], np.ones((1, 2)), [0.0], [math.pi], 1.0), "at least 2"),
        ((np.ones((3, 2)), [0.0] * 3, np.ones((3, 2)), [0.0] * 3, [math.pi] * 3, 0.0), "rotation"),
        (
            (np.ones((2, 2)), [0.0] * 2, np.ones((2, 2)), [math.nan] * 2, [math.pi] * 2, 1.0),
            "finite",
        ),
        ((np.ones((2, 2)), [0.0] * 3, np.ones((2, 2)), [0.0] * 2, [math.pi] * 2, 1.0), "shape"),
        ((np.ones((2, 2)), [0.0] * 2, np.ones((2, 2)), [0.0] * 2, [math.pi] * 2, -1.0), ">= 0"),
    ],
)
def test_refusals_say_why(args: tuple[object, ...], reason: str) -> None:
    result = solve_transform(*args)  # type: ignore[arg-type]
    assert isinstance(result, MergeRefusal)
    assert reason in result.reason


def test_one_pair_with_its_posture_when_explicitly_allowed() -> None:
    q, psi = np.array([[1.0, 2.0]]), np.array([0.3])
    p, phi = _rotate(q, 1.1) + np.array([3.0, -2.0]), psi + 1.1
    symmetry = np.array([math.pi / 2])
    assert isinstance(solve_transform(q, psi, p, phi, symmetry, 1.0), MergeRefusal)
    assert isinstance(solve_transform(q, psi, p, phi, symmetry, 0.0, min_pairs=1), MergeRefusal)
    fit = _fit(q, psi, p, phi, symmetry, 1.0, min_pairs=1)
    assert np.allclose(fit.vehicle_in_worker, (3.0, -2.0, 1.1), atol=1e-12)


def test_pallets_at_one_point_are_fitted_by_their_postures_when_w_is_positive() -> None:
    q = np.zeros((3, 2))
    p = np.full((3, 2), 4.0)
    fit = _fit(q, [0.1, 0.2, 0.3], p, [0.6, 0.7, 0.8], [TWO_PI] * 3, 1.0)
    assert np.allclose(fit.vehicle_in_worker, (4.0, 4.0, 0.5), atol=1e-12)


def test_the_covariance_is_the_first_order_propagation() -> None:
    """Against finite differences of the fit with respect to every input pose."""
    q, psi, p, phi, symmetry = _problem(11, 5, 0.8, 0.05, math.radians(2.0))
    rng = np.random.default_rng(11)
    covariances = []
    for _ in range(10):
        a = rng.normal(0.0, 0.03, (3, 3))
        covariances.append(a @ a.T + 1e-4 * np.eye(3))
    cov_v, cov_w = np.array(covariances[:5]), np.array(covariances[5:])
    w = 1.31
    fit = _fit(q, psi, p, phi, symmetry, w, vehicle_covariance=cov_v, worker_covariance=cov_w)
    base = np.array(fit.vehicle_in_worker)
    step = 1e-6
    expected = np.zeros((3, 3))
    for which, covariance in ((0, cov_v), (1, cov_w)):
        for i in range(5):
            jacobian = np.zeros((3, 3))
            for k in range(3):
                inputs = [q.copy(), psi.copy(), p.copy(), phi.copy()]
                xy, yaw = inputs[2 * which], inputs[2 * which + 1]
                if k < 2:
                    xy[i, k] += step
                else:
                    yaw[i] += step
                moved = _fit(*inputs, symmetry, w)
                jacobian[:, k] = (np.array(moved.vehicle_in_worker) - base) / step
            expected += jacobian @ covariance[i] @ jacobian.T
    assert np.allclose(fit.covariance, expected, rtol=1e-4, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(fit.covariance) > 0.0)


def test_the_inverse_and_its_covariance() -> None:
    q, psi, p, phi, symmetry = _problem(5, 5, -2.0, 0.02, 0.01)
    cov = np.array([np.diag([4e-4, 4e-4, 3e-4])] * 5)
    fit = _fit(q, psi, p, phi, symmetry, 1.31, vehicle_covariance=cov, worker_covariance=cov)
    inverse = fit.worker_in_vehicle
    x, y = _rotate(np.array([[inverse.x_m, inverse.y_m]]), fit.vehicle_in_worker.yaw_rad)[0]
    assert (x + fit.vehicle_in_worker.x_m, y + fit.vehicle_in_worker.y_m) == pytest.approx(
        (0.0, 0.0), abs=1e-12
    )

    def inverse_of(pose: np.ndarray) -> np.ndarray:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        return np.array([-(c * pose[0] + s * pose[1]), s * pose[0] - c * pose[1], -pose[2]])

    base = np.array(fit.vehicle_in_worker)
    jacobian = np.column_stack(
        [(inverse_of(base + 1e-7 * e) - inverse_of(base - 1e-7 * e)) / 2e-7 for e in np.eye(3)]
    )
    expected = jacobian @ fit.covariance @ jacobian.T
    assert np.allclose(fit.worker_in_vehicle_covariance(), expected, rtol=1e-6, atol=1e-15)


def test_iterations_are_reported() -> None:
    q, psi, p, phi, symmetry = _problem(1, 6, 0.3, 0.05, 0.05)
    fit = _fit(q, psi, p, phi, symmetry, 1.31)
    assert 1 <= fit.iterations <= 60
    assert fit.local_minima >= 1
