"""Nearest-hit ray casting of many beams against line segments and circles.

Two simulated LMS111 at 50 Hz render 100 scans of 1081 beams a second, next to the rest
of the simulation in the same process, so a scan must cost well under a millisecond. The
cast itself is one compiled pass over beams x shapes (`cast_kernels`); in a site of many
shapes, those out of range are dropped first, because a 40 m yard wall is usually
farther than the scanner's 20 m (with a handful, casting against them all is cheaper
than finding them).

Conventions, chosen to match what the scanner reports rather than what geometry allows:

- A beam that hits nothing within ``max_range_m`` returns 0.0: the LMS111 reports a
  distance of 0 for "no echo", so the twin can send the array as it is.
- A scanner origin inside (or on) a circle is blinded: every beam returns 0. A real
  scanner whose window is inside an object sees nothing useful, and returning the exit
  distance would invent a surface the beam never reflected from outside.
- A beam parallel to a segment (grazing it edge-on) does not hit it: an infinitely thin
  surface seen edge-on returns no energy. Zero-length segments are therefore invisible.
- A hit at exactly 0 m (a surface through the origin) is reported as 0, i.e. no echo.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from appliance.sim.cast_kernels import NO_HIT as NO_HIT
from appliance.sim.cast_kernels import nearest_hits_into

# Shapes are culled by distance only above this many of a kind: for fewer, casting against
# the far ones costs less than the dozen array operations that find them.
_CULL_ABOVE = 16


class RayHits(NamedTuple):
    """Per beam: nearest range (0 = no echo) and what was hit (index into shapes)."""

    ranges_m: NDArray[np.float64]
    # Index into the concatenation [segments..., circles...]; NO_HIT (-1) where range is 0.
    hit_index: NDArray[np.int64]


def _as_rows(array: NDArray[np.float64] | None, width: int, what: str) -> NDArray[np.float64]:
    if array is None:
        return np.empty((0, width), dtype=np.float64)
    rows = np.asarray(array, dtype=np.float64)
    if rows.size == 0:
        return np.empty((0, width), dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != width:
        raise ValueError(f"{what} must be an (N, {width}) array, got shape {rows.shape}")
    return rows


def point_segment_distance_m(
    x_m: float, y_m: float, segments: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Distance from a point to each segment (N,4 rows x0, y0, x1, y1); used to cull."""
    x0, y0, x1, y1 = segments.T
    ex, ey = x1 - x0, y1 - y0
    length_sq = ex * ex + ey * ey
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(length_sq > 0.0, ((x_m - x0) * ex + (y_m - y0) * ey) / length_sq, 0.0)
    s = np.clip(s, 0.0, 1.0)
    result: NDArray[np.float64] = np.hypot(x0 + s * ex - x_m, y0 + s * ey - y_m)
    return result


def nearest_hits(
    origin_x_m: float,
    origin_y_m: float,
    angles_rad: NDArray[np.float64],
    segments: NDArray[np.float64] | None,
    circles: NDArray[np.float64] | None,
    max_range_m: float,
) -> RayHits:
    """Cast beams from one origin at world-frame ``angles_rad``; return the nearest hits.

    ``segments`` is (N,4): x0, y0, x1, y1; ``circles`` is (M,3): cx, cy, radius (metres).
    Returned ranges beyond ``max_range_m`` are reported as 0 (no echo), see module doc.
    """
    angles = np.asarray(angles_rad, dtype=np.float64).ravel()
    segs = _as_rows(segments, 4, "segments")
    circs = _as_rows(circles, 3, "circles")
    if angles.size == 0:
        return RayHits(np.zeros(0), np.full(0, NO_HIT, dtype=np.int64))
    if inside_any_circle(origin_x_m, origin_y_m, circs):
        return _blinded(angles.size)
    return nearest_hits_along(
        origin_x_m, origin_y_m, beam_directions(angles), segs, circs, max_range_m
    )


def beam_directions(angles_rad: NDArray[np.float64]) -> NDArray[np.float64]:
    """(beams, 2) unit vectors of the (1-D) angles, for `nearest_hits_along`."""
    directions = np.empty((angles_rad.shape[0], 2))  # np.stack costs more than the sines
    # Contiguous results copied in: into a strided column numpy may take another (scalar)
    # sine and cosine, which may round differently.
    directions[:, 0] = np.cos(angles_rad)
    directions[:, 1] = np.sin(angles_rad)
    return directions


def _blinded(beams: int) -> RayHits:
    index = np.empty(beams, dtype=np.int64)
    index.fill(NO_HIT)
    return RayHits(np.zeros(beams), index)


def nearest_hits_along(
    origin_x_m: float,
    origin_y_m: float,
    directions: NDArray[np.float64],
    segs: NDArray[np.float64],
    circs: NDArray[np.float64],
    max_range_m: float,
) -> RayHits:
    """`nearest_hits` of beams given as (beams, 2) unit ``directions`` (`beam_directions`),
    so that casts of one scan against several shape sets compute them once. ``segs`` and
    ``circs`` are (N, 4) and (M, 3) float64 rows (either may have none), and the origin
    is outside every circle (`inside_any_circle`): a blinded scanner is the caller's.

    Each beam's hit is computed on its own (`cast_kernels.nearest_hits_into`), so it is
    the same whatever else is cast with it: a scan's static shapes and its walkers cast
    apart and joined by `nearer_of` give one cast of both, to the last bit."""
    n_segs, n_circs = segs.shape[0], circs.shape[0]
    if n_segs > _CULL_ABOVE or n_circs > _CULL_ABOVE:
        seg_ids, circ_ids = np.arange(n_segs), np.arange(n_circs)
        if n_segs > _CULL_ABOVE:
            distance = point_segment_distance_m(origin_x_m, origin_y_m, segs)
            seg_ids = np.flatnonzero(distance <= max_range_m)
            segs = segs[seg_ids]
        if n_circs > _CULL_ABOVE:
            gap = np.hypot(circs[:, 0] - origin_x_m, circs[:, 1] - origin_y_m) - circs[:, 2]
            circ_ids = np.flatnonzero(gap <= max_range_m)
            circs = circs[circ_ids]
        numbers = np.concatenate([seg_ids, circ_ids + n_segs])
    else:
        numbers = _shape_numbers(n_segs + n_circs)
    beams = directions.shape[0]
    ranges = np.empty(beams)
    index = np.empty(beams, dtype=np.int64)
    nearest_hits_into(
        origin_x_m, origin_y_m, directions, segs, circs, numbers, max_range_m, ranges, index
    )
    return RayHits(ranges, index)


@functools.lru_cache(maxsize=64)
def _shape_numbers(count: int) -> NDArray[np.int64]:
    """``np.arange(count)``, kept (read-only): a site has the same few shapes every scan."""
    numbers = np.arange(count, dtype=np.int64)
    numbers.flags.writeable = False
    return numbers


def inside_any_circle(x_m: float, y_m: float, circles: NDArray[np.float64] | None) -> bool:
    """Whether the point is inside (or on) a circle: a scanner there is blinded.

    In Python floats: a site has a handful of circles, and the arithmetic is the same
    (each operation rounded once, as numpy's element-wise one is)."""
    circs = _as_rows(circles, 3, "circles")
    for cx, cy, radius in circs.tolist():
        mx, my = x_m - cx, y_m - cy
        if mx * mx + my * my - radius * radius <= 0.0:
            return True
    return False


def nearer_of(first: RayHits, second: RayHits, second_offset: int) -> RayHits:
    """Per beam the nearer of two casts of one origin and beam set, as one cast of both
    shape sets would give it: ``second``'s indices shifted by ``second_offset`` (the
    count of ``first``'s shapes), and ties to ``first``, whose shapes come first."""
    a, b = first.ranges_m, second.ranges_m
    take = (b > 0.0) & ((a == 0.0) | (b < a))
    return RayHits(
        np.where(take, b, a),
        np.where(take, second.hit_index + second_offset, first.hit_index),
    )


def remission_of(
    hits: RayHits,
    n_segments: int,
    n_circles: int,
    segment_remission: NDArray[np.float64] | None = None,
    circle_remission: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """The remission of what each beam hit (0 = nothing), shapes as in ``cast_rays``."""
    seg_rem = _remission(segment_remission, n_segments, "segment_remission")
    circ_rem = _remission(circle_remission, n_circles, "circle_remission")
    table = np.concatenate([seg_rem, circ_rem, [0.0]])  # index -1 picks the trailing 0
    result: NDArray[np.float64] = table[hits.hit_index]
    return result


def cast_rays(
    origin_x_m: float,
    origin_y_m: float,
    angles_rad: NDArray[np.float64],
    segments: NDArray[np.float64] | None,
    circles: NDArray[np.float64] | None,
    max_range_m: float,
    segment_remission: NDArray[np.float64] | None = None,
    circle_remission: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Ranges (0 = no echo) and the remission of the surface each beam hit (0 = none).

    Remissions are per shape, in the order of ``segments`` and ``circles``; omitted ones
    count as 1.0, so callers that only want ranges need not invent them.
    """
    hits = nearest_hits(origin_x_m, origin_y_m, angles_rad, segments, circles, max_range_m)
    n_segments = 0 if segments is None else int(np.asarray(segments).reshape(-1, 4).shape[0])
    n_circles = 0 if circles is None else int(np.asarray(circles).reshape(-1, 3).shape[0])
    remission = remission_of(hits, n_segments, n_circles, segment_remission, circle_remission)
    return hits.ranges_m, remission


def _remission(values: NDArray[np.float64] | None, count: int, what: str) -> NDArray[np.float64]:
    if values is None:
        return np.ones(count)
    array = np.asarray(values, dtype=np.float64).ravel()
    if array.size != count:
        raise ValueError(f"{what} has {array.size} values for {count} shapes")
    return array
