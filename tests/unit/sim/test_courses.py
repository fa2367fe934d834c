"""Courses for the tracking simulation: shapes checked with geometry written out here."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from appliance.sim.courses import (
    MILE_M,
    CourseError,
    arc_course,
    course_length_m,
    load_course_csv,
    off_road_course,
    save_course_csv,
    straight_course,
)


def three_point_curvature(points: np.ndarray, span: int) -> np.ndarray:
    """1 / circumradius of (p[i-span], p[i], p[i+span]), signed left-positive."""
    a, b, c = points[: -2 * span], points[span:-span], points[2 * span :]
    ab, bc, ca = b - a, c - b, a - c
    cross = ab[:, 0] * bc[:, 1] - ab[:, 1] * bc[:, 0]
    lengths = np.hypot(*ab.T) * np.hypot(*bc.T) * np.hypot(*ca.T)
    curvature: np.ndarray = 2.0 * cross / lengths
    return curvature


def test_an_arc_lies_on_its_circle_between_straight_leads() -> None:
    radius, lead = 20.0, 30.0
    points = arc_course(radius, lead_in_m=lead, arc_deg=90.0, lead_out_m=10.0, spacing_m=0.25)
    centre = np.array([lead, radius])  # starts at the origin heading east, turns left
    on_arc = (points[:, 0] > lead + 0.5) & (points[:, 1] < radius - 0.5)
    distances = np.hypot(*(points[on_arc] - centre).T)
    assert np.max(np.abs(distances - radius)) < 2e-3
    lead_in = points[points[:, 0] <= lead]
    assert np.max(np.abs(lead_in[:, 1])) < 1e-9
    # the lead-out heads north, at x = lead + radius
    end = points[-5:]
    assert np.allclose(end[:, 0], lead + radius, atol=5e-3)
    assert np.all(np.diff(end[:, 1]) > 0)


def test_a_right_arc_mirrors_a_left_one() -> None:
    left = arc_course(15.0, arc_deg=120.0)
    right = arc_course(15.0, arc_deg=120.0, left=False)
    assert np.allclose(left[:, 0], right[:, 0]) and np.allclose(left[:, 1], -right[:, 1])


def test_the_off_road_mile_keeps_its_radius_bounds_and_length() -> None:
    points = off_road_course(seed=1)
    assert course_length_m(points) == pytest.approx(MILE_M, abs=1.0)
    kappa = three_point_curvature(points, span=4)
    assert np.max(np.abs(kappa)) <= 1 / 15.0 * 1.01
    assert np.max(np.abs(kappa)) > 1 / 25.0  # it does have tight arcs
    assert np.mean(np.abs(kappa) < 1e-4) > 0.05  # and straights
    # curvature changes continuously: no step bigger than a clothoid's per 2 m
    # (a ramp from +1/15 to -1/15 over 12 m changes it by 2/15/24 per 0.5 m point)
    assert np.max(np.abs(np.diff(kappa))) < 2 * (1 / 15.0) / 24.0 * 1.1


def test_the_same_seed_gives_the_same_course_and_another_seed_another() -> None:
    assert np.array_equal(off_road_course(7), off_road_course(7))
    assert not np.array_equal(off_road_course(7)[:500], off_road_course(8)[:500])


def test_a_course_file_round_trips(tmp_path: Path) -> None:
    points = arc_course(30.0, arc_deg=45.0)
    path = tmp_path / "c.csv"
    save_course_csv(path, points)
    assert np.allclose(load_course_csv(path), points, atol=1e-4)


def test_comments_headers_and_repeats_are_accepted(tmp_path: Path) -> None:
    path = tmp_path / "c.csv"
    path.write_text("# a course\nx_m,y_m\n0,0\n0,0\n1.5, 2\n\n3,4 # end\n")
    assert load_course_csv(path).tolist() == [[0.0, 0.0], [1.5, 2.0], [3.0, 4.0]]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("0,0\n1,2,3\n", ":2: expected 'x_m,y_m'"),
        ("0,0\nnorth,1\n", ":2: not two numbers"),
        ("0,0\n1,nan\n", ":2: not finite"),
        ("0,0\n0,0\n", "fewer than two distinct points"),
        ("", "no points"),
    ],
)
def test_a_bad_course_file_is_refused_naming_the_line(
    tmp_path: Path, text: str, expected: str
) -> None:
    path = tmp_path / "c.csv"
    path.write_text(text)
    with pytest.raises(CourseError, match=expected.replace("(", r"\(")):
        load_course_csv(path)


def test_a_missing_file_is_a_course_error(tmp_path: Path) -> None:
    with pytest.raises(CourseError, match="cannot read"):
        load_course_csv(tmp_path / "none.csv")


def test_a_straight_course_is_straight() -> None:
    points = straight_course(100.0)
    assert course_length_m(points) == pytest.approx(100.0)
    assert math.isclose(float(np.max(np.abs(points[:, 1]))), 0.0)
