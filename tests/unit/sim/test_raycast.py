"""Ray casting against geometry small enough to check by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.sim import load_site
from appliance.sim.raycast import (
    NO_HIT,
    beam_directions,
    cast_rays,
    nearer_of,
    nearest_hits,
    nearest_hits_along,
)


def _segments(*rows: tuple[float, float, float, float]) -> np.ndarray:
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


def _circles(*rows: tuple[float, float, float]) -> np.ndarray:
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


WALL_AT_5 = _segments((5.0, -1.0, 5.0, 1.0))
STRAIGHT = np.array([0.0])


def test_beam_straight_at_a_segment() -> None:
    ranges, remission = cast_rays(0.0, 0.0, STRAIGHT, WALL_AT_5, None, 20.0, np.array([0.7]))
    assert ranges[0] == pytest.approx(5.0, abs=1e-12)
    assert remission[0] == pytest.approx(0.7)


def test_oblique_beam_and_offset_origin() -> None:
    angle = math.atan2(0.5, 4.0)  # from (1, 0) to (5, 0.5)
    hits = nearest_hits(1.0, 0.0, np.array([angle]), WALL_AT_5, None, 20.0)
    assert hits.ranges_m[0] == pytest.approx(math.hypot(4.0, 0.5), abs=1e-12)
    assert hits.hit_index[0] == 0


def test_beam_at_a_circle_gives_distance_minus_radius() -> None:
    ranges, _ = cast_rays(0.0, 0.0, STRAIGHT, None, _circles((5.0, 0.0, 0.5)), 20.0)
    assert ranges[0] == pytest.approx(4.5, abs=1e-12)


def test_nearest_of_several_hits_wins() -> None:
    segments = _segments((5.0, -1.0, 5.0, 1.0), (3.0, -1.0, 3.0, 1.0))
    circles = _circles((2.0, 0.0, 0.25), (8.0, 0.0, 1.0))
    hits = nearest_hits(0.0, 0.0, STRAIGHT, segments, circles, 20.0)
    assert hits.ranges_m[0] == pytest.approx(1.75)
    assert hits.hit_index[0] == 2  # circles are numbered after the segments
    hits = nearest_hits(0.0, 0.0, STRAIGHT, segments, circles[1:], 20.0)
    assert hits.ranges_m[0] == pytest.approx(3.0)
    assert hits.hit_index[0] == 1


def test_one_call_casts_every_beam() -> None:
    angles = np.array([0.0, math.pi / 2, math.pi, -math.pi / 2])
    segments = _segments((5.0, -1.0, 5.0, 1.0), (-1.0, 2.0, 1.0, 2.0))
    circles = _circles((-3.0, 0.0, 1.0))
    ranges, remission = cast_rays(
        0.0, 0.0, angles, segments, circles, 20.0, np.array([0.9, 0.5]), np.array([0.3])
    )
    np.testing.assert_allclose(ranges, [5.0, 2.0, 2.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(remission, [0.9, 0.5, 0.3, 0.0])


def test_misses_and_shapes_behind_give_zero() -> None:
    ranges, remission = cast_rays(0.0, 0.0, np.array([math.pi, math.pi / 2]), WALL_AT_5, None, 20.0)
    assert ranges.tolist() == [0.0, 0.0]
    assert remission.tolist() == [0.0, 0.0]


def test_beyond_max_range_is_no_echo_and_at_max_range_is_a_hit() -> None:
    far = _segments((25.0, -1.0, 25.0, 1.0))
    assert cast_rays(0.0, 0.0, STRAIGHT, far, None, 20.0)[0][0] == 0.0
    at_max = _segments((20.0, -1.0, 20.0, 1.0))
    assert cast_rays(0.0, 0.0, STRAIGHT, at_max, None, 20.0)[0][0] == pytest.approx(20.0)
    circle = _circles((21.0, 0.0, 0.5))  # surface at 20.5 m: out of range
    assert cast_rays(0.0, 0.0, STRAIGHT, None, circle, 20.0)[0][0] == 0.0


def test_far_shapes_do_not_hide_near_ones_after_culling() -> None:
    segments = _segments((100.0, -50.0, 100.0, 50.0), (4.0, -1.0, 4.0, 1.0))
    hits = nearest_hits(0.0, 0.0, STRAIGHT, segments, None, 20.0)
    assert hits.ranges_m[0] == pytest.approx(4.0)
    assert hits.hit_index[0] == 1  # the index survives the culling of segment 0


def test_a_site_of_many_shapes_is_culled_and_casts_the_same() -> None:
    """Above a handful of shapes the far ones are dropped first: same hits, same indices."""
    rng = np.random.default_rng(7)
    segments = rng.uniform(-40.0, 40.0, size=(30, 4))
    centres = rng.uniform(-40.0, 40.0, size=(24, 2))
    circles = np.column_stack([centres, rng.uniform(0.1, 1.0, size=24)])
    circles = circles[np.hypot(circles[:, 0], circles[:, 1]) > circles[:, 2] + 0.1]
    angles = np.linspace(-math.pi, math.pi, 721)
    culled = nearest_hits(0.0, 0.0, angles, segments, circles, 20.0)
    one_by_one = nearest_hits(0.0, 0.0, angles, segments[:1], None, 20.0)
    shapes = [(segments[i : i + 1], None, i) for i in range(1, len(segments))]
    shapes += [(None, circles[i : i + 1], len(segments) + i) for i in range(len(circles))]
    for segment, circle, offset in shapes:
        one_by_one = nearer_of(
            one_by_one, nearest_hits(0.0, 0.0, angles, segment, circle, 20.0), offset
        )
    assert np.count_nonzero(culled.ranges_m) > 100
    np.testing.assert_allclose(culled.ranges_m, one_by_one.ranges_m, rtol=0.0, atol=1e-9)
    np.testing.assert_array_equal(culled.hit_index, one_by_one.hit_index)


def test_beam_parallel_to_a_segment_does_not_hit_it() -> None:
    along = _segments((1.0, 0.0, 5.0, 0.0))  # edge-on, on the beam's line
    beside = _segments((1.0, 1.0, 5.0, 1.0))  # parallel, offset
    for segments in (along, beside):
        hits = nearest_hits(0.0, 0.0, STRAIGHT, segments, None, 20.0)
        assert hits.ranges_m[0] == 0.0
        assert hits.hit_index[0] == NO_HIT


def test_segment_ends_are_part_of_the_segment() -> None:
    angles = np.array([math.atan2(1.0, 5.0), math.atan2(-1.0, 5.0)])
    ranges, _ = cast_rays(0.0, 0.0, angles, WALL_AT_5, None, 20.0)
    np.testing.assert_allclose(ranges, [math.hypot(5.0, 1.0)] * 2, rtol=1e-12)


def test_zero_length_segment_is_invisible() -> None:
    dot = _segments((5.0, 0.0, 5.0, 0.0))
    assert cast_rays(0.0, 0.0, STRAIGHT, dot, None, 20.0)[0][0] == 0.0


def test_origin_inside_a_circle_is_blind() -> None:
    angles = np.linspace(-math.pi, math.pi, 37)
    circles = _circles((0.2, 0.0, 1.0), (10.0, 0.0, 1.0))
    hits = nearest_hits(0.0, 0.0, angles, WALL_AT_5, circles, 20.0)
    assert not hits.ranges_m.any()
    assert (hits.hit_index == NO_HIT).all()


def test_origin_on_a_surface_is_no_echo() -> None:
    through_origin = _segments((0.0, -1.0, 0.0, 1.0))
    assert cast_rays(0.0, 0.0, STRAIGHT, through_origin, None, 20.0)[0][0] == 0.0


def test_beam_tangent_to_a_circle_touches_it() -> None:
    ranges, _ = cast_rays(0.0, 0.0, STRAIGHT, None, _circles((5.0, 1.0, 1.0)), 20.0)
    assert ranges[0] == pytest.approx(5.0, abs=1e-6)


@pytest.mark.parametrize(
    ("segments", "circles"),
    [
        (None, None),
        (np.empty((0, 4)), np.empty((0, 3))),
        (np.empty(0), np.empty(0)),
    ],
)
def test_empty_scene_returns_no_echo(
    segments: np.ndarray | None, circles: np.ndarray | None
) -> None:
    ranges, remission = cast_rays(0.0, 0.0, np.zeros(5), segments, circles, 20.0)
    assert ranges.shape == (5,)
    assert not ranges.any()
    assert not remission.any()


def test_no_beams() -> None:
    ranges, remission = cast_rays(0.0, 0.0, np.empty(0), WALL_AT_5, None, 20.0)
    assert ranges.shape == (0,)
    assert remission.shape == (0,)


def test_bad_shapes_are_rejected() -> None:
    with pytest.raises(ValueError, match="segments"):
        cast_rays(0.0, 0.0, STRAIGHT, np.zeros((2, 3)), None, 20.0)
    with pytest.raises(ValueError, match="circle_remission"):
        cast_rays(0.0, 0.0, STRAIGHT, None, _circles((5.0, 0.0, 1.0)), 20.0, None, np.ones(2))


def test_results_do_not_alias_the_scratch_buffers() -> None:
    first, _ = cast_rays(0.0, 0.0, STRAIGHT, WALL_AT_5, None, 20.0)
    cast_rays(0.0, 0.0, STRAIGHT, _segments((2.0, -1.0, 2.0, 1.0)), None, 20.0)
    assert first[0] == pytest.approx(5.0)


def test_casting_along_precomputed_directions_is_casting_the_angles() -> None:
    """The scanner model casts the static site and the walkers along one scan's
    directions: the same bits as casting each from the angles."""
    shapes = load_site("launcher").shapes_at(3.0)
    angles = np.linspace(-math.pi, math.pi, 1081)
    directions = beam_directions(angles)
    for segments, circles in (
        (shapes.segments, shapes.circles),
        (shapes.segments, None),
        (None, shapes.circles[-1:]),  # one shape: the walker alone
    ):
        expected = nearest_hits(-9.0, 0.5, angles, segments, circles, 20.0)
        found = nearest_hits_along(
            -9.0,
            0.5,
            directions,
            np.empty((0, 4)) if segments is None else segments,
            np.empty((0, 3)) if circles is None else circles,
            20.0,
        )
        assert found.ranges_m.tobytes() == expected.ranges_m.tobytes()
        assert found.hit_index.tobytes() == expected.hit_index.tobytes()
