"""What the localizer knows of the launcher: where its landmarks are, in its own frame.

The launcher frame is Qian et al.'s Fig. 7 "global coordinates fixed on the launcher":
origin at the centre of the front board's face, +x along the launcher's axis pointing
into it (the heading of a docked vehicle), +y to the left of a vehicle facing the board.
So the front board is the line x = 0 between y = ±half its width, and a vehicle in front
of it has x < 0. The map is data: the same numbers the simulated site is built from
(``appliance.sim.builders.LauncherSpec``), handed down by the runtime, since this layer
may not import the simulator above it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class CylinderLandmark:
    name: str
    x_m: float
    y_m: float
    radius_m: float


@dataclass(frozen=True)
class LauncherMap:
    """The launcher's landmarks. Defaults are the built-in site's (``sites/launcher.toml``)."""

    front_board_width_m: float = 3.0
    side_board_length_m: float = 0.8
    side_board_sweep_deg: float = 45.0
    cylinder_radius_m: float = 0.15
    cylinder_lateral_m: float = 2.5
    cylinder_ahead_m: float = 0.5

    def __post_init__(self) -> None:
        for name in ("front_board_width_m", "side_board_length_m", "cylinder_radius_m"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")

    @property
    def half_width_m(self) -> float:
        return self.front_board_width_m / 2.0

    @property
    def cylinders(self) -> tuple[CylinderLandmark, CylinderLandmark]:
        return (
            CylinderLandmark(
                "cylinder_left",
                -self.cylinder_ahead_m,
                self.cylinder_lateral_m,
                self.cylinder_radius_m,
            ),
            CylinderLandmark(
                "cylinder_right",
                -self.cylinder_ahead_m,
                -self.cylinder_lateral_m,
                self.cylinder_radius_m,
            ),
        )

    def side_board_far_end(self, side: float) -> tuple[float, float]:
        """The free end of a side board (``side`` +1 left, -1 right), hinged at the corner."""
        sweep = math.radians(self.side_board_sweep_deg)
        return (
            self.side_board_length_m * math.sin(sweep),
            side * (self.half_width_m + self.side_board_length_m * math.cos(sweep)),
        )
