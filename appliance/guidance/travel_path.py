"""The route as the vehicle drives it: in travel order, prepared once per route and direction.

The planner projects onto the route in its own order; the tracker and the speed profile
read the route in the direction it is driven. Both directions are whole paths made once
(the first time each is driven), so a control cycle maps the planner's arc length to a
point on the travel path with one table search, instead of cutting a window out of the
route and measuring it again every cycle. Nothing here depends on the vehicle's pose or
on the local/global transform: the follower works in the route's frame (a rigid
transform moves the vehicle, not the route), so what is made here stays true for as
long as the route does.

The local window of Fig. 6 (the route from a few metres behind the projection to some
metres ahead, in travel order) is still given, when asked for (``window``): for status
and tests, not for the cycle.
"""

from __future__ import annotations

import bisect
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from appliance.guidance.path_geometry import PathProjection, Polyline

FloatArray = NDArray[np.float64]


class TravelDirection(StrEnum):
    FORWARD = "forward"  # in the order of the route's points
    REVERSE = "reverse"


class TravelPaths:
    """One cleaned route (no zero-length segments) in both travel directions.

    Immutable once made: a new route is a new ``TravelPaths``, so whatever was derived
    from one (the paths, a speed table) can be checked against it by identity.
    """

    def __init__(self, route_m: FloatArray, segment_m: FloatArray, cum_s: FloatArray) -> None:
        """``segment_m`` and ``cum_s``: the planner's segment lengths and arc lengths."""
        self.route_m = route_m
        self.cum_s = cum_s
        self.length_m = float(cum_s[-1])
        self._cum_list: list[float] = cum_s.tolist()
        self._segment_list: list[float] = segment_m.tolist()
        self._xy_list: list[list[float]] = route_m.tolist()
        self._paths: dict[TravelDirection, Polyline] = {}

    def path(self, direction: TravelDirection) -> Polyline:
        """The whole route in travel order (made at the first request)."""
        path = self._paths.get(direction)
        if path is None:
            forward = direction is TravelDirection.FORWARD
            points = self.route_m if forward else self.route_m[::-1]
            path = self._paths[direction] = Polyline.from_points(points)
            path.prepare()
        return path

    def projection(self, direction: TravelDirection, progress_m: float) -> PathProjection:
        """The point ``progress_m`` along the travel path (the planner's progress)."""
        return self.path(direction).projection_at_arc(progress_m)

    def window(
        self, s: float, direction: TravelDirection, behind_m: float, ahead_m: float
    ) -> tuple[FloatArray, int, float]:
        """The route from ``behind_m`` behind the route arc length ``s`` to ``ahead_m``
        ahead, in travel order (clipped at the ends), and the projection within it."""
        total = self.length_m
        if direction is TravelDirection.FORWARD:
            s_lo, s_hi = max(0.0, s - behind_m), min(total, s + ahead_m)
        else:
            s_lo, s_hi = max(0.0, s - ahead_m), min(total, s + behind_m)
        eps = 1e-9
        inner_lo = bisect.bisect_right(self._cum_list, s_lo + eps)
        inner_hi = bisect.bisect_left(self._cum_list, s_hi - eps)
        path = np.empty((inner_hi - inner_lo + 2, 2))
        path[0] = self._point_at(s_lo)
        path[1:-1] = self.route_m[inner_lo:inner_hi]
        path[-1] = self._point_at(s_hi)
        arcs = np.concatenate(([s_lo], self.cum_s[inner_lo:inner_hi], [s_hi]))
        if direction is TravelDirection.REVERSE:
            path, arcs = path[::-1].copy(), s_hi - arcs[::-1]
            travelled = s_hi - s
        else:
            arcs, travelled = arcs - s_lo, s - s_lo
        k = int(arcs.searchsorted(travelled, side="right")) - 1
        k = min(max(k, 0), len(path) - 2)
        span = arcs[k + 1] - arcs[k]
        local_fraction = min(max((travelled - arcs[k]) / span, 0.0), 1.0) if span > 0 else 0.0
        path.flags.writeable = False
        return path, k, float(local_fraction)

    def _point_at(self, s: float) -> tuple[float, float]:
        cum = self._cum_list
        i = min(max(bisect.bisect_right(cum, s) - 1, 0), len(cum) - 2)
        f = min(max((s - cum[i]) / self._segment_list[i], 0.0), 1.0)
        (ax, ay), (bx, by) = self._xy_list[i], self._xy_list[i + 1]
        return ax + f * (bx - ax), ay + f * (by - ay)
