"""What one control cycle produces: a command per actuator path, and notes to log.

Kept apart from the core so that the control loop, the sinks and the status view can
depend on the output without depending on the rules that made it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from appliance.modes import AUTOMATIC_MODES, Mode
from drivers.actuators.messages import (
    BrakeCommand,
    PanelCommand,
    SteeringCommand,
    SteeringMode,
    ThrottleCommand,
)
from drivers.pc104.messages import HighLevelState, HlExpectedPose, HlPose, MotionCommand
from safety.arbitration import OperatorInput

SAFE_MODES = frozenset({Mode.BOOT, Mode.SELF_CHECK, Mode.ERROR, Mode.ESTOP})


@dataclass(frozen=True)
class Note:
    """Something the loop should log once: an event name and its fields."""

    event: str
    fields: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class CoreOutput:
    now_s: float
    mode: Mode
    steering: SteeringCommand
    throttle: ThrottleCommand
    brake: BrakeCommand
    panel: PanelCommand
    pc104: MotionCommand
    hl_state: HighLevelState
    operator: OperatorInput
    steer_tyre_rad: float | None  # what steering was commanded (tyre angle), None: released
    speed_setpoint_mps: float | None  # None: PC104 told STOP
    notes: tuple[Note, ...] = ()
    # For a PC104 that steers on pose: the estimate, and where the plan goes (engaged only).
    pc104_pose: HlPose | None = None
    pc104_expected_pose: HlExpectedPose | None = None

    @property
    def engaged(self) -> bool:
        return self.mode in AUTOMATIC_MODES

    @property
    def safe(self) -> bool:
        return self.mode in SAFE_MODES


def hl_state(mode: Mode) -> HighLevelState:
    if mode in AUTOMATIC_MODES:
        return HighLevelState.ENGAGED
    if mode in (Mode.ERROR, Mode.ESTOP):
        return HighLevelState.FAULT
    if mode is Mode.READY:
        return HighLevelState.STANDBY
    return HighLevelState.INIT


def printable(text: str) -> str:
    return "".join(c if " " <= c <= "~" else "?" for c in text)


def describe_commands(out: CoreOutput) -> dict[str, str]:
    steering = out.steering
    pc104 = out.pc104
    return {
        "steering": "released"
        if steering.mode is SteeringMode.RELEASE
        else f"{steering.mode.name.lower()} servo {steering.wheel_angle_setpoint_rad:+.3f} rad"
        + (
            ""
            if out.steer_tyre_rad is None
            else f", tyre {math.degrees(out.steer_tyre_rad):+.2f} deg"
        ),
        "throttle": "released" if not out.throttle.enable else f"{out.throttle.position_pct:.1f} %",
        "brake": f"applied {out.brake.position_pct:.1f} %" if out.brake.enable else "released",
        "pc104": "STOP"
        if pc104.pattern.value == "stop"
        else f"{pc104.pattern.value} {pc104.speed_mps:.2f} m/s"
        f" front {math.degrees(pc104.front_steer_rad):+.2f} deg",
        "lamps": str(out.panel.lamps.name or "none").lower(),
        "display": out.panel.display_text,
        "heartbeat": str(out.hl_state),
    }
