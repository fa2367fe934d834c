"""A worker's route through a storage area: where the terminal is held while scanning.

Sites come from files with any number of pallet areas, jittered pallets, walls and posts,
so the route is derived from the geometry, not from a builder's grid: a worker scanning
pallets stands in front of each side of each pallet that is open to an aisle or to the
floor around the area, at a comfortable distance (``standoff_m``, or the middle of an
aisle narrower than twice that), never closer to anything than a body allows
(``clearance_m``); spots closer together than ``merge_m`` are one stop, and the stops are
walked nearest-next. Every pallet with an open side thus has a stop facing that side a
metre or so away, where a 5 m terminal sees it whole. Deterministic: no randomness, ties
broken by order (the pallets' order in the site, sides front, left, back, right).

Walkers are ignored (they move); a pallet boxed in on all four sides gets no stop.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from appliance.sim.raycast import nearest_hits, point_segment_distance_m
from appliance.sim.site import PERSON_RADIUS_M, Site, SitePallet
from drivers.geometry import Pose2D

_SIDES = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))  # outward normals, pallet frame
_OFF_THE_SIDE_M = 1e-6  # rays start just outside the side they look away from
# Farther than this the free distance of a side no longer matters (the standoff rules).
_FAR_M = 1000.0

FloatArray = NDArray[np.float64]


def walk_around(
    site: Site,
    pallet_names: Sequence[str] | None = None,
    standoff_m: float = 1.0,
    *,
    clearance_m: float = PERSON_RADIUS_M + 0.1,
    merge_m: float = 1.2,
    start_xy_m: tuple[float, float] | None = None,
) -> list[Pose2D]:
    """Stops around ``pallet_names`` (default: every pallet of the site), in walking
    order from the stop nearest ``start_xy_m`` (default: the first stop found); each
    stop's yaw faces the (first) pallet side it was placed for."""
    if not (standoff_m > 0.0 and clearance_m >= 0.0 and merge_m >= 0.0):
        raise ValueError("standoff_m must be > 0, clearance_m and merge_m >= 0")
    pallets = _selected(site, pallet_names)
    shapes = site.static_shapes()
    spots: list[tuple[float, float, float]] = []
    for pallet in pallets:
        for nx, ny in _SIDES:
            spot = _side_spot(
                pallet, nx, ny, standoff_m, clearance_m, shapes.segments, shapes.circles
            )
            if spot is not None:
                spots.append(spot)
    stops = _merged(spots, merge_m, clearance_m, shapes.segments, shapes.circles)
    return _nearest_next(stops, start_xy_m)


def _selected(site: Site, names: Sequence[str] | None) -> tuple[SitePallet, ...]:
    if names is None:
        return site.pallets
    by_name = {p.name: p for p in site.pallets}
    missing = [n for n in names if n not in by_name]
    if missing:
        raise KeyError(f"site {site.name!r} has no pallet {missing[0]!r}")
    return tuple(by_name[n] for n in names)


def _side_spot(
    pallet: SitePallet,
    nx: float,
    ny: float,
    standoff_m: float,
    clearance_m: float,
    segments: FloatArray,
    circles: FloatArray,
) -> tuple[float, float, float] | None:
    """Where a worker stands to scan one side: along its outward normal from its middle,
    at the standoff or halfway to the next obstacle, if a body fits there."""
    half = pallet.length_m / 2.0 if nx else pallet.width_m / 2.0
    mx, my = pallet.pose.apply(nx * half, ny * half)
    yaw = pallet.pose.yaw_rad + math.atan2(ny, nx)
    ox, oy = mx + _OFF_THE_SIDE_M * math.cos(yaw), my + _OFF_THE_SIDE_M * math.sin(yaw)
    hits = nearest_hits(ox, oy, np.array([yaw]), segments, circles, _FAR_M)
    free_m = float(hits.ranges_m[0]) if hits.ranges_m[0] > 0.0 else math.inf
    distance_m = min(standoff_m, free_m / 2.0)
    if distance_m < clearance_m:
        return None
    x, y = mx + distance_m * math.cos(yaw), my + distance_m * math.sin(yaw)
    if not _clear(x, y, clearance_m, segments, circles):
        return None
    return x, y, math.remainder(yaw + math.pi, 2.0 * math.pi)  # facing the side


def _clear(
    x_m: float, y_m: float, clearance_m: float, segments: FloatArray, circles: FloatArray
) -> bool:
    """No shape nearer than ``clearance_m`` (a body's radius and a margin)."""
    if segments.shape[0] and point_segment_distance_m(x_m, y_m, segments).min() < clearance_m:
        return False
    if circles.shape[0]:
        gaps = np.hypot(circles[:, 0] - x_m, circles[:, 1] - y_m) - circles[:, 2]
        if gaps.min() < clearance_m:
            return False
    return True


def _merged(
    spots: list[tuple[float, float, float]],
    merge_m: float,
    clearance_m: float,
    segments: FloatArray,
    circles: FloatArray,
) -> list[Pose2D]:
    """Spots within ``merge_m`` of a stop's running mean join it; a stop stands at its
    spots' mean if a body fits there, else at its first spot (which fits)."""
    groups: list[list[tuple[float, float, float]]] = []
    means: list[tuple[float, float]] = []
    for spot in spots:
        for i, (gx, gy) in enumerate(means):
            if math.hypot(spot[0] - gx, spot[1] - gy) <= merge_m:
                groups[i].append(spot)
                count = len(groups[i])
                means[i] = (gx + (spot[0] - gx) / count, gy + (spot[1] - gy) / count)
                break
        else:
            groups.append([spot])
            means.append((spot[0], spot[1]))
    stops: list[Pose2D] = []
    for group, (gx, gy) in zip(groups, means, strict=True):
        first = group[0]
        if _clear(gx, gy, clearance_m, segments, circles):
            stops.append(Pose2D(gx, gy, first[2]))
        else:
            stops.append(Pose2D(*first))
    return stops


def _nearest_next(stops: list[Pose2D], start_xy_m: tuple[float, float] | None) -> list[Pose2D]:
    """The stops in the order a walker visiting the nearest unvisited one next takes."""
    if not stops:
        return []
    left = list(stops)
    x, y = start_xy_m if start_xy_m is not None else (left[0].x_m, left[0].y_m)
    route: list[Pose2D] = []
    while left:
        nearest = min(range(len(left)), key=lambda i: math.hypot(left[i].x_m - x, left[i].y_m - y))
        stop = left.pop(nearest)
        route.append(stop)
        x, y = stop.x_m, stop.y_m
    return route
