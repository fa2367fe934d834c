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
from appliance.perception.jit import IN_1D, IN_2D, kernel
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
    discs = np.array([(r.cx_m, r.cy_m, r.radius_m) for r in rois if isinstance(r, DiscRoi)])
    capsules = np.array(
        [(r.x0_m, r.y0_m, r.x1_m, r.y1_m, r.half_width_m) for r in rois if isinstance(r, LineRoi)]
    )
    return _in_regions(
        np.ascontiguousarray(xy_m[:, 0]),
        np.ascontiguousarray(xy_m[:, 1]),
        discs.reshape(-1, 3),
        capsules.reshape(-1, 5),
    )


@kernel(IN_1D, IN_1D, IN_2D, IN_2D)
def _in_regions(x_m: FloatArray, y_m: FloatArray, discs: FloatArray, capsules: FloatArray
                ) -> BoolArray:  # fmt: skip
    """Whether each point is in a disc (cx, cy, radius) or within a capsule's half width
    of its segment (x0, y0, x1, y1, half width). A point at 1e300 m is in none."""
    inside = np.zeros(x_m.shape[0], dtype=np.bool_)
    for i in range(x_m.shape[0]):
        for k in range(discs.shape[0]):
            dx, dy = x_m[i] - discs[k, 0], y_m[i] - discs[k, 1]
            if dx * dx + dy * dy <= discs[k, 2] * discs[k, 2]:
                inside[i] = True
                break
        if inside[i]:
            continue
        for k in range(capsules.shape[0]):
            x0, y0, x1, y1 = capsules[k, 0], capsules[k, 1], capsules[k, 2], capsules[k, 3]
            half_width = capsules[k, 4]
            ex, ey = x1 - x0, y1 - y0
            length_sq = ex * ex + ey * ey
            px, py = x_m[i] - x0, y_m[i] - y0
            along = 0.0
            if length_sq > 0.0:  # the foot of the point on the segment, clipped to it
                along = min(max((px * ex + py * ey) / length_sq, 0.0), 1.0)
            px -= along * ex
            py -= along * ey
            if px * px + py * py <= half_width * half_width:
                inside[i] = True
                break
    return inside


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
