"""A scan's casts: `raycast.nearest_hits_along`'s arithmetic in fewer array operations.

Why: the docking simulation renders a scan every 20 ms of simulated time between the
localizer's steps, and there the caches are cold: each numpy call costs a microsecond
or two whatever its size, and a scan of the launcher was three hundred of them. So the
per-origin terms of the shapes (the products' operands) are computed once for all casts
of a scan (the central rays, the walkers apart, the footprints' sub-rays), each cast
takes the nearest hit over segments and circles in one pass instead of one per kind, and
the walkers' hits are merged with the static site's as they are found.

Results are `nearest_hits_along`'s, bit for bit: the products are taken on the same
operands (BLAS rounds them with fused multiply-adds, which element-wise numpy could not
reproduce), the rest is the same element-wise arithmetic in the same order, and ties go
to the same shape. Culling every shape to the beams inside its wedge of angles was
tried: it halves the arithmetic but adds more calls than it saves here.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import NamedTuple, TypeVar

import numpy as np
from numpy.typing import NDArray

from appliance.sim.raycast import (
    _CULL_ABOVE,
    _PARALLEL_EPS,
    _SCRATCH,
    NO_HIT,
    RayHits,
    point_segment_distance_m,
)

_EVERY = slice(None)
_NONE = slice(0)
_KEPT_VIEWS = 64


class _Views(threading.local):
    """`raycast._SCRATCH`'s arrays by (key, rows, cols), as last handed out: one look-up
    instead of a slice and a reshape (a scan asks for two dozen), emptied when large (the
    footprints' casts vary the rows). A view may outlive its buffer's growth: it is still
    scratch of its own, and at most these few are kept."""

    def __init__(self) -> None:
        self.floats: dict[tuple[str, int, int], NDArray[np.float64]] = {}
        self.flags: dict[tuple[str, int, int], NDArray[np.bool_]] = {}


_VIEWS = _Views()


_Array = TypeVar("_Array", NDArray[np.float64], NDArray[np.bool_])


def _kept(
    views: dict[tuple[str, int, int], _Array],
    make: Callable[[str, int, int], _Array],
    key: str,
    rows: int,
    cols: int,
) -> _Array:
    """The view last handed out for (key, rows, cols), else a new one from ``make``."""
    view = views.get((key, rows, cols))
    if view is None:
        if len(views) >= _KEPT_VIEWS:
            views.clear()
        view = views[key, rows, cols] = make(key, rows, cols)
    return view


def _floats(key: str, rows: int, cols: int) -> NDArray[np.float64]:
    return _kept(_VIEWS.floats, _SCRATCH.float_array, key, rows, cols)


def _flags(key: str, rows: int, cols: int) -> NDArray[np.bool_]:
    return _kept(_VIEWS.flags, _SCRATCH.flag_array, key, rows, cols)


class ShapeTerms(NamedTuple):
    """A scan's shapes seen from its origin, which is outside every circle: the
    operands of `raycast`'s products, ``seg_normal`` rows (ey, -ex) for d x e,
    ``seg_offset`` rows (-wy, wx) for w x d and ``circ_offset`` rows (mx, my) for m.d,
    and the per-shape terms w x e and |m|^2 - r^2."""

    ox: float
    oy: float
    segs: NDArray[np.float64]
    circs: NDArray[np.float64]
    seg_normal: NDArray[np.float64]
    seg_offset: NDArray[np.float64]
    w_cross_e: NDArray[np.float64]
    circ_offset: NDArray[np.float64]
    circ_c: NDArray[np.float64]


def shape_terms(
    ox: float, oy: float, segs: NDArray[np.float64], circs: NDArray[np.float64]
) -> ShapeTerms:
    """`ShapeTerms` of (N, 4) segments and (M, 3) circles from (ox, oy), each as
    `raycast`'s cast computes it. ``segs`` must not change in place (a site's do not):
    its directions are kept for the next scan of the same segments."""
    ex, ey, seg_normal = _segment_directions(segs)
    wx = segs[:, 0] - ox
    wy = segs[:, 1] - oy
    seg_offset = np.empty((2, segs.shape[0]))
    np.negative(wy, out=seg_offset[0])
    seg_offset[1] = wx
    circ_offset = np.empty((2, circs.shape[0]))
    mx, my = circ_offset[0], circ_offset[1]
    np.subtract(ox, circs[:, 0], out=mx)
    np.subtract(oy, circs[:, 1], out=my)
    return ShapeTerms(
        ox,
        oy,
        segs,
        circs,
        seg_normal,
        seg_offset,
        wx * ey - wy * ex,
        circ_offset,
        mx * mx + my * my - circs[:, 2] * circs[:, 2],
    )


_Directions = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
_last_segments: tuple[NDArray[np.float64], _Directions] | None = None


def _segment_directions(segs: NDArray[np.float64]) -> _Directions:
    """ex, ey and the rows (ey, -ex) of the segments, kept for the last array given:
    the scans of a site are of the same segments."""
    global _last_segments
    last = _last_segments
    if last is not None and last[0] is segs:
        return last[1]
    ex = segs[:, 2] - segs[:, 0]
    ey = segs[:, 3] - segs[:, 1]
    normal = np.empty((2, segs.shape[0]))
    normal[0] = ey
    np.negative(ex, out=normal[1])
    for array in (ex, ey, normal):
        array.flags.writeable = False
    _last_segments = (segs, (ex, ey, normal))  # one assignment: seen whole or not at all
    return ex, ey, normal


def nearest_hits_seen(
    terms: ShapeTerms,
    directions: NDArray[np.float64],
    max_range_m: float,
    circles: slice = _EVERY,
    segments: bool = True,
) -> RayHits:
    """`nearest_hits_along` of the segments (or none) and ``circles`` (a run of the
    circles) of ``terms``, from its origin, along (beams, 2) ``directions``."""
    normal, offset, w_cross_e = terms.seg_normal, terms.seg_offset, terms.w_cross_e
    circ_offset, circ_c = terms.circ_offset, terms.circ_c
    if circles != _EVERY or not segments:
        every = _EVERY if segments else _NONE
        normal, offset, w_cross_e = normal[:, every], offset[:, every], w_cross_e[every]
        circ_offset, circ_c = np.ascontiguousarray(circ_offset[:, circles]), circ_c[circles]
    numbers = None  # the products' columns' shape numbers, where not 0, 1, 2, ...
    n_segs, n_circs = normal.shape[1], circ_offset.shape[1]
    if n_segs > _CULL_ABOVE or n_circs > _CULL_ABOVE:  # dropped by distance, as there
        seg_ids, circ_ids = _SCRATCH.shape_numbers(n_segs), _SCRATCH.shape_numbers(n_circs)
        if n_segs > _CULL_ABOVE:
            distance = point_segment_distance_m(terms.ox, terms.oy, terms.segs)
            seg_ids = np.flatnonzero(distance <= max_range_m)
            normal, offset = normal.take(seg_ids, axis=1), offset.take(seg_ids, axis=1)
            w_cross_e = w_cross_e.take(seg_ids)
        if n_circs > _CULL_ABOVE:
            circs = terms.circs[circles]
            gap = np.hypot(circs[:, 0] - terms.ox, circs[:, 1] - terms.oy) - circs[:, 2]
            circ_ids = np.flatnonzero(gap <= max_range_m)
            circ_offset, circ_c = circ_offset.take(circ_ids, axis=1), circ_c.take(circ_ids)
        numbers = np.concatenate([seg_ids, circ_ids + n_segs])
    rays = directions.shape[0]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        kinds = []
        if normal.shape[1]:
            kinds.append(_segment_ts(directions, normal, offset, w_cross_e))
        if circ_offset.shape[1]:
            kinds.append(_circle_ts(directions, circ_offset, circ_c))
    if not kinds or rays == 0:
        return RayHits(np.zeros(rays), np.full(rays, NO_HIT, dtype=np.int64))
    if len(kinds) == 1:
        t = kinds[0]
    else:  # both kinds side by side, for one search of the nearest
        t = _floats("kinds", rays, kinds[0].shape[1] + kinds[1].shape[1])
        np.concatenate(kinds, axis=1, out=t)
    if t.shape[1] == 1:
        best, nearest = np.zeros(rays, dtype=np.intp), t[:, 0]  # read before the next cast
    else:  # the first of the nearest: segments before circles, each in order
        best = t.argmin(axis=1)
        nearest = t.ravel().take(best + _SCRATCH.row_starts(rays, t.shape[1]))
    if numbers is not None:
        best = numbers.take(best)
    hit = nearest <= max_range_m
    hit &= nearest > 0.0
    return RayHits(np.where(hit, nearest, 0.0), np.where(hit, best, NO_HIT))


def with_walkers(
    hits: RayHits,
    terms: ShapeTerms,
    directions: NDArray[np.float64],
    max_range_m: float,
    walkers: slice,
    first_number: int,
) -> RayHits:
    """``raycast.nearer_of(hits, nearest_hits_seen(...), first_number)`` of the circles
    ``walkers`` alone (numbered from ``first_number``), the walkers' own cast folded in.

    Why apart: a scanner at rest keeps the static site's hits (`scanner_model.RayCache`)
    and casts only the walkers, whose products are then taken on their own (a single
    walker's is a matrix-vector product, rounded differently from a matrix product)."""
    if terms.circs[walkers].shape[0] != 1:
        walking = nearest_hits_seen(terms, directions, max_range_m, walkers, segments=False)
        return _nearer(hits, walking.ranges_m, walking.hit_index + first_number, True)
    offset = np.ascontiguousarray(terms.circ_offset[:, walkers])
    with np.errstate(invalid="ignore"):
        t = _circle_ts(directions, offset, terms.circ_c[walkers])[:, 0]
    seen = t <= max_range_m
    seen &= t > 0.0
    return _nearer(hits, t, first_number, seen)


def _nearer(
    hits: RayHits,
    ranges_m: NDArray[np.float64],
    index: NDArray[np.int64] | int,
    seen: NDArray[np.bool_] | bool,
) -> RayHits:
    """`raycast.nearer_of` of ``hits`` and a cast of ``ranges_m`` (``seen`` where they
    are an echo, or True: where positive), ties to ``hits``."""
    a = hits.ranges_m
    take = ranges_m > 0.0 if seen is True else seen
    nearer = a == 0.0
    nearer |= ranges_m < a
    take &= nearer
    return RayHits(np.where(take, ranges_m, a), np.where(take, index, hits.hit_index))


def _segment_ts(
    directions: NDArray[np.float64],
    normal: NDArray[np.float64],
    offset: NDArray[np.float64],
    w_cross_e: NDArray[np.float64],
) -> NDArray[np.float64]:
    """(beams, segments) ranges, inf for no hit: `raycast._nearest_segment_hits`'s
    arithmetic in its order (floating-point warnings off), in scratch arrays (valid
    until the next cast)."""
    rays, count = directions.shape[0], normal.shape[1]
    denom = _floats("denom", rays, count)
    s = _floats("s", rays, count)
    t = _floats("t", rays, count)
    ok = _flags("ok", rays, count)
    check = _flags("check", rays, count)
    np.matmul(directions, normal, out=denom)  # d x e, operands (2, n) C-ordered
    np.matmul(directions, offset, out=s)  # w x d
    np.abs(denom, out=t)
    np.greater(t, _PARALLEL_EPS, out=ok)  # not parallel (nor a zero-length segment)
    np.reciprocal(denom, out=denom)
    s *= denom
    np.multiply(denom, w_cross_e, out=t)
    s -= 0.5
    np.abs(s, out=s)
    ok &= np.less_equal(s, 0.5, out=check)  # 0 <= s <= 1: within the segment
    ok &= np.greater_equal(t, 0.0, out=check)  # not behind the origin
    np.putmask(t, np.logical_not(ok, out=ok), np.inf)
    return t


def _circle_ts(
    directions: NDArray[np.float64], offset: NDArray[np.float64], circ_c: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(beams, circles) ranges, inf for no hit: `raycast._nearest_circle_hits`'s
    arithmetic in its order (floating-point warnings off), in scratch arrays (valid
    until the next cast)."""
    rays, count = directions.shape[0], offset.shape[1]
    b = _floats("b", rays, count)
    t = _floats("root", rays, count)
    miss = _flags("miss", rays, count)
    np.matmul(directions, offset, out=b)  # m.d, the operand (2, n) C-ordered
    np.multiply(b, b, out=t)
    t -= circ_c
    np.sqrt(t, out=t)
    t += b
    np.negative(t, out=t)
    np.greater_equal(t, 0.0, out=miss)  # a nan root (no hit) fails too
    np.putmask(t, np.logical_not(miss, out=miss), np.inf)
    return t
