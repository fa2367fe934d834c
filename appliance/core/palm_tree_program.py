"""The palm tree driven by the daemon, on the core: armed by `dbw calibrate palm-tree --auto`.

While armed, the program (``appliance.guidance.palm_tree_drive``) is the autopilot source:
its wheel angle (where it aims the wheel now, on the way to the arc's) becomes a tyre
angle through the calibration file's own maps (so the
servo is aimed back at exactly that wheel angle), its speed target replaces the
operator's set speed in SPEED_HOLD. It has the vehicle only in SPEED_HOLD with the engage
button held (hold-to-move is a condition of arming it); anything else pauses it, and the
core's usual rules (the override, a brake tap, a fault, a stale input) apply as to any
source's wish.
"""

from __future__ import annotations

import math

from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.config.palm_tree_models import palm_tree_drive_problems
from appliance.core.wish import AutopilotWish
from appliance.guidance.palm_tree_drive import DriveCommand, PalmTreeDrive
from appliance.modes import Mode

# Standing, for arming: a GNSS/INS speed reads a few cm/s on a vehicle held by its brake.
STANDING_MPS = 0.3


class PalmTreeProgram:
    """One armed run of the program (see the module)."""

    def __init__(self, config: VehicleConfig, calibration: Calibration, first_arc: int) -> None:
        self.calibration = calibration
        params = config.palm_tree_drive.params(calibration.valid_wheel_range_rad)
        self.program = PalmTreeDrive(params)
        self.program.reset(first_arc)
        self.last: DriveCommand | None = None

    def wish(
        self,
        wheel_rad: float | None,
        speed_mps: float | None,
        now_s: float,
        in_control: bool,
        steering: bool,
    ) -> AutopilotWish:
        """``in_control``: the program has the vehicle; ``steering``: engaged at all."""
        command = self.program.update(wheel_rad, speed_mps, now_s, in_control, steering)
        self.last = command
        steer = self.calibration.tyre_rad_from_wheel(command.wheel_aim_rad)
        return AutopilotWish(
            ready=command.stuck is None,
            reason="" if command.stuck is None else f"palm tree: {command.stuck}",
            steer_tyre_rad=steer,
            max_speed_mps=command.speed_mps,
            speed_mps=command.speed_mps,
            status={"palm_tree": command.as_status()},
        )

    def held(self) -> AutopilotWish:
        """After the program ends engaged: the wheel where the program left it, standing,
        until the operator takes over (turning it back is the operator's call)."""
        last = self.last
        wheel = 0.0 if last is None else last.wheel_aim_rad
        return AutopilotWish(
            ready=True,
            steer_tyre_rad=self.calibration.tyre_rad_from_wheel(wheel),
            max_speed_mps=0.0,
            speed_mps=0.0,
            status={"palm_tree": {"phase": "ended"}},
        )


def palm_tree_refusal(
    config: VehicleConfig,
    calibration: Calibration | None,
    mode: Mode,
    speed_mps: float | None,
    arc_text: str,
) -> str | None:
    """Why the program may not be armed now (None: it may): allowed by the vehicle file,
    under hold-to-move, with a pot map to read and aim the wheel by, from READY, standing;
    a resumed one from one of its arcs."""
    problems = palm_tree_drive_problems(config.palm_tree_drive, config.limits, config.engagement)
    if problems:
        return "; ".join(problems)
    if calibration is None:
        return (
            "the palm tree reads and aims the wheel through the calibration file's pot map: "
            "run dbw calibrate pot-center and pot-map first"
        )
    arcs = config.palm_tree_drive.params(calibration.valid_wheel_range_rad).arcs
    if not (arc_text.isdigit() and int(arc_text) < arcs):
        return f"the palm tree resumes from an arc 0..{arcs - 1}, not {arc_text!r}"
    if mode is not Mode.READY:
        return f"the palm tree starts from READY, not {mode}"
    if speed_mps is None or not math.isfinite(speed_mps):
        return "the palm tree needs a measured speed (is the GNSS/INS fixed?)"
    if abs(speed_mps) > STANDING_MPS:
        return f"the palm tree starts standing (moving at {abs(speed_mps):.2f} m/s)"
    return None
