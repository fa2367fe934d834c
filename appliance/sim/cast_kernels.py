"""The simulated scanner's compiled loops: a scan's nearest hits, and the receiver's echo.

Why compiled: `dbw sim dock` renders a 1081-beam scan of a dozen shapes every 20 ms of
simulated time, and as array code a scan was some 300 numpy calls on small arrays, each
a microsecond or two before any arithmetic. Here a cast is one pass over beams x shapes
and a beam's echo one pass over its sub-rays (`appliance.perception.jit`: compiled at
import, numpy's handling of division by zero, no fast-math).

Every product is taken element by element and rounded once per operation, in the order
the formulas below are written: the result of a cast does not depend on how many beams
or shapes are in it, nor on the CPU (a matrix product would round with fused
multiply-adds where the CPU has them). A kernel calls only kernels of this file.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from appliance.perception.jit import F64, IN_2D, IN_INDEX, OUT_1D, OUT_INDEX, kernel

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

PARALLEL_EPS = 1e-9  # |d x e| below which a beam counts as parallel (1e-9 rad for 1 m)
NO_HIT = -1
NO_RETURN_M = 1e9  # stands in for a sub-ray's missing return while sorting and grouping


@kernel(F64, F64, IN_2D, IN_2D, IN_2D, IN_INDEX, F64, OUT_1D, OUT_INDEX)
def nearest_hits_into(ox: float, oy: float, directions: FloatArray, segs: FloatArray,
                      circs: FloatArray, numbers: IndexArray, max_range_m: float,
                      ranges: FloatArray, index: IndexArray) -> None:  # fmt: skip
    """Per beam of (beams, 2) unit ``directions`` from (ox, oy), the nearest hit of (N, 4)
    segments x0, y0, x1, y1 and (M, 3) circles cx, cy, r into ``ranges`` (0: none within
    ``max_range_m``, or at 0 m) and ``index`` (``numbers[k]`` of the k-th shape,
    segments first; NO_HIT for none). Ties go to the earlier shape. The origin must be
    outside every circle (a scanner inside one is blinded, which is the caller's).

    A segment: origin + t d = p0 + s e gives t = (w x e) / (d x e), s = (w x d) / (d x e)
    with w = p0 - origin; a hit has 0 <= s <= 1 and t >= 0, and a beam parallel to it
    (|d x e| <= PARALLEL_EPS) none. A circle: |m + t d|^2 = r^2 with m = origin - centre
    gives the entry t = -(sqrt(b^2 - c) + b), b = m.d, c = |m|^2 - r^2 (a miss: b^2 < c),
    valid when t >= 0."""
    n_segs, n_circs = segs.shape[0], circs.shape[0]
    seg = np.empty((n_segs, 5))  # d x e = dx ey + dy (-ex), w x d = dx (-wy) + dy wx
    for j in range(n_segs):
        ex = segs[j, 2] - segs[j, 0]
        ey = segs[j, 3] - segs[j, 1]
        wx = segs[j, 0] - ox
        wy = segs[j, 1] - oy
        seg[j, 0], seg[j, 1], seg[j, 2], seg[j, 3] = ey, -ex, -wy, wx
        seg[j, 4] = wx * ey - wy * ex
    circ = np.empty((n_circs, 3))
    for k in range(n_circs):
        mx = ox - circs[k, 0]
        my = oy - circs[k, 1]
        circ[k, 0], circ[k, 1] = mx, my
        circ[k, 2] = mx * mx + my * my - circs[k, 2] * circs[k, 2]
    for i in range(directions.shape[0]):
        dx, dy = directions[i, 0], directions[i, 1]
        best, which = np.inf, -1
        for j in range(n_segs):
            denom = dx * seg[j, 0] + dy * seg[j, 1]
            if abs(denom) > PARALLEL_EPS:
                reciprocal = 1.0 / denom
                s = (dx * seg[j, 2] + dy * seg[j, 3]) * reciprocal
                t = reciprocal * seg[j, 4]
                if abs(s - 0.5) <= 0.5 and t >= 0.0 and t < best:
                    best, which = t, j
        for k in range(n_circs):
            b = dx * circ[k, 0] + dy * circ[k, 1]
            discriminant = b * b - circ[k, 2]
            if discriminant >= 0.0:  # else a miss (and no square root of it, as Python)
                t = -(math.sqrt(discriminant) + b)
                if t >= 0.0 and t < best:
                    best, which = t, n_segs + k
        if best <= max_range_m and best > 0.0:
            ranges[i], index[i] = best, numbers[which]
        else:
            ranges[i], index[i] = 0.0, NO_HIT


@kernel(IN_2D, IN_2D, F64, F64, OUT_1D, OUT_1D)
def first_strong_echo_into(ranges_m: FloatArray, energy: FloatArray, pulse_merge_m: float,
                           min_energy: float, found_m: FloatArray, found_energy: FloatArray
                           ) -> None:  # fmt: skip
    """What a pulsed receiver makes of each row of (beams, returns) ``ranges_m`` (0: no
    return) and their ``energy``, into ``found_m`` and ``found_energy`` (0, 0: nothing).

    Returns are taken nearest first (equal ranges in their column order), and one within
    ``pulse_merge_m`` of the previous one overlaps its pulse: they arrive as one echo,
    whose energy is their sum and whose range is their energy-weighted mean, both summed
    in that order. A larger gap starts the next echo. The first echo with at least
    ``min_energy`` (more than 0 if ``min_energy`` is 0) is the measurement."""
    returns = ranges_m.shape[1]
    at_least = min_energy > 0.0  # else: more than 0
    order_m = np.empty(returns)
    order_energy = np.empty(returns)
    for i in range(ranges_m.shape[0]):
        for k in range(returns):  # an insertion sort: stable, and the rows are short
            if ranges_m[i, k] > 0.0:
                range_m, e = ranges_m[i, k], energy[i, k]
            else:
                range_m, e = NO_RETURN_M, 0.0
            slot = k
            while slot > 0 and order_m[slot - 1] > range_m:
                order_m[slot], order_energy[slot] = order_m[slot - 1], order_energy[slot - 1]
                slot -= 1
            order_m[slot], order_energy[slot] = range_m, e
        found_m[i], found_energy[i] = 0.0, 0.0
        total, moment = 0.0, 0.0
        for k in range(returns):
            if k > 0 and order_m[k] - order_m[k - 1] > pulse_merge_m:
                if (total >= min_energy) if at_least else (total > 0.0):
                    break
                total, moment = 0.0, 0.0
            total += order_energy[k]
            moment += order_energy[k] * order_m[k]
        if (total >= min_energy) if at_least else (total > 0.0):
            found_m[i], found_energy[i] = moment / total, total
