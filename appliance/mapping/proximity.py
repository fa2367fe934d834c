"""Proximity points (Tazaki et al. 2020): a 3D cloud seen from a viewpoint as a 2D
"virtual scan" of the nearest obstacles, for the pallet detection of Kinouchi et al.
2.2 (2)(i) (`cloud_pallets`).

**Proximity points.** Around a viewpoint, the floor plan is cut into azimuth bins; in
each bin, of the points within a height band, the one nearest the viewpoint
horizontally is kept. The cloud becomes a 2D "virtual scan" of the nearest obstacles,
and a pallet's visible faces become a scan's outline: one face or an L, whose corner,
the nearest point of all, gathers many points. Vectorised: one pass of array arithmetic
over the band's points per viewpoint (``np.minimum.at`` per bin, then the first point
that reaches each bin's minimum); no Python loop over points.

**Height band.** 0.05 to 0.13 m above the floor (``floor_z_m``: the cloud is levelled,
z up). A pallet is 0.144 m tall: bottom boards (0-22 mm), blocks (to ~100 mm), deck and
stringer boards (to 144 mm). Between the blocks the fork openings show the inside of
the pallet, but the deck's edge above them is in line with the blocks' faces, so every
bin along a face has a point on the face. The lower edge is 5 cm, five times a
terminal's ~1 cm floor noise: a floor point past 3σ is one in a thousand, and with a
few hundred floor points under each bin's ray a 3 cm edge would let a stray one in
front of a pallet in every few bins (each is the bin's nearest point, and bends the
face). The upper edge is 14 mm under the deck's top, so cargo on the deck (from
144 mm up) stays out, but for the noise's tail, and the tail of cargo set back from
the pallet's edges is behind the faces, where a nearest point never is.

**Glimpses.** Where a bin along a pallet's face caught no point of the deck's edge
(a sparse cloud, a fork opening), its nearest point is something behind the face: the
deck's underside, a block inside. Points more than 3σ behind both sides of a hole at
most ``max_hole_m`` wide (a width on the surface: more bins near the viewpoint), whose
sides the breakpoint rule would join, are glimpses through it, not an outline:
`drop_glimpses` empties those bins, and the face stays one object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.mapping.pallets import FloatArray
from appliance.perception.segments import breakpoint_distance_m

IntArray = npt.NDArray[np.intp]

DEFAULT_BAND_M = (0.05, 0.13)
DEFAULT_STEP_RAD = math.radians(0.25)


def check_step(step_rad: float) -> int:
    """The number of bins in a turn; a step too fine to bin by (or not a number) is a
    programming error."""
    if not (math.isfinite(step_rad) and 1e-6 <= step_rad <= math.pi):
        raise ValueError(f"azimuth_step_rad must be in [1e-6, π], got {step_rad}")
    return math.ceil(2.0 * math.pi / step_rad)


@dataclass(frozen=True, eq=False)
class ProximityScan:
    """The proximity points of one viewpoint: occupied bins in azimuth order (from −π,
    counter-clockwise), each bin's nearest point and its horizontal distance."""

    bins: IntArray  # (K,) ascending
    xy_m: FloatArray  # (K, 2)
    range_m: FloatArray  # (K,)
    bin_count: int
    step_rad: float


def proximity_points(
    xyz_m: npt.ArrayLike,
    origin_xyz_m: npt.ArrayLike,
    height_band_m: tuple[float, float] = DEFAULT_BAND_M,
    azimuth_step_rad: float = DEFAULT_STEP_RAD,
    *,
    min_range_m: float = 0.0,
    max_range_m: float = math.inf,
) -> FloatArray:
    """(K, 2) nearest points per azimuth bin around ``origin_xyz_m`` among the points
    whose z is within ``height_band_m``, in azimuth order; empty bins dropped, points
    with nan/inf ignored."""
    band = band_xy(as_rows(xyz_m, 3), height_band_m[0], height_band_m[1])
    origin = as_rows(origin_xyz_m, 3)
    if origin.shape[0] != 1 or not np.isfinite(origin).all():
        return np.zeros((0, 2))
    scan = proximity_scan(band, origin[0, :2], azimuth_step_rad, min_range_m, max_range_m)
    return scan.xy_m


def as_rows(values: npt.ArrayLike, width: int) -> FloatArray:
    """``values`` as (N, width) floats; an array of any other shape (or not numbers) as
    no rows at all."""
    try:
        array = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return np.zeros((0, width))
    if array.ndim == 1 and array.shape[0] == width:
        array = array[None, :]
    if array.ndim != 2 or array.shape[1] != width:
        return np.zeros((0, width))
    return array


def band_xy(xyz: FloatArray, low_z_m: float, high_z_m: float) -> FloatArray:
    """The horizontal positions of the finite points within the height band."""
    z = xyz[:, 2]
    inside = (z >= low_z_m) & (z <= high_z_m)  # nan is in no band
    inside &= np.isfinite(xyz[:, 0]) & np.isfinite(xyz[:, 1])
    band: FloatArray = xyz[inside, :2]
    return band


def proximity_scan(
    band_xy_m: FloatArray,
    origin_xy_m: FloatArray,
    azimuth_step_rad: float,
    min_range_m: float = 0.0,
    max_range_m: float = math.inf,
) -> ProximityScan:
    """The proximity points of finite horizontal points ``band_xy_m`` (already cut to
    the height band) around ``origin_xy_m``; ties go to the first point."""
    bin_count = check_step(azimuth_step_rad)
    with np.errstate(all="ignore"):
        offset = band_xy_m - origin_xy_m
        distance = np.hypot(offset[:, 0], offset[:, 1])
        near = (distance >= min_range_m) & (distance <= max_range_m) & np.isfinite(distance)
        kept = np.flatnonzero(near)
        offset, distance = offset[kept], distance[kept]
        azimuth = np.arctan2(offset[:, 1], offset[:, 0])
        bins = ((azimuth + math.pi) / azimuth_step_rad).astype(np.intp)
        np.clip(bins, 0, bin_count - 1, out=bins)
    least = np.full(bin_count, np.inf)
    np.minimum.at(least, bins, distance)
    reaching = np.flatnonzero(distance == least[bins])  # ascending: first point first
    occupied, first = np.unique(bins[reaching], return_index=True)
    chosen = reaching[first]
    return ProximityScan(
        occupied.astype(np.intp),
        band_xy_m[kept[chosen]],  # the cloud's own points, not recomputed
        distance[chosen],
        bin_count,
        azimuth_step_rad,
    )


def hole_bins(range_m: FloatArray, step_rad: float, hole_m: float) -> FloatArray:
    """How many bins a hole ``hole_m`` wide spans at each range: an opening is a size
    on the surface, so it covers more bins near the viewpoint than far from it."""
    bins: FloatArray = hole_m / np.maximum(range_m * step_rad, 1e-9)
    return bins


def drop_glimpses(
    scan: ProximityScan, max_hole_m: float, lambda_rad: float, sigma_m: float
) -> ProximityScan:
    """The scan without its glimpses through holes (see the module docstring): points
    more than 3σ behind both flanking points, when the bins between the flanks span at
    most ``max_hole_m`` at the flanks' range and the flanks are close enough to be one
    surface."""
    count = int(scan.bins.shape[0])
    if count < 3:
        return scan
    glimpse = np.zeros(count, dtype=np.bool_)
    index = np.arange(count)
    widest = hole_bins(scan.range_m, scan.step_rad, max_hole_m)
    # Points in a hole, at most one a bin; 32 is 5 cm down to 0.36 m from the viewpoint
    # (the check is quadratic in it).
    longest = min(int(np.max(widest)), count - 2, 32)
    for run in range(1, longest + 1):
        before, after = (index - 1) % count, (index + run) % count
        span = (scan.bins[after] - scan.bins[before]) % scan.bin_count
        chord = scan.xy_m[after] - scan.xy_m[before]
        limit = breakpoint_distance_m(
            scan.range_m[before], (span * scan.step_rad).astype(np.float64), lambda_rad, sigma_m
        )
        hit = (span >= run + 1) & (span - 1 <= widest[before])
        hit &= np.hypot(chord[:, 0], chord[:, 1]) <= limit
        # Behind both flanks: a flank that is itself behind the surface (the far side of
        # a wide hole) is as far as the points next to it, and stops the run.
        farther = np.maximum(scan.range_m[before], scan.range_m[after]) + 3.0 * sigma_m
        for offset in range(run):
            hit &= scan.range_m[(index + offset) % count] > farther
        for offset in range(run):
            glimpse[(index[hit] + offset) % count] = True
    if not glimpse.any():
        return scan
    keep = ~glimpse
    return ProximityScan(
        scan.bins[keep], scan.xy_m[keep], scan.range_m[keep], scan.bin_count, scan.step_rad
    )
