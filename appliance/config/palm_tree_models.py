"""The vehicle file's ``[palm_tree_drive]``: whether, and how, the daemon drives the palm tree.

Off by default: a program steering to full lock and driving arcs is something a vehicle's
owner allows knowingly, and only with hold-to-move (the operator beside the vehicle, the
engage button held, letting go stops it). In the vehicle file, like ``[pedal_sweep]``,
because the daemon runs the program and a recording's replay must run the same one.
"""

from __future__ import annotations

import math

from pydantic import BaseModel, ConfigDict, Field

from appliance.config.pedal_models import _Engagement, _Limits
from appliance.guidance.palm_tree_drive import PalmTreeDriveParams, half_turn_targets

HALF_TURN_RAD = math.pi
# Kept inside the pot map's valid range by this many tolerances: a wheel aimed at the
# range's very end may settle just outside it, where the pot reads nothing valid.
END_MARGIN_TOLERANCES = 2.0


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


class PalmTreeDriveSettings(_Model):
    allowed: bool = False
    # Walking pace: the operator walks beside it, holding the engage button.
    speed_mps: float = Field(1.0, gt=0.0, le=2.0)
    # Per half turn; the fit wants 8 m of arc at least (its curvature precision).
    arc_m: float = Field(10.0, ge=8.0, le=50.0)
    wheel_tolerance_rad: float = Field(0.05, gt=0.0, le=0.5)
    # The wheel turned standing at a hand's pace (the steering-tracking rule's 3 deg and
    # the servo's lag allow about 6 rad/s of wheel on the simulated Husky; a dry-steered
    # linkage is spared the rest).
    steer_rate_rad_per_s: float = Field(2.0, gt=0.0, le=10.0)
    settle_s: float = Field(1.0, ge=0.0, le=10.0)
    steer_timeout_s: float = Field(20.0, gt=1.0, le=120.0)

    def params(self, wheel_range_rad: tuple[float, float]) -> PalmTreeDriveParams:
        """The program over the calibration's valid wheel range (its pot map's)."""
        margin = END_MARGIN_TOLERANCES * self.wheel_tolerance_rad
        low, high = wheel_range_rad
        return PalmTreeDriveParams(
            wheel_targets_rad=half_turn_targets(low + margin, high - margin, HALF_TURN_RAD),
            arc_m=self.arc_m,
            speed_mps=self.speed_mps,
            wheel_tolerance_rad=self.wheel_tolerance_rad,
            steer_rate_rad_per_s=self.steer_rate_rad_per_s,
            settle_s=self.settle_s,
            steer_timeout_s=self.steer_timeout_s,
        )


def palm_tree_drive_problems(
    drive: PalmTreeDriveSettings, limits: _Limits, engagement: _Engagement
) -> list[str]:
    """Why the vehicle file's palm-tree program may not run (empty: it may)."""
    problems = []
    if not drive.allowed:
        problems.append(
            "the vehicle file does not allow the palm tree driven by the daemon "
            "([palm_tree_drive] allowed = true); drive it by hand"
        )
    if not engagement.hold_to_move:
        problems.append(
            "the palm tree is driven by the daemon only under hold-to-move "
            "(engagement.hold_to_move = true)"
        )
    cap = min(limits.max_speed_mps, engagement.max_set_speed_mps)
    if drive.speed_mps > cap:
        problems.append(
            f"palm_tree_drive.speed_mps {drive.speed_mps} is past the set speed's limit "
            f"({cap:.2f} m/s)"
        )
    return problems
