"""Courses with exact geometry for the route tests: straight lines joined tangentially by
circular arcs, sampled every ``step_m`` along the path, and the exact distance of any point
from them (written out here, not taken from the code under test)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ArcCourse:
    """Straight ``lead_m`` east from the origin, a left arc of ``radius_m`` through
    ``turn_deg``, then straight ``tail_m`` on the new heading."""

    radius_m: float
    turn_deg: float = 90.0
    lead_m: float = 20.0
    tail_m: float = 20.0

    @property
    def arc_m(self) -> float:
        return self.radius_m * math.radians(self.turn_deg)

    @property
    def length_m(self) -> float:
        return self.lead_m + self.arc_m + self.tail_m

    @property
    def centre_m(self) -> tuple[float, float]:
        return self.lead_m, self.radius_m

    def at(self, s_m: float) -> tuple[float, float]:
        """The point ``s_m`` along the course."""
        if s_m <= self.lead_m:
            return s_m, 0.0
        cx, cy = self.centre_m
        if s_m <= self.lead_m + self.arc_m:
            angle = (s_m - self.lead_m) / self.radius_m
            return cx + self.radius_m * math.sin(angle), cy - self.radius_m * math.cos(angle)
        turn = math.radians(self.turn_deg)
        ex, ey = cx + self.radius_m * math.sin(turn), cy - self.radius_m * math.cos(turn)
        along = s_m - self.lead_m - self.arc_m
        return ex + along * math.cos(turn), ey + along * math.sin(turn)

    def points(self, step_m: float) -> FloatArray:
        count = round(self.length_m / step_m)
        return np.array([self.at(k * self.length_m / count) for k in range(count + 1)])

    def distance_m(self, x: float, y: float) -> float:
        """Exact distance from (x, y) to the course."""
        lead = math.hypot(x - min(max(x, 0.0), self.lead_m), y)
        cx, cy = self.centre_m
        turn = math.radians(self.turn_deg)
        angle = math.atan2(x - cx, -(y - cy))  # 0 at the arc's start, growing along it
        if 0.0 <= angle <= turn:
            arc = abs(math.hypot(x - cx, y - cy) - self.radius_m)
        else:
            arc = min(
                math.dist((x, y), self.at(self.lead_m)),
                math.dist((x, y), self.at(self.lead_m + self.arc_m)),
            )
        ex, ey = self.at(self.lead_m + self.arc_m)
        dx, dy = math.cos(turn), math.sin(turn)
        along = min(max((x - ex) * dx + (y - ey) * dy, 0.0), self.tail_m)
        tail = math.hypot(x - ex - along * dx, y - ey - along * dy)
        return min(lead, arc, tail)
