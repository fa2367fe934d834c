"""The extraction finds what it found before it was made fast: key numbers of fixed scans,
recorded with the straightforward implementation (commit 77e91df), compared to the
current one to floating-point noise.

The scans are cast here in closed form (the launcher's boards and cylinders, a wall, a
thin post and a wider one, a tree-like scatter) with seeded noise and a crude beam
footprint (a beam that only grazes an arc reports its edge, so arcs look wider), so that
they exercise the paths a simulated scan does (footprint trimming, the free-radius
check, split-and-merge with corners, occluded ends, each common rejection) without
depending on the simulator; a few arcs with outliers at their ends take the refit path.
The recording is ``recorded_features.json`` next to this file: segments and rejection
counts exactly, every other number to 1e-9 (m, rad) or, for σ and correlations, a
relative 1e-6. To re-record after an intended change of results, write `_key_numbers`
of each case and `_arc_numbers` of each arc into it, in its layout.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from appliance.perception.cylinders import CircleParams, fit_cylinder
from appliance.perception.features import DiscRoi, LineRoi, Roi, extract_features
from appliance.perception.points import scan_points
from appliance.perception.types import CircleFeature, FitRejection, ScanFeatures, ScannerModel
from drivers.geometry import Pose2D

from .scenes import (
    MOUNTS,
    SENSOR_ANGLES,
    FloatArray,
    circle_ranges,
    to_frame,
    vehicle_before_board,
    with_noise,
)

# The launcher frame: front board on x = 0, side boards swept 45° back from its ends,
# cylinders 0.5 m before the board, a wall behind, two posts and a shrub.
BOARDS = (
    (0.0, -1.5, 0.0, 1.5),
    (0.0, 1.5, 0.566, 2.066),
    (0.0, -1.5, 0.566, -2.066),
    (4.0, -9.0, 4.0, 9.0),
)
CYLINDERS = ((-0.5, 2.5, 0.15), (-0.5, -2.5, 0.15), (-6.0, -4.5, 0.10), (-9.0, 5.0, 0.25))
SHRUB = (-7.0, 6.5)
MAX_RANGE_M = 20.0


def _cast(vehicle: Pose2D, mount: Pose2D, rng: np.random.Generator) -> FloatArray:
    """Ranges (0 = no echo) of one scan of the scene, in the sensor's beam order."""
    sensor = vehicle.compose(mount)
    angles = SENSOR_ANGLES + sensor.yaw_rad
    ux, uy = np.cos(angles), np.sin(angles)
    ranges = np.full(angles.shape, np.inf)
    for x0, y0, x1, y1 in BOARDS:
        ex, ey = x1 - x0, y1 - y0
        ax, ay = x0 - sensor.x_m, y0 - sensor.y_m
        with np.errstate(divide="ignore", invalid="ignore"):
            denominator = ux * ey - uy * ex
            t = (ax * ey - ay * ex) / denominator
            s = (ax * uy - ay * ux) / denominator
        hit = (t > 0.0) & (s >= 0.0) & (s <= 1.0)
        ranges = np.where(hit & (t < ranges), t, ranges)
    shrub = rng.uniform(0.0, 0.8, (40, 2)) + SHRUB
    for x, y in shrub:
        dx, dy = x - sensor.x_m, y - sensor.y_m
        along = dx * ux + dy * uy
        hit = (along > 0.0) & (np.abs(dx * uy - dy * ux) < 0.01)
        ranges = np.where(hit & (along < ranges), along, ranges)
    for cx, cy, radius in CYLINDERS:
        dx, dy = cx - sensor.x_m, cy - sensor.y_m
        along = dx * ux + dy * uy
        miss = np.sqrt(np.maximum(dx * dx + dy * dy - along * along, 0.0))
        # A beam whose footprint (8 mm + 15 mrad) only grazes the arc reports its edge.
        footprint = 0.5 * (0.008 + 0.015 * along)
        inside = np.sqrt(np.maximum(radius * radius - miss * miss, 0.0))
        t = np.where(miss < radius, along - inside, along)
        hit = (along > 0.0) & (miss < radius + footprint)
        ranges = np.where(hit & (t < ranges), t, ranges)
    noisy = ranges + rng.normal(0.0, 0.012, ranges.shape)
    return np.where(np.isfinite(ranges) & (ranges < MAX_RANGE_M), noisy, 0.0)


def _rois(vehicle: Pose2D, error_m: tuple[float, float]) -> list[Roi]:
    """The localizer's regions (0.6 m discs, a 0.4 m capsule) around a pose that is
    ``error_m`` off in the launcher frame."""
    ex, ey = error_m
    rois: list[Roi] = [
        DiscRoi(*to_frame(vehicle, x + ex, y + ey), 0.6) for x, y, _ in CYLINDERS[:2]
    ]
    rois.append(LineRoi(*to_frame(vehicle, ex, ey - 1.5), *to_frame(vehicle, ex, ey + 1.5), 0.4))
    return rois


# name: (front end to board m, lateral m, yaw deg, scanner, seed, regions' error or None,
# range offset m)
CASES = {
    "far whole left": (10.0, 0.3, 2.0, "left", 1, None, 0.0),
    "far whole right": (10.0, 0.3, 2.0, "right", 2, None, 0.0),
    "far rois right": (10.0, -0.2, -1.0, "right", 3, (0.1, -0.1), 0.0),
    "mid whole left": (4.0, 0.0, 0.0, "left", 4, None, 0.02),
    "near whole left": (2.0, 0.2, -2.0, "left", 5, None, 0.0),
    "near rois left": (2.0, 0.2, -2.0, "left", 6, (0.0, 0.0), 0.0),
    "near rois right": (1.0, -0.1, 1.0, "right", 7, (0.05, 0.1), -0.01),
    "close whole right": (0.3, 0.0, 0.5, "right", 8, None, 0.0),
    "close rois left": (0.3, 0.05, -0.5, "left", 9, (0.0, 0.05), 0.0),
}


def _extract(case: str) -> ScanFeatures:
    distance_m, lateral_m, yaw_deg, scanner, seed, error_m, offset_m = CASES[case]
    vehicle = vehicle_before_board(distance_m, lateral_m, yaw_deg)
    mount = MOUNTS[scanner]
    ranges = _cast(vehicle, mount, np.random.default_rng(seed))
    rois = None if error_m is None else _rois(vehicle, error_m)
    return extract_features(ranges, SENSOR_ANGLES, mount, rois=rois, range_offset_m=offset_m)


def _key_numbers(features: ScanFeatures) -> tuple[object, ...]:
    """What a feature is, as plain numbers: segments, counts, then per line (first and
    last beam, points, occluded ends, r, α, the ends, rms, σ r, σ α, correlation) and
    per circle (first and last beam, points, cx, cy, rms, σ x, σ y, correlation)."""
    lines = tuple(
        (
            (line.first_index, line.last_index, line.n_points),
            (line.start_occluded, line.end_occluded),
            (line.r_m, line.alpha_rad, *line.start_xy_m, *line.end_xy_m, line.rms_m),
            _spread(line.covariance),
        )
        for line in features.lines
    )
    circles = tuple(_circle_numbers(circle) for circle in features.circles)
    return features.segments, dict(sorted(features.rejections.items())), lines, circles


def _circle_numbers(circle: CircleFeature) -> tuple[object, ...]:
    return (
        (circle.first_index, circle.last_index, circle.n_points),
        (circle.cx_m, circle.cy_m, circle.rms_m),
        _spread(circle.covariance),
    )


def _spread(covariance: FloatArray) -> tuple[float, float, float]:
    """σ of each coordinate and their correlation."""
    sx, sy = math.sqrt(covariance[0, 0]), math.sqrt(covariance[1, 1])
    return sx, sy, float(covariance[0, 1]) / (sx * sy)


def test_the_scenes_hold_what_the_comparison_needs() -> None:
    """Every path worth comparing is taken by some case (else the recording proves little)."""
    found = [_extract(case) for case in CASES]
    counts: dict[str, int] = {}
    for features in found:
        for key, n in features.rejections.items():
            counts[key] = counts.get(key, 0) + n
    for reason in ("too_wide", "too_narrow", "not_isolated"):
        assert counts.get(f"circle.{reason}", 0) > 0, reason
    for reason in ("too_short", "too_few_points"):
        assert counts.get(f"line.{reason}", 0) > 0, reason
    assert sum(len(f.circles) for f in found) >= 2 * len(CASES) - 4
    assert any(line.start_occluded or line.end_occluded for f in found for line in f.lines)


# A known-radius refit after dropping a mixed echo at an end is rare in whole scans:
# thin-ray arcs with outliers at their ends take that path. (distance, bearing deg,
# seed, outlier m at the first beam, at the last beam)
ARCS = {
    "first end": (3.0, 10.0, 11, 0.3, 0.0),
    "both ends": (4.0, -20.0, 12, 0.25, -0.1),
    "last end twice": (1.5, 40.0, 13, 0.0, 0.3),
}
THIN = ScannerModel(footprint_exit_m=0.0, footprint_divergence_rad=0.0)


def _arc_fit(case: str) -> CircleFeature | FitRejection:
    distance_m, bearing_deg, seed, first_m, last_m = ARCS[case]
    bearing = math.radians(bearing_deg)
    exact = circle_ranges(
        distance_m * math.cos(bearing), distance_m * math.sin(bearing), 0.15, SENSOR_ANGLES
    )
    ranges = with_noise(exact, np.random.default_rng(seed))
    hit = np.flatnonzero(exact > 0.0)
    ranges[hit[0]] += first_m
    ranges[hit[-1]] += last_m
    if last_m > 0.0:
        ranges[hit[-2]] += last_m
    points = scan_points(ranges, SENSOR_ANGLES)
    return fit_cylinder(points, (int(hit[0]), int(hit[-1]) + 1), CircleParams(), THIN)


def _arc_numbers(result: CircleFeature | FitRejection) -> object:
    return str(result.reason) if isinstance(result, FitRejection) else _circle_numbers(result)


@pytest.fixture(scope="module")
def recorded() -> dict[str, dict[str, object]]:
    text = Path(__file__).with_name("recorded_features.json").read_text(encoding="utf-8")
    loaded: dict[str, dict[str, object]] = json.loads(text)
    return loaded


def _assert_close(got: object, recorded: object, where: str) -> None:
    """Equal structure, integers and flags; positions, angles and rms to 1e-9 (m, rad);
    the last group of a feature (σ, σ, correlation) to a relative 1e-6."""
    assert isinstance(got, tuple | list) and isinstance(recorded, list), where
    assert len(got) == len(recorded), where
    for i, (feature, expected) in enumerate(zip(got, recorded, strict=True)):
        *exact, values, spread = feature
        *exact_expected, values_expected, spread_expected = expected
        assert [list(group) for group in exact] == exact_expected, f"{where}[{i}]"
        assert values == pytest.approx(values_expected, rel=0.0, abs=1e-9), f"{where}[{i}]"
        assert spread == pytest.approx(spread_expected, rel=1e-6, abs=0.0), f"{where}[{i}]"


@pytest.mark.parametrize("case", CASES)
def test_the_features_are_the_recorded_ones(
    case: str, recorded: dict[str, dict[str, object]]
) -> None:
    segments, rejections, lines, circles = _key_numbers(_extract(case))
    expected = recorded["features"][case]
    assert isinstance(expected, dict)
    assert [list(s) for s in segments] == expected["segments"]
    assert rejections == expected["rejections"]
    _assert_close(lines, expected["lines"], "lines")
    _assert_close(circles, expected["circles"], "circles")


@pytest.mark.parametrize("case", ARCS)
def test_the_refitted_arcs_are_the_recorded_ones(
    case: str, recorded: dict[str, dict[str, object]]
) -> None:
    got, expected = _arc_numbers(_arc_fit(case)), recorded["arcs"][case]
    if isinstance(expected, str):
        assert got == expected
    else:
        _assert_close([got], [expected], case)
