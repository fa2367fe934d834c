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

One compiled pass over the beams (`_clusters`, a `jit` kernel: as array arithmetic it
was two dozen numpy calls per scan); only the (few) clusters are looped over by the
caller.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.perception.jit import F64, I64, IN_1D, IN_BOOL, kernel
from appliance.perception.points import AngleCache
from appliance.perception.types import BoolArray, FloatArray, RejectReason, ScannerModel

IndexArray = npt.NDArray[np.int64]


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
    if valid.shape[0] == 0:
        return Segmentation((), {})
    step_sine, remaining_sine = _STEP_SINES.get(angles_rad, params.lambda_rad)
    starts, stops, too_few, dispersed = _clusters(
        np.ascontiguousarray(xy_m[:, 0]),
        np.ascontiguousarray(xy_m[:, 1]),
        ranges_m,
        valid,
        step_sine,
        remaining_sine,
        3.0 * scanner.sigma_m,
        params.min_points,
        params.max_mean_spacing_m,
    )
    rejections = {
        f"segment.{reason}": n
        for reason, n in ((RejectReason.ISOLATED, too_few), (RejectReason.DISPERSED, dispersed))
        if n
    }
    kept = zip(starts.tolist(), stops.tolist(), strict=True)
    return Segmentation(tuple(kept), rejections)


@kernel(IN_1D, IN_1D, IN_1D, IN_BOOL, IN_1D, IN_1D, F64, I64, F64)
def _clusters(xs: FloatArray, ys: FloatArray, ranges_m: FloatArray, valid: BoolArray,
              step_sine: FloatArray, remaining_sine: FloatArray, noise_m: float,
              min_points: int, max_mean_spacing_m: float
              ) -> tuple[IndexArray, IndexArray, int, int]:  # fmt: skip
    """The kept clusters' starts and stops, and how many were too few points and how
    many dispersed. Two valid neighbours are joined when their gap is within
    ``ranges_m · step_sine / remaining_sine + noise_m`` (`breakpoint_distance_m`)."""
    count = valid.shape[0]
    gaps = np.empty(max(count - 1, 0))
    finite = True
    for i in range(count - 1):
        dx, dy = xs[i + 1] - xs[i], ys[i + 1] - ys[i]
        gaps[i] = math.sqrt(dx * dx + dy * dy)
        finite = finite and gaps[i] < math.inf
    if not finite:  # beyond 1e154 m the squares overflow: hypot does not
        for i in range(count - 1):
            gaps[i] = math.hypot(xs[i + 1] - xs[i], ys[i + 1] - ys[i])
    starts = np.empty(count, dtype=np.int64)
    stops = np.empty(count, dtype=np.int64)
    kept = too_few = dispersed = 0
    start = -1
    travelled = 0.0  # the joined gaps since the cluster's start
    for i in range(count):
        if not valid[i]:
            continue
        if start < 0:
            start, travelled = i, 0.0
        joined = False
        if i + 1 < count and valid[i + 1]:
            limit = ranges_m[i] * step_sine[i]
            limit /= remaining_sine[i]
            limit += noise_m
            joined = gaps[i] <= limit
        if joined:
            travelled += gaps[i]
            continue
        size = i + 1 - start
        if size < min_points:
            too_few += 1
        elif not travelled / max(size - 1, 1) <= max_mean_spacing_m:
            dispersed += 1
        else:
            starts[kept], stops[kept] = start, i + 1
            kept += 1
        start = -1
    return starts[:kept], stops[:kept], too_few, dispersed


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
