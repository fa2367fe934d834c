"""When a cluster is the cylinder landmark: each acceptance check with a scene that
should trip it, and scenes that must not pull the centre off (realistic scans from the
simulator: noise, beam footprint, remission limit)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.perception.cylinders import CircleParams, fit_cylinder
from appliance.perception.features import extract_features
from appliance.perception.gates import chi_square_quantile
from appliance.perception.points import scan_points
from appliance.perception.types import CircleFeature, FitRejection, ScannerModel
from appliance.sim import Circle, Pose2D, Segment, Site, render_scan

from .scenes import SENSOR_ANGLES, circle_ranges, render, with_noise

ORIGIN = Pose2D(0.0, 0.0, 0.0)
SCANNER = ScannerModel()
# The closed-form arcs below are thin-ray scans: no footprint to widen them.
THIN = ScannerModel(footprint_exit_m=0.0, footprint_divergence_rad=0.0)
PARAMS = CircleParams()


def _circles(site: Site, seed: int) -> tuple[list[CircleFeature], dict[str, int]]:
    features = extract_features(render(site, ORIGIN, ORIGIN, seed), SENSOR_ANGLES, ORIGIN)
    return list(features.circles), dict(features.rejections)


def _within(circle: CircleFeature, x_m: float, y_m: float, sigmas: float = 4.0) -> bool:
    """The centre within ``sigmas`` of its own covariance from the truth."""
    error = np.array([circle.cx_m - x_m, circle.cy_m - y_m])
    return float(error @ np.linalg.solve(circle.covariance, error)) <= sigmas**2


@pytest.mark.parametrize("distance_m", [2.0, 5.0, 10.0, 15.0])
def test_a_lone_cylinder_is_found_where_it_is(distance_m: float) -> None:
    site = Site((), (Circle(distance_m, 0.3, 0.15, 0.9, "cylinder"),))
    for seed in range(5):
        circles, _ = _circles(site, seed)
        assert len(circles) == 1
        assert _within(circles[0], distance_m, 0.3)
        if distance_m <= 2.0:
            assert math.hypot(circles[0].cx_m - distance_m, circles[0].cy_m - 0.3) < 0.01


@pytest.mark.parametrize("distance_m", [3.0, 8.0, 15.0])
def test_a_thinner_post_is_not_the_landmark(distance_m: float) -> None:
    site = Site((), (Circle(distance_m, 0.3, 0.10, 0.3, "post"),))
    for seed in range(5):
        circles, rejections = _circles(site, seed)
        assert circles == []
        assert (
            rejections.get("circle.too_narrow", 0) + rejections.get("circle.radius_mismatch", 0)
            == 1
        )


def test_a_post_of_the_landmarks_size_is_one() -> None:
    """Nothing in a scan tells a 0.3 m pipe from another: the estimator must gate."""
    circles, _ = _circles(Site((), (Circle(5.0, -1.0, 0.15, 0.3, "post"),)), 0)
    assert len(circles) == 1 and _within(circles[0], 5.0, -1.0)


@pytest.mark.parametrize("distance_m", [3.0, 8.0])
def test_a_person_is_not_a_cylinder(distance_m: float) -> None:
    circles, rejections = _circles(Site((), (Circle(distance_m, 0.3, 0.25, 0.3, "person"),)), 1)
    assert circles == [] and rejections.get("circle.too_wide") == 1


@pytest.mark.parametrize("distance_m", [3.0, 8.0])
@pytest.mark.parametrize("gap_m", [0.0, 0.03, 0.1, 0.3])
def test_a_person_beside_the_cylinder_never_pulls_it_off(distance_m: float, gap_m: float) -> None:
    """Touching, the two are one cluster too wide for a cylinder; a little apart, the
    cylinder is fitted on its own points; never a centre between the two."""
    person_y = 0.3 + 0.15 + 0.25 + gap_m
    site = Site(
        (),
        (
            Circle(distance_m, 0.3, 0.15, 0.9, "cylinder"),
            Circle(distance_m, person_y, 0.25, 0.3, "person"),
        ),
    )
    for seed in range(5):
        circles, _ = _circles(site, seed)
        for circle in circles:
            assert _within(circle, distance_m, 0.3)
        if gap_m == 0.0:
            assert circles == []


def test_an_arc_cut_short_by_something_in_front_is_not_isolated() -> None:
    site = Site((), (Circle(8.0, 0.3, 0.15, 0.9, "cylinder"), Circle(7.0, 0.45, 0.1, 0.3, "post")))
    for seed in range(5):
        circles, rejections = _circles(site, seed)
        assert all(abs(c.cy_m - 0.3) > 0.1 for c in circles)  # only ever the post, elsewhere
        assert (
            rejections.get("circle.not_isolated", 0) + rejections.get("circle.too_narrow", 0) >= 1
        )


def test_a_wall_close_behind_joins_the_cylinder_a_wall_farther_does_not() -> None:
    """The device merges echoes less than a pulse length apart: a wall 0.3 m behind is
    one cluster with the cylinder (no landmark, but no wrong one); 1 m behind is clear."""
    for behind_m, found in ((0.3, False), (1.0, True)):
        wall = Segment(5.0 + behind_m, -3.0, 5.0 + behind_m, 3.0, 0.5, "wall")
        circles, _ = _circles(Site((wall,), (Circle(5.0, 0.3, 0.15, 0.9, "cylinder"),)), 2)
        assert [(_within(c, 5.0, 0.3)) for c in circles] == ([True] if found else [])


def _exact_arc(distance_m: float = 5.0, seed: int = 0) -> tuple[np.ndarray, tuple[int, int]]:
    """A noisy cylinder without the footprint, and its beams [start, stop)."""
    exact = circle_ranges(distance_m, 0.3, 0.15, SENSOR_ANGLES)
    hit = np.flatnonzero(exact)
    return with_noise(exact, np.random.default_rng(seed)), (int(hit[0]), int(hit[-1]) + 1)


def test_a_neighbour_as_near_as_the_arc_means_not_isolated() -> None:
    """A wall's corner, or a person's shoulder, right beside the arc."""
    ranges, (start, stop) = _exact_arc()
    assert isinstance(
        fit_cylinder(scan_points(ranges, SENSOR_ANGLES), (start, stop), PARAMS, THIN),
        CircleFeature,
    )
    for neighbour in (start - 1, stop):
        beside = ranges.copy()
        beside[neighbour] = ranges[start] + 0.05
        result = fit_cylinder(scan_points(beside, SENSOR_ANGLES), (start, stop), PARAMS, THIN)
        assert isinstance(result, FitRejection) and result.reason == "not_isolated"


def test_the_scan_edge_means_not_isolated() -> None:
    ranges, (start, stop) = _exact_arc()
    count = stop - start
    edge = np.zeros_like(ranges)
    edge[:count] = ranges[start:stop]
    result = fit_cylinder(scan_points(edge, SENSOR_ANGLES), (0, count), PARAMS, THIN)
    assert isinstance(result, FitRejection) and result.reason == "not_isolated"


def test_an_arc_bulging_away_does_not_face_the_scanner() -> None:
    """The far side of a circle: concave towards the scanner (a pipe's inside, a corner)."""
    along = 5.0 * np.cos(SENSOR_ANGLES) + 0.3 * np.sin(SENSOR_ANGLES)
    inside = 0.15**2 - (5.0**2 + 0.3**2 - along**2)
    ranges = np.where(inside > 0.0, along + np.sqrt(np.maximum(inside, 0.0)), 0.0)
    hit = np.flatnonzero(ranges)
    result = fit_cylinder(
        scan_points(ranges, SENSOR_ANGLES), (int(hit[0]), int(hit[-1]) + 1), PARAMS, THIN
    )
    assert isinstance(result, FitRejection) and result.reason in ("not_facing", "rms_too_large")


def test_a_mixed_echo_at_an_end_is_dropped() -> None:
    """A beam half on the cylinder and half on something behind reports a range between;
    the end point is trimmed and the centre stays put."""
    for params in (PARAMS, CircleParams(trim_footprint_edges=False)):
        ranges, (start, stop) = _exact_arc(seed=3)
        clean = fit_cylinder(scan_points(ranges, SENSOR_ANGLES), (start, stop), params, THIN)
        ranges[stop - 1] += 0.2
        mixed = fit_cylinder(scan_points(ranges, SENSOR_ANGLES), (start, stop), params, THIN)
        assert isinstance(clean, CircleFeature) and isinstance(mixed, CircleFeature)
        assert math.hypot(mixed.cx_m - clean.cx_m, mixed.cy_m - clean.cy_m) < 0.005
        assert mixed.last_index < stop - 1


def test_residuals_above_the_noise_are_rejected() -> None:
    ranges, (start, stop) = _exact_arc(seed=4)
    noisy = ranges + np.where(
        ranges > 0.0, np.random.default_rng(5).normal(0.0, 0.05, ranges.shape), 0.0
    )
    result = fit_cylinder(
        scan_points(noisy, SENSOR_ANGLES),
        (start, stop),
        CircleParams(trim_footprint_edges=False),
        THIN,
    )
    assert isinstance(result, FitRejection) and result.reason in (
        "rms_too_large",
        "radius_mismatch",
    )


def test_too_few_points() -> None:
    ranges, (start, _) = _exact_arc()
    result = fit_cylinder(scan_points(ranges, SENSOR_ANGLES), (start, start + 3), PARAMS, THIN)
    assert isinstance(result, FitRejection) and result.reason == "too_few_points"


@pytest.mark.parametrize(
    ("dof", "expected"), [(2, 13.816), (5, 20.515), (30, 59.703), (200, 267.54)]
)
def test_chi_square_quantile_is_close_enough(dof: int, expected: float) -> None:
    """Wilson–Hilferty against the tabulated 99.9 % quantiles: within 3 % (2.3 % at 2)."""
    assert chi_square_quantile(dof, 3.09) == pytest.approx(expected, rel=0.03)


def test_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="radius_m"):
        CircleParams(radius_m=0.0)
    with pytest.raises(ValueError, match="min_points"):
        CircleParams(min_points=2)


@pytest.mark.parametrize("distance_m", [0.8, 1.2, 2.0])
@pytest.mark.parametrize("ideal", [False, True])
def test_a_near_cylinder_is_found_from_its_tangents(distance_m: float, ideal: bool) -> None:
    """Near the launcher (docking) the arc spans 2 asin(R/d) between its tangents, and its
    chord at the mean range is short of the diameter by up to a third; the width check
    must still take it, with and without the beam footprint."""
    from appliance.perception.features import FeatureParams
    from appliance.sim.scanner_errors import ideal_scanner

    site = Site((), (Circle(distance_m, 0.1, 0.15, 0.9, "cylinder"),))
    params = FeatureParams(scanner=THIN) if ideal else FeatureParams()
    for seed in range(3):
        rng = np.random.default_rng(seed)
        errors = {"errors": ideal_scanner()} if ideal else {}
        ranges, _ = render_scan(site, 0.0, ORIGIN, ORIGIN, rng=rng, **errors)
        circles = extract_features(ranges, SENSOR_ANGLES, ORIGIN, params).circles
        assert len(circles) == 1
        assert math.hypot(circles[0].cx_m - distance_m, circles[0].cy_m - 0.1) < 0.01


def test_thin_rays_find_the_landmark_far_out_wherever_the_beams_fall() -> None:
    """With no footprint, each end of the arc can lose up to a beam step to the space
    between two beams: at 16 m the 0.3 m landmark spans about four 0.25° beams and may
    look two steps narrower than its tangents. It is still the landmark, for every
    placement of the beams across one step (found: `dbw sim dock --ideal-scanner` lost
    the far cylinder from the centred start)."""
    step = float(SENSOR_ANGLES[1] - SENSOR_ANGLES[0])
    distance_m = 16.0
    for k in range(24):
        bearing = 0.2 + step * k / 24
        exact = circle_ranges(
            distance_m * math.cos(bearing), distance_m * math.sin(bearing), 0.15, SENSOR_ANGLES
        )
        ranges = exact.copy()  # no noise: only where the beams fall is varied
        hit = np.flatnonzero(exact > 0.0)
        points = scan_points(ranges, SENSOR_ANGLES)
        found = fit_cylinder(points, (int(hit[0]), int(hit[-1]) + 1), PARAMS, THIN)
        assert isinstance(found, CircleFeature), (k, found)
