"""The core's part of `dbw status`: mode, reasons, faults and commands as plain data."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from appliance.core.output import describe_commands

if TYPE_CHECKING:
    from appliance.core.core import ControlCore


def core_status(self: ControlCore, now_s: float) -> dict[str, Any]:
    state = self.state
    out = self.last_output
    m = self._measured
    return {
        "mode": str(state.mode),
        "mode_since_s": None if self.mode_since_s is None else round(now_s - self.mode_since_s, 3),
        "set_speed_mps": state.set_speed_mps,
        "measured_speed_mps": None if m is None else m.speed_mps,
        "hold_to_move": {
            "required": self.config.engagement.hold_to_move,
            "held": state.hold_to_move_held,
        },
        "estop_latched": state.estop_latched,
        "last_refusal": list(self.last_refusal),
        "faults": [
            {"key": f.key, "detail": f.detail, "since_s": round(now_s - f.raised_s, 3)}
            for f in self.faults.active_faults.values()
        ]
        + [
            {
                "key": f.reason,
                "detail": "latched: press OVERRIDE once cleared",
                "since_s": round(now_s - f.since_s, 3),
            }
            for f in state.faults
            if f.reason not in self.faults.active_faults
        ],
        "fault_history": [
            {"key": r.key, "detail": r.detail, "raised_s": r.raised_s, "cleared_s": r.cleared_s}
            for r in self.faults.history[-20:]
        ],
        "overrides": {}
        if out is None
        else {
            "steering": out.operator.steering_override,
            "brake_pedal": out.operator.brake_pedal,
            "throttle_pedal": out.operator.throttle_pedal,
        },
        "commands": {} if out is None else describe_commands(out),
    }
