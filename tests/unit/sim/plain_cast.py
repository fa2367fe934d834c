"""The simulator's casts and echo written as plain element-wise numpy, for tests that
hold the compiled loops (`appliance.sim.cast_kernels`) to them bit for bit.

Each value is computed by the same operations in the same order, each rounded once (no
matrix product, whose fused multiply-adds would round differently on some CPUs); the
formulation is otherwise independent: whole (beams x shapes) arrays, numpy's argmin
for the nearest (its first on ties), a stable sort and bincount for the echoes.
"""

from __future__ import annotations

import numpy as np

from appliance.sim.raycast import NO_HIT, RayHits


def plain_cast(
    ox: float,
    oy: float,
    directions: np.ndarray,
    segs: np.ndarray,
    circs: np.ndarray,
    max_range_m: float,
) -> RayHits:
    """`raycast.nearest_hits_along`: the nearest hit per beam, segments numbered first."""
    beams = directions.shape[0]
    dx, dy = directions[:, :1], directions[:, 1:]
    ex, ey = segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1]
    wx, wy = segs[:, 0] - ox, segs[:, 1] - oy
    mx, my = ox - circs[:, 0], oy - circs[:, 1]
    c = mx * mx + my * my - circs[:, 2] * circs[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        denom = dx * ey + dy * -ex  # d x e
        reciprocal = 1.0 / denom
        s = (dx * -wy + dy * wx) * reciprocal  # (w x d) / (d x e)
        t = reciprocal * (wx * ey - wy * ex)  # (w x e) / (d x e)
        segment_hit = (np.abs(denom) > 1e-9) & (np.abs(s - 0.5) <= 0.5) & (t >= 0.0)
        b = dx * mx + dy * my
        root = -(np.sqrt(b * b - c) + b)
    ts = np.hstack([np.where(segment_hit, t, np.inf), np.where(root >= 0.0, root, np.inf)])
    if ts.shape[1] == 0 or beams == 0:
        return RayHits(np.zeros(beams), np.full(beams, NO_HIT, dtype=np.int64))
    best = np.argmin(ts, axis=1)
    nearest = ts[np.arange(beams), best]
    hit = (nearest <= max_range_m) & (nearest > 0.0)
    return RayHits(np.where(hit, nearest, 0.0), np.where(hit, best, NO_HIT).astype(np.int64))


def plain_first_strong_echo(
    ranges_m: np.ndarray, energy: np.ndarray, pulse_merge_m: float, min_energy: float
) -> tuple[np.ndarray, np.ndarray]:
    """`scanner_errors.first_strong_echo`, returns sorted stably (equal ranges in their
    column order) and each echo's sums taken in that order by bincount."""
    beams, returns = ranges_m.shape
    hit = ranges_m > 0.0
    far = np.where(hit, ranges_m, 1e9)
    row_starts = returns * np.arange(beams)
    flat_order = (np.argsort(far, axis=1, kind="stable") + row_starts[:, None]).ravel()
    sorted_m = far.ravel()[flat_order]
    sorted_energy = np.where(hit, energy, 0.0).ravel()[flat_order]
    starts = np.empty(beams * returns, dtype=np.bool_)
    np.greater(sorted_m[1:] - sorted_m[:-1], pulse_merge_m, out=starts[1:])
    starts[row_starts] = True
    echo = np.cumsum(starts) - 1
    echo += row_starts.repeat(returns) - echo[row_starts].repeat(returns)
    size = beams * returns
    echo_energy = np.bincount(echo, sorted_energy, size).reshape(beams, returns)
    moment = np.bincount(echo, sorted_energy * sorted_m, size).reshape(beams, returns)
    strong = echo_energy >= min_energy if min_energy > 0.0 else echo_energy > 0.0
    first = np.argmax(strong, axis=1)
    rows = np.arange(beams)
    found = strong[rows, first]
    found_energy = np.where(found, echo_energy[rows, first], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        found_m = moment[rows, first] / np.where(found, found_energy, 1.0)
    found_m[~found] = 0.0
    return found_m, found_energy
