"""Segmentation: the adaptive breakpoint, holes, the scan's two ends, what is dropped."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.perception.points import scan_points
from appliance.perception.segments import (
    Segmentation,
    SegmentParams,
    breakpoint_distance_m,
    segment_scan,
)
from appliance.perception.types import ScannerModel

from .scenes import SENSOR_ANGLES, line_ranges

SCANNER = ScannerModel()
PARAMS = SegmentParams()
STEP = math.radians(0.25)


def _segment(ranges: np.ndarray, angles: np.ndarray = SENSOR_ANGLES) -> Segmentation:
    points = scan_points(ranges, angles)
    return segment_scan(points.xy_m, points.ranges_m, angles, points.valid, PARAMS, SCANNER)


def test_breakpoint_distance_is_borges_and_aldon() -> None:
    expected = 10.0 * math.sin(STEP) / math.sin(math.radians(10.0) - STEP) + 3 * 0.012
    got = breakpoint_distance_m(np.array([10.0]), np.array([STEP]), math.radians(10.0), 0.012)
    assert got[0] == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.293, abs=0.001)  # 0.29 m at 10 m with 0.25° beams


def test_a_board_is_one_segment_and_a_hole_breaks_it() -> None:
    ranges = line_ranges(5.0, 0.0, SENSOR_ANGLES)
    ranges[np.abs(SENSOR_ANGLES) > math.radians(20.0)] = 0.0
    whole = _segment(ranges).segments
    assert len(whole) == 1
    start, stop = whole[0]
    assert (ranges[start:stop] > 0.0).all() and stop - start == np.count_nonzero(ranges)
    ranges[540] = 0.0  # one beam without echo in the middle of the board
    assert _segment(ranges).segments == ((start, 540), (541, stop))


def test_a_jump_in_range_breaks_a_segment() -> None:
    ranges = line_ranges(5.0, 0.0, SENSOR_ANGLES)
    ranges[np.abs(SENSOR_ANGLES) > math.radians(20.0)] = 0.0
    ranges[541:] = np.where(ranges[541:] > 0.0, ranges[541:] + 0.5, 0.0)  # a step back
    segments = _segment(ranges).segments
    assert len(segments) == 2 and segments[0][1] == 541 == segments[1][0]


def test_isolated_and_dispersed_points_are_dropped_and_counted() -> None:
    ranges = np.zeros(SENSOR_ANGLES.size)
    ranges[100:102] = 5.0  # two points: isolated
    ranges[300] = 7.0  # one: isolated
    spread = SegmentParams(max_mean_spacing_m=0.01)  # everything counts as dispersed
    result = _segment(ranges)
    assert result.segments == ()
    assert result.rejections == {"segment.isolated": 2}
    ranges[500:520] = 5.0
    points = scan_points(ranges, SENSOR_ANGLES)
    thin = segment_scan(points.xy_m, points.ranges_m, SENSOR_ANGLES, points.valid, spread, SCANNER)
    assert thin.segments == ()
    assert thin.rejections == {"segment.isolated": 2, "segment.dispersed": 1}


def test_the_scans_two_ends_are_never_joined() -> None:
    """A full turn puts the last beam 0.25° from the first, at the same range: a
    wrap-around join would make one segment of them; there must be two."""
    angles = -math.pi + STEP * np.arange(1440)
    ranges = np.full(angles.size, 3.0)
    assert _segment(ranges, angles).segments == ((0, 1440),)
    ranges[700] = 0.0
    assert _segment(ranges, angles).segments == ((0, 700), (701, 1440))


def test_regions_outside_the_mask_count_as_no_echo() -> None:
    ranges = line_ranges(5.0, 0.0, SENSOR_ANGLES)
    ranges[np.abs(SENSOR_ANGLES) > math.radians(20.0)] = 0.0
    points = scan_points(ranges, SENSOR_ANGLES)
    mask = points.valid.copy()
    mask[530:550] = False
    segments = segment_scan(points.xy_m, points.ranges_m, SENSOR_ANGLES, mask, PARAMS, SCANNER)
    assert all(stop <= 530 or start >= 550 for start, stop in segments.segments)


def test_parameters_are_checked() -> None:
    with pytest.raises(ValueError, match="lambda_rad"):
        SegmentParams(lambda_rad=0.0)
    with pytest.raises(ValueError, match="min_points"):
        SegmentParams(min_points=0)


# Ranges from a small alphabet so that neighbours are often equal, sometimes 0, sometimes
# far apart: every kind of boundary shows up in a few dozen beams.
beam_range = st.sampled_from([0.0, 0.0, 1.0, 1.01, 1.02, 1.5, 3.0, 3.02, 19.9])


@given(st.lists(beam_range, min_size=0, max_size=60), st.booleans())
def test_segments_hold_only_echoes_and_respect_the_breakpoints(
    ranges_list: list[float], coarse: bool
) -> None:
    step = math.radians(0.5 if coarse else 0.25)
    angles = -math.radians(135.0) + step * np.arange(len(ranges_list))
    ranges = np.array(ranges_list, dtype=np.float64)
    points = scan_points(ranges, angles)
    result = segment_scan(points.xy_m, points.ranges_m, angles, points.valid, PARAMS, SCANNER)
    previous_stop = 0
    for start, stop in result.segments:
        assert previous_stop <= start < stop <= len(ranges_list)  # sorted, disjoint, no wrap
        assert stop - start >= PARAMS.min_points
        assert (ranges[start:stop] > 0.0).all()  # never across a beam without echo
        gaps = np.hypot(*np.diff(points.xy_m[start:stop], axis=0).T)
        limits = breakpoint_distance_m(
            ranges[start : stop - 1], np.full(stop - start - 1, step), PARAMS.lambda_rad, 0.012
        )
        assert (gaps <= limits).all()
        previous_stop = stop
    kept = sum(stop - start for start, stop in result.segments)
    assert kept <= np.count_nonzero(ranges)
