"""One scan in, the launcher's features out (Qian et al. 3.2.3 and Fig. 5).

The steps are the paper's: points, clusters by adjacent-point distance, isolated and
dispersed points dropped, then line fitting and arc fitting on what is left. Each
cluster is offered to the cylinder test first (cheap to refuse: too wide, not
isolated); a cluster that is not a cylinder goes to split-and-merge for boards.

Regions of interest (3.2.3 b): once the estimator has a pose it can predict where the
cylinders and the front board are. Only beams whose point lies in some region are
then processed; the others count as no echo, so fewer, smaller clusters reach the
fits, which is where the time goes. The tests that look *beside* a cluster (is a
cylinder isolated, is a line's end occluded) still read the raw scan, so a feature found
inside a region is the one the whole scan gives.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
import numpy.typing as npt

from appliance.perception.cylinders import CircleParams, fit_cylinder
from appliance.perception.lines import LineParams, extract_lines
from appliance.perception.points import scan_points
from appliance.perception.segments import SegmentParams, segment_scan
from appliance.perception.types import (
    BoolArray,
    CircleFeature,
    FitRejection,
    FloatArray,
    LineFeature,
    ScanFeatures,
    ScannerModel,
)
from drivers.geometry import Pose2D
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, MountedScan


@dataclass(frozen=True)
class DiscRoi:
    """A disc around a predicted landmark, in the output frame."""

    cx_m: float
    cy_m: float
    radius_m: float

    def __post_init__(self) -> None:
        if not self.radius_m > 0.0:
            raise ValueError(f"radius_m must be > 0, got {self.radius_m}")

    def contains(self, xy_m: FloatArray) -> BoolArray:
        return self.contains_xy(xy_m[:, 0], xy_m[:, 1])

    def contains_xy(self, x_m: FloatArray, y_m: FloatArray) -> BoolArray:
        """`contains` of the points' coordinates as two arrays."""
        dx, dy = x_m - self.cx_m, y_m - self.cy_m
        dx *= dx
        dy *= dy
        dx += dy
        inside: BoolArray = dx <= self.radius_m * self.radius_m
        return inside


@dataclass(frozen=True)
class LineRoi:
    """The points within ``half_width_m`` of a predicted board's segment (a capsule),
    in the output frame."""

    x0_m: float
    y0_m: float
    x1_m: float
    y1_m: float
    half_width_m: float

    def __post_init__(self) -> None:
        if not self.half_width_m > 0.0:
            raise ValueError(f"half_width_m must be > 0, got {self.half_width_m}")

    def contains(self, xy_m: FloatArray) -> BoolArray:
        return self.contains_xy(xy_m[:, 0], xy_m[:, 1])

    def contains_xy(self, x_m: FloatArray, y_m: FloatArray) -> BoolArray:
        """`contains` of the points' coordinates as two arrays."""
        ex, ey = self.x1_m - self.x0_m, self.y1_m - self.y0_m
        length_sq = ex * ex + ey * ey
        px, py = x_m - self.x0_m, y_m - self.y0_m
        if length_sq > 0.0:
            along = px * ex
            along += py * ey
            along /= length_sq
            # Clipped to the segment (a sign of zero lost here is squared away below).
            np.maximum(along, 0.0, out=along)
            np.minimum(along, 1.0, out=along)
        else:
            along = np.zeros(len(px))
        px -= along * ex
        py -= along * ey
        px *= px
        py *= py
        px += py
        inside: BoolArray = px <= self.half_width_m * self.half_width_m
        return inside


Roi = DiscRoi | LineRoi


@dataclass(frozen=True)
class FeatureParams:
    """Everything the extraction can be tuned by; defaults for the LMS111 and the launcher."""

    scanner: ScannerModel = field(default_factory=ScannerModel)
    segments: SegmentParams = field(default_factory=SegmentParams)
    lines: LineParams = field(default_factory=LineParams)
    circles: CircleParams = field(default_factory=CircleParams)


_DEFAULTS = FeatureParams()


def roi_mask(xy_m: FloatArray, rois: Sequence[Roi]) -> BoolArray:
    """Beams whose point lies in at least one region."""
    if not rois:
        return np.zeros(xy_m.shape[0], dtype=np.bool_)
    x_m, y_m = np.ascontiguousarray(xy_m[:, 0]), np.ascontiguousarray(xy_m[:, 1])
    with np.errstate(over="ignore", invalid="ignore"):  # a point at 1e300 m is in none
        mask = rois[0].contains_xy(x_m, y_m)
        for roi in rois[1:]:
            mask |= roi.contains_xy(x_m, y_m)
    return mask


def extract_features(
    ranges_m: npt.ArrayLike,
    angles_rad: npt.ArrayLike,
    frame: Pose2D,
    params: FeatureParams | None = None,
    rois: Sequence[Roi] | None = None,
    *,
    range_offset_m: float = 0.0,
) -> ScanFeatures:
    """Segments, lines and cylinders of one scan, in the frame ``frame`` maps into.

    ``ranges_m`` (0 = no echo) and ``angles_rad`` are per beam in the sensor frame (x out
    of the window, counter-clockwise); ``frame`` is the sensor's pose in the output
    frame (the mount pose for vehicle-frame features). ``rois``: None processes the whole
    scan; a sequence (even empty) only the beams inside some region.
    ``range_offset_m`` is the scanner's range calibration, subtracted from each echo.
    """
    params = _DEFAULTS if params is None else params
    points = scan_points(ranges_m, angles_rad, frame, range_offset_m=range_offset_m)
    use = points.valid if rois is None else points.valid & roi_mask(points.xy_m, rois)
    angles = np.asarray(angles_rad, dtype=np.float64)
    segmentation = segment_scan(
        points.xy_m, points.ranges_m, angles, use, params.segments, params.scanner
    )
    counts: Counter[str] = Counter(segmentation.rejections)
    lines: list[LineFeature] = []
    circles: list[CircleFeature] = []
    for segment in segmentation.segments:
        circle = fit_cylinder(points, segment, params.circles, params.scanner)
        if isinstance(circle, CircleFeature):
            circles.append(circle)
            continue
        counts[f"circle.{circle.reason}"] += 1
        for result in extract_lines(points, segment, params.lines, params.scanner):
            if isinstance(result, FitRejection):
                counts[f"line.{result.reason}"] += 1
            else:
                lines.append(result)
    return ScanFeatures(
        segmentation.segments, tuple(lines), tuple(circles), MappingProxyType(dict(counts))
    )


def extract_mounted_features(
    mounted: MountedScan,
    params: FeatureParams | None = None,
    rois: Sequence[Roi] | None = None,
    *,
    range_offset_m: float = 0.0,
) -> ScanFeatures:
    """`extract_features` of a driver's scan, in the vehicle frame (its mount)."""
    sensor_angles = mounted.scan.angles_rad - DEVICE_FORWARD_RAD
    return extract_features(
        mounted.scan.ranges_m,
        sensor_angles,
        mounted.mount,
        params,
        rois,
        range_offset_m=range_offset_m,
    )
