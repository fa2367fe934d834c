"""Circle fits against independent solvers, their covariance against Monte Carlo, and
any cluster of points against them."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.linalg
import scipy.optimize
from hypothesis import given
from hypothesis import strategies as st

from appliance.perception.circle_search import normal_variance
from appliance.perception.circles import (
    CircleFit,
    fit_circle_free,
    fit_circle_known_radius,
    free_radius_mismatch,
    taubin_circle,
)
from appliance.perception.points import scan_points
from appliance.perception.types import FitRejection, ScannerModel

from .scenes import SENSOR_ANGLES, circle_ranges, with_noise

SCANNER = ScannerModel()


def _arc(seed: int, radius: float = 0.15, span_deg: float = 140.0, n: int = 12) -> np.ndarray:
    """Points on the near side of a circle 5 m out, with noise."""
    rng = np.random.default_rng(seed)
    centre = np.array([5.0, rng.uniform(-1.0, 1.0)])
    phi = math.pi + np.radians(np.linspace(-span_deg / 2, span_deg / 2, n))
    xy = centre + radius * np.column_stack([np.cos(phi), np.sin(phi)])
    return xy + rng.normal(0.0, 0.01 * radius, xy.shape)


def _taubin_generalised_eigen(xy: np.ndarray) -> tuple[float, float, float]:
    """Taubin's fit as he wrote it: M a = η N a on the 4x4 moments of (z, x, y, 1),
    the smallest non-negative finite η (data moved to their centroid for conditioning:
    the fit does not depend on where the origin is)."""
    shift = xy.mean(axis=0)
    x, y = (xy - shift).T
    z = x * x + y * y
    design = np.column_stack([z, x, y, np.ones_like(x)])
    moments = design.T @ design / len(x)
    mx, my, mz = x.mean(), y.mean(), z.mean()
    constraint = np.array(
        [[4 * mz, 2 * mx, 2 * my, 0], [2 * mx, 1, 0, 0], [2 * my, 0, 1, 0], [0, 0, 0, 0]]
    )
    values, vectors = scipy.linalg.eig(moments, constraint)
    values = np.real(values)
    finite = np.flatnonzero(np.isfinite(values) & (values > -1e-12))
    a, b, c, d = np.real(vectors[:, finite[np.argmin(values[finite])]])
    cx, cy = -b / (2 * a), -c / (2 * a)
    return cx + shift[0], cy + shift[1], math.sqrt(b * b + c * c - 4 * a * d) / (2 * abs(a))


@pytest.mark.parametrize("seed", range(10))
def test_taubin_matches_the_generalised_eigenproblem(seed: int) -> None:
    xy = _arc(seed, span_deg=60.0 + 20.0 * seed)
    got = taubin_circle(xy)
    assert isinstance(got, tuple)
    np.testing.assert_allclose(got, _taubin_generalised_eigen(xy), rtol=0, atol=1e-9)


def _least_squares(xy: np.ndarray, x0: np.ndarray, radius: float | None) -> np.ndarray:
    def residuals(x: np.ndarray) -> np.ndarray:
        r = x[2] if radius is None else radius
        return np.hypot(xy[:, 0] - x[0], xy[:, 1] - x[1]) - r

    tight = {"xtol": 1e-15, "ftol": 1e-15, "gtol": 1e-15}
    return scipy.optimize.least_squares(residuals, x0, method="lm", **tight).x


@pytest.mark.parametrize("seed", range(10))
def test_known_radius_fit_matches_scipy_least_squares(seed: int) -> None:
    xy = _arc(seed, span_deg=40.0 + 25.0 * seed, n=5 + seed)
    fit = fit_circle_known_radius(xy, 0.15, (0.0, 0.0), SCANNER)
    assert isinstance(fit, CircleFit)
    expected = _least_squares(xy, np.array([fit.cx_m + 0.01, fit.cy_m - 0.01]), 0.15)
    np.testing.assert_allclose([fit.cx_m, fit.cy_m], expected, rtol=0, atol=1e-9)
    assert fit.rms_m == pytest.approx(
        math.sqrt(np.mean((np.hypot(*(xy - expected).T) - 0.15) ** 2)), rel=1e-6
    )


@pytest.mark.parametrize("seed", range(10))
def test_free_fit_matches_scipy_least_squares(seed: int) -> None:
    xy = _arc(seed, radius=0.1 + 0.05 * seed, span_deg=90.0 + 20.0 * seed, n=8 + seed)
    fit = fit_circle_free(xy, (0.0, 0.0), SCANNER)
    assert isinstance(fit, CircleFit)
    start = np.array([fit.cx_m + 0.01, fit.cy_m, fit.radius_m * 1.05])
    expected = _least_squares(xy, start, None)
    np.testing.assert_allclose([fit.cx_m, fit.cy_m, fit.radius_m], expected, rtol=0, atol=1e-9)


def test_a_line_has_no_taubin_circle() -> None:
    xy = np.column_stack([np.linspace(0.0, 1.0, 10), np.full(10, 2.0)])
    result = taubin_circle(xy)
    assert isinstance(result, FitRejection) and result.reason == "collinear"
    assert isinstance(fit_circle_free(xy, (0.0, 0.0), SCANNER), FitRejection)


def _fits(distance_m: float, draws: int, free: bool) -> tuple[np.ndarray, np.ndarray]:
    """Centres (and radii) of ``draws`` noisy scans of a 0.15 m cylinder, and the
    covariance the fit predicts on the exact scan."""
    rng = np.random.default_rng(7)
    exact = circle_ranges(distance_m, 0.3, 0.15, SENSOR_ANGLES)
    hit = exact > 0.0

    def fit(ranges: np.ndarray) -> CircleFit:
        xy = scan_points(ranges[hit], SENSOR_ANGLES[hit]).xy_m
        result = (
            fit_circle_free(xy, (0.0, 0.0), SCANNER)
            if free
            else fit_circle_known_radius(xy, 0.15, (0.0, 0.0), SCANNER)
        )
        assert isinstance(result, CircleFit)
        return result

    predicted = fit(exact)
    estimates = []
    for _ in range(draws):
        f = fit(with_noise(exact, rng))
        estimates.append((f.cx_m, f.cy_m, f.radius_m))
    covariance = np.diag([*np.diag(predicted.covariance), predicted.radius_sigma_m**2])
    covariance[0, 1] = covariance[1, 0] = predicted.covariance[0, 1]
    return np.array(estimates), covariance


@pytest.mark.parametrize(
    ("distance_m", "free"), [(2.0, False), (5.0, False), (10.0, False), (5.0, True)]
)
def test_covariance_matches_monte_carlo(distance_m: float, free: bool) -> None:
    """2000 noisy scans (fixed seed): the centre's sample covariance is the predicted one
    to 10 % per variance (3 % is one σ of a sample variance of 2000) and 0.05 in
    correlation; for the free fit, the radius' variance too."""
    estimates, predicted = _fits(distance_m, 2000, free)
    sample = np.cov(estimates.T)
    assert np.diag(sample)[:2] == pytest.approx(np.diag(predicted)[:2], rel=0.10)
    rho = lambda c: c[0, 1] / math.sqrt(c[0, 0] * c[1, 1])  # noqa: E731
    assert rho(sample) == pytest.approx(rho(predicted), abs=0.05)
    if free:
        assert sample[2, 2] == pytest.approx(predicted[2, 2], rel=0.10)
        # The three-parameter fit on a noisy half circle is biased (a few mm towards the
        # scanner, with a smaller radius): why the landmark's centre is fitted with R known.
        assert estimates[:, :2].mean(axis=0) == pytest.approx([distance_m, 0.3], abs=0.005)
    else:
        assert estimates[:, :2].mean(axis=0) == pytest.approx([distance_m, 0.3], abs=0.001)


coordinate = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, 1e-300, 1e-9, 0.15, 5.0, 1e12, -1e15]),
)
cluster = st.lists(st.tuples(coordinate, coordinate), min_size=0, max_size=10)


@given(cluster, st.sampled_from([0.15, 1e-6, 3.0]), st.booleans())
def test_any_cluster_gives_a_circle_or_a_rejection(
    points: list[tuple[float, float]], radius: float, doubled: bool
) -> None:
    xy = np.array(points * (2 if doubled else 1), dtype=np.float64).reshape(-1, 2)
    for result in (
        fit_circle_known_radius(xy, radius, (0.0, 0.0), SCANNER),
        fit_circle_free(xy, (0.0, 0.0), SCANNER),
    ):
        if isinstance(result, CircleFit):
            values = [
                result.cx_m,
                result.cy_m,
                result.radius_m,
                result.rms_m,
                result.radius_sigma_m,
            ]
            assert all(math.isfinite(v) for v in values)
            assert np.isfinite(result.covariance).all()
        else:
            assert isinstance(result, FitRejection)
    algebraic = taubin_circle(xy)
    assert isinstance(algebraic, FitRejection) or all(math.isfinite(v) for v in algebraic)


@given(st.integers(1, 6), st.floats(-1e3, 1e3), st.floats(-1e3, 1e3))
def test_coincident_points_are_rejected_or_fitted_finitely(n: int, x: float, y: float) -> None:
    xy = np.tile([x, y], (n, 1))
    assert isinstance(taubin_circle(xy), FitRejection)
    result = fit_circle_known_radius(xy, 0.15, (0.0, 0.0), SCANNER)
    assert isinstance(result, FitRejection) or np.isfinite(result.covariance).all()


def _radius_mismatch_reference(
    xy: np.ndarray, known: CircleFit, tolerance_m: float, sigmas: float
) -> float | None:
    """The radius check as it was written first: the free fit to convergence, then the
    comparison with its σ."""
    free = fit_circle_free(xy, (0.0, 0.0), SCANNER, start=(known.cx_m, known.cy_m, 0.15))
    if isinstance(free, FitRejection):
        return None
    allowed = tolerance_m + sigmas * free.radius_sigma_m
    return free.radius_m if abs(free.radius_m - 0.15) > allowed else None


@pytest.mark.parametrize("seed", range(12))
def test_the_radius_check_decides_as_the_full_free_fit(seed: int) -> None:
    """`free_radius_mismatch` settles most arcs before the free fit converges; its answer
    is the full fit's on arcs of the landmark, of posts thinner and thicker, near and far,
    short and long, noisy, with an outlier."""
    rng = np.random.default_rng(100 + seed)
    outcomes = set()
    for _ in range(40):
        radius = float(rng.choice([0.15, 0.15, 0.1, 0.13, 0.17, 0.2, 0.3]))
        bearing, distance = rng.uniform(-2.0, 2.0), rng.uniform(0.7, 15.0)
        centre = distance * np.array([math.cos(bearing), math.sin(bearing)])
        half_span = rng.uniform(0.3, 1.4)
        phi = math.pi + bearing + np.linspace(-half_span, half_span, int(rng.integers(8, 70)))
        xy = centre + radius * np.column_stack([np.cos(phi), np.sin(phi)])
        xy += rng.normal(0.0, float(rng.choice([0.003, 0.012, 0.03])), xy.shape)
        if rng.random() < 0.2:
            xy[rng.integers(0, len(xy))] += rng.normal(0.0, 0.1, 2)
        known = fit_circle_known_radius(xy, 0.15, (0.0, 0.0), SCANNER)
        if isinstance(known, FitRejection):
            continue
        expected = _radius_mismatch_reference(xy, known, 0.02, 3.0)
        assert free_radius_mismatch(xy, known, (0.0, 0.0), SCANNER, 0.02, 3.0) == expected
        outcomes.add(expected is None)
    assert outcomes == {True, False}  # both answers were asked for


def _sandwich_reference(xy: np.ndarray, fit: CircleFit, free: bool) -> np.ndarray:
    """The covariance written out in numpy: J of the residuals at the solution, each
    residual's variance from its beam's incidence, (JᵀJ)⁻¹ JᵀWJ (JᵀJ)⁻¹."""
    offsets = xy - np.array([fit.cx_m, fit.cy_m])
    radial = offsets / np.linalg.norm(offsets, axis=1)[:, None]
    beams = xy / np.linalg.norm(xy, axis=1)[:, None]  # the scanner at the origin
    weights = SCANNER.normal_variance(np.sum(beams * radial, axis=1))
    jacobian = -np.column_stack([radial, np.ones(len(xy))]) if free else -radial
    inverse = np.linalg.inv(jacobian.T @ jacobian)
    full: np.ndarray = inverse @ (jacobian.T * weights) @ jacobian @ inverse
    return full


@pytest.mark.parametrize("seed", range(10))
def test_the_covariances_are_the_sandwich_written_out(seed: int) -> None:
    """The compiled covariance of both fits against the same algebra in numpy."""
    xy = _arc(seed, n=int(np.random.default_rng(seed).integers(8, 40)))
    free = fit_circle_free(xy, (0.0, 0.0), SCANNER)
    known = fit_circle_known_radius(xy, 0.15, (0.0, 0.0), SCANNER)
    assert isinstance(free, CircleFit) and isinstance(known, CircleFit)
    expected_free = _sandwich_reference(xy, free, free=True)
    assert free.covariance == pytest.approx(expected_free[:2, :2], rel=1e-9, abs=1e-18)
    assert free.radius_sigma_m**2 == pytest.approx(expected_free[2, 2], rel=1e-9)
    expected = _sandwich_reference(xy, known, free=False)
    assert known.covariance == pytest.approx(expected, rel=1e-9, abs=1e-18)


@given(
    st.floats(1e-4, 0.1),
    st.sampled_from([0.0, 1e-9, 1e-4, 1e-3]),
    st.floats(-1.0, 1.0),
)
def test_one_points_variance_is_the_scanner_models(
    sigma_m: float, floor_sigma_m: float, cos_incidence: float
) -> None:
    """The compiled per-point noise is `ScannerModel.normal_variance` of that point (to
    the last bits a square by multiplication and one by ``pow`` may round apart in)."""
    scanner = ScannerModel(sigma_m=sigma_m, floor_sigma_m=floor_sigma_m)
    expected = float(scanner.normal_variance(np.array([cos_incidence]))[0])
    got = normal_variance(sigma_m, floor_sigma_m, cos_incidence)
    assert got == pytest.approx(expected, rel=1e-15, abs=0.0)
