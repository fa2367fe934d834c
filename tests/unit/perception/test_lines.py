"""Lines: the TLS fit against SVD, the covariance against propagation and Monte Carlo,
split-and-merge on corners and outliers, the Hessian form, and occluded ends."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.perception.line_fit import (
    LineFit,
    column_sums,
    fit_line,
    line_from_list,
    moment_columns,
    tls_line,
)
from appliance.perception.lines import LineParams, extract_lines, split_and_merge
from appliance.perception.points import scan_points
from appliance.perception.types import FitRejection, LineFeature, ScannerModel
from drivers.geometry import Pose2D

from .scenes import SENSOR_ANGLES, angle_difference, line_ranges, with_noise

SCANNER = ScannerModel()
PARAMS = LineParams()


def _svd_line(xy: np.ndarray) -> tuple[float, float]:
    """The TLS line the textbook way: the normal is the least singular direction."""
    centroid = xy.mean(axis=0)
    _, _, vt = np.linalg.svd(xy - centroid)
    normal = vt[-1]
    r = float(normal @ centroid)
    if r < 0.0:
        r, normal = -r, -normal
    return r, math.atan2(normal[1], normal[0])


@pytest.mark.parametrize("seed", range(20))
def test_unweighted_tls_matches_svd(seed: int) -> None:
    rng = np.random.default_rng(seed)
    direction = rng.uniform(-math.pi, math.pi)
    along = rng.uniform(-3.0, 3.0, rng.integers(3, 200))
    offset = rng.uniform(0.5, 30.0)
    normal = np.array([math.cos(direction), math.sin(direction)])
    xy = np.outer(along, [-normal[1], normal[0]]) + offset * normal
    xy += rng.normal(0.0, rng.choice([1e-4, 0.012, 0.3]), xy.shape)
    expected_r, expected_alpha = _svd_line(xy)
    for got in (tls_line(xy), fit_line(xy, None, SCANNER)):
        assert got is not None and not isinstance(got, FitRejection)
        r, alpha = (got.r_m, got.alpha_rad) if isinstance(got, LineFit) else got
        assert r == pytest.approx(expected_r, abs=1e-9 * max(1.0, expected_r))
        assert abs(angle_difference(alpha, expected_alpha)) <= 1e-9


def test_weighted_fit_is_the_fixed_point_of_its_own_weights() -> None:
    """The IRLS result is the weighted TLS line for the weights it implies."""
    rng = np.random.default_rng(3)
    angles = SENSOR_ANGLES[200:500]
    points = scan_points(with_noise(line_ranges(4.0, math.radians(-30.0), angles), rng), angles)
    fit = fit_line(points.xy_m, points.directions, SCANNER)
    assert isinstance(fit, LineFit)
    normal = np.array([math.cos(fit.alpha_rad), math.sin(fit.alpha_rad)])
    weights = 1.0 / SCANNER.normal_variance(points.directions @ normal)
    again = tls_line(points.xy_m, weights)
    assert again is not None
    assert again[0] == pytest.approx(fit.r_m, abs=1e-9)
    assert abs(angle_difference(again[1], fit.alpha_rad)) <= 1e-9
    # and it is not the unweighted line: the weights matter at this incidence
    assert abs(angle_difference(tls_line(points.xy_m)[1], fit.alpha_rad)) > 1e-9


def _fit_from_ranges(
    ranges: np.ndarray, angles: np.ndarray, frame: Pose2D, scanner: ScannerModel
) -> LineFit:
    points = scan_points(ranges, angles, frame)
    fit = fit_line(points.xy_m, points.directions, scanner)
    assert isinstance(fit, LineFit)
    return fit


def test_covariance_is_the_first_order_propagation_of_the_range_noise() -> None:
    """Differentiate the whole estimator numerically with respect to each range and
    propagate σ_r along every beam; the closed form must agree. In a mount frame, so
    that r carries the angle's error through its lever arm."""
    scanner = ScannerModel(floor_sigma_m=0.0)
    frame = Pose2D(5.8, 1.5, math.radians(45.0))
    angles = SENSOR_ANGLES[300:420]
    ranges = line_ranges(6.0, math.radians(-50.0), angles)
    fit = _fit_from_ranges(ranges, angles, frame, scanner)
    jacobian = np.empty((2, ranges.size))
    h = 1e-6
    for i in range(ranges.size):
        up, down = ranges.copy(), ranges.copy()
        up[i] += h
        down[i] -= h
        a, b = (_fit_from_ranges(x, angles, frame, scanner) for x in (up, down))
        jacobian[:, i] = [
            (a.r_m - b.r_m) / (2 * h),
            angle_difference(a.alpha_rad, b.alpha_rad) / (2 * h),
        ]
    propagated = scanner.sigma_m**2 * jacobian @ jacobian.T
    np.testing.assert_allclose(fit.covariance, propagated, rtol=1e-4)
    assert abs(fit.covariance[0, 1]) / math.sqrt(fit.covariance[0, 0] * fit.covariance[1, 1]) > 0.5


def test_covariance_matches_monte_carlo() -> None:
    """2000 noisy scans of one wall (fixed seed): the spread of the estimates is the
    predicted covariance. Tolerance: 10 % on each σ² (the sample variance of 2000 draws
    has a relative σ of 3 %) and 0.05 on the correlation."""
    rng = np.random.default_rng(2024)
    frame = Pose2D(5.8, -1.5, math.radians(-45.0))
    angles = SENSOR_ANGLES[450:700]
    exact = line_ranges(7.0, math.radians(35.0), angles)
    predicted = _fit_from_ranges(exact, angles, frame, SCANNER).covariance
    estimates = np.array(
        [
            (fit.r_m, fit.alpha_rad)
            for fit in (
                _fit_from_ranges(with_noise(exact, rng), angles, frame, SCANNER)
                for _ in range(2000)
            )
        ]
    )
    sample = np.cov(estimates.T)
    assert np.diag(sample) == pytest.approx(np.diag(predicted), rel=0.10)
    correlation = lambda c: c[0, 1] / math.sqrt(c[0, 0] * c[1, 1])  # noqa: E731
    assert correlation(sample) == pytest.approx(correlation(predicted), abs=0.05)


@pytest.mark.parametrize("alpha_deg", [-179.0, -135.0, -90.0, -10.0, 0.0, 45.0, 90.0, 170.0, 180.0])
def test_hessian_normal_form(alpha_deg: float) -> None:
    """r >= 0, α in (−π, π], the normal pointing from the origin to the line."""
    alpha = math.radians(alpha_deg)
    normal = np.array([math.cos(alpha), math.sin(alpha)])
    xy = 3.0 * normal + np.outer(np.linspace(-1.0, 1.0, 11), [-normal[1], normal[0]])
    fit = fit_line(xy, None, SCANNER)
    assert isinstance(fit, LineFit)
    assert fit.r_m == pytest.approx(3.0) and fit.r_m >= 0.0
    assert -math.pi < fit.alpha_rad <= math.pi
    assert abs(angle_difference(fit.alpha_rad, alpha)) < 1e-12
    np.testing.assert_allclose(xy @ [math.cos(fit.alpha_rad), math.sin(fit.alpha_rad)], fit.r_m)


def test_split_and_merge_finds_a_corner() -> None:
    """A board and a side board swept back 45° at its end: two lines, both right."""
    angles = SENSOR_ANGLES[440:640]
    board = line_ranges(5.0, 0.0, angles)
    side_alpha = math.radians(-45.0)  # through (5, 1.5), running back at 45°
    side = line_ranges(5.0 * math.cos(side_alpha) + 1.5 * math.sin(side_alpha), side_alpha, angles)
    y = board * np.sin(angles)
    ranges = with_noise(np.where(y <= 1.5, board, side), np.random.default_rng(5))
    points = scan_points(ranges, angles)
    pieces, _ = split_and_merge(points.xy_m, PARAMS, SCANNER)
    assert len(pieces) == 2
    (_, first), (_, second) = pieces
    assert first.r_m == pytest.approx(5.0, abs=0.01) and abs(first.alpha_rad) < math.radians(0.5)
    assert abs(angle_difference(second.alpha_rad, side_alpha)) < math.radians(2.0)


def test_an_outlier_does_not_break_a_board() -> None:
    angles = SENSOR_ANGLES[480:600]
    ranges = with_noise(line_ranges(5.0, 0.0, angles), np.random.default_rng(6))
    ranges[60] -= 0.4  # one wild echo (a mixed pixel, a raindrop)
    points = scan_points(ranges, angles)
    lines = [
        x
        for x in extract_lines(points, (0, angles.size), PARAMS, SCANNER)
        if isinstance(x, LineFeature)
    ]
    assert len(lines) == 1
    assert lines[0].n_points < angles.size  # the outlier is not in it
    assert lines[0].r_m == pytest.approx(5.0, abs=0.005)


def _board_scan(
    extra: dict[int, float], first: int = 480, last: int = 600
) -> tuple[np.ndarray, LineFeature]:
    """A board at 5 m over beams [first, last), other beams as given, and its line."""
    ranges = np.zeros(SENSOR_ANGLES.size)
    ranges[first:last] = line_ranges(5.0, 0.0, SENSOR_ANGLES[first:last])
    for index, value in extra.items():
        ranges[index] = value
    points = scan_points(ranges, SENSOR_ANGLES)
    results = extract_lines(points, (first, last), PARAMS, SCANNER)
    lines = [x for x in results if isinstance(x, LineFeature)]
    assert len(lines) == 1
    return ranges, lines[0]


def test_ends_with_nothing_beyond_are_true_ends() -> None:
    _, line = _board_scan({})
    assert not line.start_occluded and not line.end_occluded
    assert (line.first_index, line.last_index) == (480, 599)
    # Clipped to the data: the end points are the first and last points, on the line.
    assert line.start_xy_m[0] == pytest.approx(5.0) and line.start_xy_m[1] < line.end_xy_m[1]
    assert line.length_m == pytest.approx(line.end_xy_m[1] - line.start_xy_m[1])
    assert line.direction == pytest.approx((0.0, 1.0))


def test_something_in_front_beyond_an_end_occludes_it() -> None:
    _, line = _board_scan({479: 3.0})  # a post in front of the board's continuation
    assert line.start_occluded and not line.end_occluded


def test_something_clearly_behind_an_end_does_not() -> None:
    _, line = _board_scan({479: 7.0, 600: 9.0})  # a wall 2 m behind
    assert not line.start_occluded and not line.end_occluded


def test_the_fields_of_views_edge_occludes() -> None:
    ranges = np.zeros(SENSOR_ANGLES.size)
    ranges[:40] = line_ranges(3.0, math.radians(-135.0), SENSOR_ANGLES[:40])
    points = scan_points(ranges, SENSOR_ANGLES)
    (line,) = [
        x for x in extract_lines(points, (0, 40), PARAMS, SCANNER) if isinstance(x, LineFeature)
    ]
    assert line.start_occluded and not line.end_occluded


def test_short_pieces_are_rejected_with_reasons() -> None:
    ranges = np.zeros(SENSOR_ANGLES.size)
    ranges[500:504] = 5.0
    points = scan_points(ranges, SENSOR_ANGLES)
    assert [x.reason for x in extract_lines(points, (500, 504), PARAMS, SCANNER)] == [
        "too_few_points"
    ]
    ranges[500:510] = line_ranges(5.0, 0.0, SENSOR_ANGLES[500:510])  # 0.2 m of board
    points = scan_points(ranges, SENSOR_ANGLES)
    assert [x.reason for x in extract_lines(points, (500, 510), PARAMS, SCANNER)] == ["too_short"]


coordinate = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False),
    st.sampled_from([0.0, 1e-300, -1e-300, 1e-9, 1e12, -1e15, 3.0]),
)
cluster = st.lists(st.tuples(coordinate, coordinate), min_size=0, max_size=12)


@given(cluster, st.booleans())
def test_any_cluster_gives_a_line_or_a_rejection(
    points: list[tuple[float, float]], beams: bool
) -> None:
    xy = np.array(points, dtype=np.float64).reshape(-1, 2)
    if beams and len(points) > 0:
        directions = np.column_stack(
            [np.cos(np.arange(len(points))), np.sin(np.arange(len(points)))]
        )
    else:
        directions = None
    result = fit_line(xy, directions, SCANNER)
    if isinstance(result, LineFit):
        assert math.isfinite(result.r_m) and result.r_m >= 0.0
        assert -math.pi < result.alpha_rad <= math.pi
        assert np.isfinite(result.covariance).all()
        assert math.isfinite(result.rms_m) and math.isfinite(result.max_residual_m)
    else:
        assert isinstance(result, FitRejection)


@given(cluster)
def test_any_cluster_repeated_gives_a_line_or_a_rejection(
    points: list[tuple[float, float]],
) -> None:
    """Duplicates: every point twice, and all points the same."""
    xy = np.array(points + points, dtype=np.float64).reshape(-1, 2)
    for data in (xy, np.repeat(xy[:1], 5, axis=0)):
        result = fit_line(data, None, SCANNER)
        assert isinstance(result, FitRejection) or np.isfinite(result.covariance).all()


def test_every_pieces_line_is_the_one_its_plain_sums_give() -> None:
    """Split-and-merge adds each piece's moment rows in order, as ``np.add.reduce``
    does: every rough line it returns, for a run of points or for the points a settled
    corner kept, is the one the plain sums of its points give, to the last bit."""
    rng = np.random.default_rng(8)
    checked = 0
    for _ in range(40):
        corners = rng.uniform(-3.0, 3.0, (int(rng.integers(2, 5)), 2)) + rng.uniform(-20, 20, 2)
        xy = np.concatenate(
            [np.linspace(a, b, int(rng.integers(8, 80))) for a, b in itertools.pairwise(corners)]
        )
        xy += rng.normal(0.0, float(rng.choice([0.002, 0.012, 0.03])), xy.shape)
        if rng.random() < 0.5:
            xy[rng.integers(0, len(xy))] += rng.normal(0.0, 0.3, 2)  # an outlier
        assert column_sums(xy).tobytes() == np.add.reduce(xy, axis=0).tobytes()
        shift = np.add.reduce(xy, axis=0) / len(xy)
        moments = moment_columns(xy - shift)
        weight = 1.0 / (SCANNER.sigma_m**2 + SCANNER.floor_sigma_m**2)
        pieces, _ = split_and_merge(xy, PARAMS, SCANNER)
        for indices, line in pieces:
            sums = np.add.reduce(moments[indices], axis=0).tolist()
            assert line == line_from_list([weight * v for v in sums], *shift.tolist())
            checked += 1
    assert checked > 60
