"""Cutting a scan into clusters of neighbouring points (Qian et al. 3.2.3, first step).

Two consecutive points belong to one object when they are closer than the adaptive
breakpoint distance of Borges & Aldon (2004)::

    D_max = r_{n-1} · sin Δφ / sin(λ − Δφ) + 3 σ_r

The first term is how far apart two points on a surface seen at the grazing angle λ
would be; it grows with range, so a fixed threshold (too loose close by, too tight far
away) is not needed. The second covers the range noise of both points. Then:

- a beam without an echo always breaks a cluster: a hole is never bridged, because an
  object seen through a hole is not the object on either side of it;
- the first and last beams of a 270° scan are never joined: they look 90° apart, and a
  wrap-around join would only ever glue two unrelated objects;
- clusters of too few points (isolated: rain, dust, a mixed pixel between two edges)
  and clusters whose points are on average farther apart than a surface gives
  (dispersed: vegetation, a grazing wall) are dropped and counted.

Vectorised: one pass of array arithmetic over all beams; only the (few) clusters are
looped over by the caller.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from appliance.perception.points import AngleCache
from appliance.perception.types import BoolArray, FloatArray, RejectReason, ScannerModel


@dataclass(frozen=True)
class SegmentParams:
    """Breakpoint and cluster filter settings.

    ``lambda_rad`` 10° is Borges & Aldon's choice: surfaces seen more obliquely than
    that are cut, which costs nothing here (no landmark is seen that flat) and keeps a
    cylinder apart from a wall behind it. Three points make the smallest cluster worth
    keeping (a 0.3 m cylinder at 20 m gives four). 0.35 m mean spacing is twice the
    0.5° beam spacing at 20 m: beyond that the points no longer sample a surface.
    """

    lambda_rad: float = math.radians(10.0)
    min_points: int = 3
    max_mean_spacing_m: float = 0.35

    def __post_init__(self) -> None:
        if not 0.0 < self.lambda_rad <= math.pi / 2.0:
            raise ValueError(f"lambda_rad must be in (0, π/2], got {self.lambda_rad}")
        if self.min_points < 1:
            raise ValueError(f"min_points must be >= 1, got {self.min_points}")
        if not self.max_mean_spacing_m > 0.0:
            raise ValueError(f"max_mean_spacing_m must be > 0, got {self.max_mean_spacing_m}")


@dataclass(frozen=True)
class Segmentation:
    """The kept clusters as half-open beam index ranges, and what was dropped."""

    segments: tuple[tuple[int, int], ...]
    rejections: Mapping[str, int]


def breakpoint_distance_m(
    previous_range_m: FloatArray,
    delta_angle_rad: FloatArray,
    lambda_rad: float,
    sigma_m: float,
) -> FloatArray:
    """Borges & Aldon's D_max for each pair of consecutive beams.

    The beam step is clamped just below λ: at λ the formula's denominator vanishes (a
    surface seen at λ would need an infinite gap), and a scan that coarse is not what
    the rule was made for; a finite, very large threshold is the honest answer.
    """
    with np.errstate(invalid="ignore"):
        step = np.minimum(np.abs(delta_angle_rad), 0.999 * lambda_rad)
        distance: FloatArray = previous_range_m * np.sin(step) / np.sin(lambda_rad - step)
    return distance + 3.0 * sigma_m


def segment_scan(
    xy_m: FloatArray,
    ranges_m: FloatArray,
    angles_rad: FloatArray,
    valid: BoolArray,
    params: SegmentParams,
    scanner: ScannerModel,
) -> Segmentation:
    """Clusters of consecutive valid beams closer than the breakpoint distance.

    ``xy_m`` (N, 2) are the points in any Cartesian frame (distances do not depend on
    it), ``angles_rad`` the beam angles (only their differences matter), ``valid`` the
    beams to use: beams outside it count as no echo.
    """
    count = int(valid.shape[0])
    if count == 0:
        return Segmentation((), {})
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        step = xy_m[1:] - xy_m[:-1]
        squared = step * step
        gaps = np.sqrt(squared[:, 0] + squared[:, 1])
        if count > 1 and not np.maximum.reduce(gaps) < math.inf:  # beyond 1e154 m: hypot
            gaps = np.hypot(step[:, 0], step[:, 1])
        step_sine, remaining_sine = _STEP_SINES.get(angles_rad, params.lambda_rad)
        limits = ranges_m[:-1] * step_sine
        limits /= remaining_sine
        limits += 3.0 * scanner.sigma_m
        joined = valid[:-1] & valid[1:] & (gaps <= limits)
        # A cluster starts at every valid beam not joined to its predecessor.
        apart = ~joined
        starts_flag = valid.copy()
        starts_flag[1:] &= apart
        ends_flag = valid.copy()
        ends_flag[:-1] &= apart
        starts = starts_flag.nonzero()[0]
        stops = ends_flag.nonzero()[0] + 1
        sizes = stops - starts
        # Mean spacing per cluster from a running sum of the joined gaps.
        travelled = np.empty(count)
        travelled[0] = 0.0
        np.where(joined, gaps, 0.0).cumsum(out=travelled[1:])
        mean_spacing = (travelled[stops - 1] - travelled[starts]) / np.maximum(sizes - 1, 1)
    too_few = sizes < params.min_points
    dispersed = ~too_few & ~(mean_spacing <= params.max_mean_spacing_m)
    keep = ~(too_few | dispersed)
    rejections = {
        f"segment.{reason}": n
        for reason, n in (
            (RejectReason.ISOLATED, int(np.count_nonzero(too_few))),
            (RejectReason.DISPERSED, int(np.count_nonzero(dispersed))),
        )
        if n
    }
    kept = zip(starts[keep].tolist(), stops[keep].tolist(), strict=True)
    return Segmentation(tuple(kept), rejections)


def _step_sines(angles: FloatArray, lambda_rad: float) -> tuple[FloatArray, FloatArray]:
    """``sin Δφ`` and ``sin(λ − Δφ)`` of `breakpoint_distance_m` for the beams at
    ``angles``: a scanner's angles are the same scan after scan."""
    delta = np.diff(angles)
    with np.errstate(invalid="ignore"):
        step = np.minimum(np.abs(delta), 0.999 * lambda_rad)
        sines = np.sin(step), np.sin(lambda_rad - step)
    for sine in sines:
        sine.flags.writeable = False
    return sines


_STEP_SINES = AngleCache(_step_sines)
