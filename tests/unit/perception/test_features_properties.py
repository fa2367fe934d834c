"""Whatever a scan holds, extraction returns features or counted rejections: never an
exception, never a NaN, never an index outside the scan."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.perception.features import (
    DiscRoi,
    FeatureParams,
    LineRoi,
    Roi,
    extract_features,
    roi_mask,
)
from appliance.perception.types import ScanFeatures
from drivers.geometry import Pose2D

# A small alphabet of ranges (repeats make segments, zeros and jumps break them) plus
# anything at all, so that lines, arcs, debris and garbage all occur in 100 beams.
beam = st.one_of(
    st.sampled_from([0.0, 0.0, 2.0, 2.01, 2.02, 2.05, 5.0, 5.3, 19.99]),
    st.floats(-1.0, 40.0),
    st.sampled_from([math.nan, math.inf, 1e-300, 1e300]),
)
frame = st.builds(Pose2D, st.floats(-100.0, 100.0), st.floats(-100.0, 100.0), st.floats(-7.0, 7.0))
coordinate = st.floats(-30.0, 30.0)
roi = st.one_of(
    st.builds(DiscRoi, coordinate, coordinate, st.floats(0.01, 30.0)),
    st.builds(LineRoi, coordinate, coordinate, coordinate, coordinate, st.floats(0.01, 5.0)),
)


def _check(features: ScanFeatures, count: int) -> None:
    previous = 0
    for start, stop in features.segments:
        assert previous <= start < stop <= count
        previous = stop
    for line in features.lines:
        values = [line.r_m, line.alpha_rad, line.rms_m, *line.start_xy_m, *line.end_xy_m]
        assert all(math.isfinite(v) for v in values)
        assert line.r_m >= 0.0 and -math.pi < line.alpha_rad <= math.pi
        assert np.isfinite(line.covariance).all() and (np.diag(line.covariance) >= 0.0).all()
        assert 0 <= line.first_index <= line.last_index < count
        assert math.isfinite(line.length_m)
    for circle in features.circles:
        assert all(math.isfinite(v) for v in (circle.cx_m, circle.cy_m, circle.rms_m))
        assert np.isfinite(circle.covariance).all() and (np.diag(circle.covariance) >= 0.0).all()
        assert 0 <= circle.first_index <= circle.last_index < count
    assert all(isinstance(n, int) and n > 0 for n in features.rejections.values())


@given(
    st.lists(beam, min_size=0, max_size=100),
    st.sampled_from([0.25, 0.5]),
    frame,
    st.none() | st.lists(roi, max_size=3),
)
def test_any_scan_gives_features_or_rejections(
    ranges: list[float], step_deg: float, pose: Pose2D, rois: list[Roi] | None
) -> None:
    angles = math.radians(-135.0) + math.radians(step_deg) * np.arange(len(ranges))
    _check(extract_features(np.array(ranges), angles, pose, FeatureParams(), rois), len(ranges))


@given(st.lists(beam, min_size=1, max_size=60), frame)
def test_a_region_covering_everything_is_the_whole_scan(ranges: list[float], pose: Pose2D) -> None:
    angles = math.radians(-135.0) + math.radians(0.25) * np.arange(len(ranges))
    whole = extract_features(np.array(ranges), angles, pose)
    everything = DiscRoi(pose.x_m, pose.y_m, 1e6)
    covered = extract_features(np.array(ranges), angles, pose, rois=[everything])
    assert covered.segments == whole.segments
    assert [(x.r_m, x.alpha_rad) for x in covered.lines] == [
        (x.r_m, x.alpha_rad) for x in whole.lines
    ]
    assert [(c.cx_m, c.cy_m) for c in covered.circles] == [(c.cx_m, c.cy_m) for c in whole.circles]


def test_roi_shapes() -> None:
    xy = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.05], [2.3, 0.0], [1.0, 0.3]])
    assert roi_mask(xy, [DiscRoi(0.0, 0.0, 1.0)]).tolist() == [True, True, False, False, False]
    band = LineRoi(0.0, 0.0, 2.0, 0.0, 0.1)  # a capsule: the ends are rounded
    assert roi_mask(xy, [band]).tolist() == [True, True, True, False, False]
    assert roi_mask(xy, []).tolist() == [False] * 5
    point = LineRoi(1.0, 0.0, 1.0, 0.0, 0.5)  # a zero-length band is a disc
    assert roi_mask(xy, [point]).tolist() == [False, True, False, False, True]
    with pytest.raises(ValueError, match="radius_m"):
        DiscRoi(0.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="half_width_m"):
        LineRoi(0.0, 0.0, 1.0, 0.0, -1.0)


def test_rejections_are_read_only() -> None:
    features = extract_features(np.array([5.0]), np.array([0.0]), Pose2D(0.0, 0.0, 0.0))
    assert features.rejections == {"segment.isolated": 1}
    with pytest.raises(TypeError):
        features.rejections["x"] = 1
