"""Planar poses: the one geometric type the device layer's data carries.

A scanner's mount in the vehicle frame is a pose (``drivers.lms111.mounted``), and so is
everything above it: the vehicle on its site, a landmark, a pallet, a target. One type for
all of them, at the bottom of the floor plan, means no layer converts another's poses and
no layer imports upward to get at them.
"""

from __future__ import annotations

import math
from typing import NamedTuple


class Pose2D(NamedTuple):
    """A planar pose: position in metres, heading in radians (counter-clockwise from x)."""

    x_m: float
    y_m: float
    yaw_rad: float

    def compose(self, other: Pose2D) -> Pose2D:
        """``other`` expressed in this pose's frame, returned in the parent frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return Pose2D(
            self.x_m + c * other.x_m - s * other.y_m,
            self.y_m + s * other.x_m + c * other.y_m,
            self.yaw_rad + other.yaw_rad,
        )

    def apply(self, x_m: float, y_m: float) -> tuple[float, float]:
        """A point given in this pose's frame, in the parent frame."""
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        return self.x_m + c * x_m - s * y_m, self.y_m + s * x_m + c * y_m
