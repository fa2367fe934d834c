"""The core's part of `dbw status`: mode, reasons, faults and commands as plain data.

Built from what the core holds, handed over piece by piece, so this module depends on the
pieces' types and not on the core that owns them.
"""

from __future__ import annotations

from typing import Any

from appliance.core.autopilot import AutopilotWish
from appliance.core.observe import Measurements
from appliance.core.output import CoreOutput, describe_commands
from appliance.modes import ModeState
from safety.faults import FaultMonitor


def core_status(
    *,
    state: ModeState,
    mode_since_s: float | None,
    measured: Measurements | None,
    hold_to_move_required: bool,
    last_refusal: tuple[str, ...],
    engage_blockers: tuple[str, ...],
    faults: FaultMonitor,
    last_output: CoreOutput | None,
    now_s: float,
    autopilot_name: str = "",
    last_wish: AutopilotWish | None = None,
) -> dict[str, Any]:
    out = last_output
    m = measured
    return {
        "mode": str(state.mode),
        "mode_since_s": None if mode_since_s is None else round(now_s - mode_since_s, 3),
        "set_speed_mps": state.set_speed_mps,
        "measured_speed_mps": None if m is None else m.speed_mps,
        "hold_to_move": {
            "required": hold_to_move_required,
            "held": state.hold_to_move_held,
        },
        "estop_latched": state.estop_latched,
        "last_refusal": list(last_refusal),
        "engage_blockers": list(engage_blockers),
        "faults": [
            {"key": f.key, "detail": f.detail, "since_s": round(now_s - f.raised_s, 3)}
            for f in faults.active_faults.values()
        ]
        + [
            {
                "key": f.reason,
                "detail": "latched: press OVERRIDE once cleared",
                "since_s": round(now_s - f.since_s, 3),
            }
            for f in state.faults
            if f.reason not in faults.active_faults
        ],
        "fault_history": [
            {"key": r.key, "detail": r.detail, "raised_s": r.raised_s, "cleared_s": r.cleared_s}
            for r in faults.history[-20:]
        ],
        "overrides": {}
        if out is None
        else {
            "steering": out.operator.steering_override,
            "brake_pedal": out.operator.brake_pedal,
            "throttle_pedal": out.operator.throttle_pedal,
        },
        "commands": {} if out is None else describe_commands(out),
        "autopilot": {
            "source": autopilot_name,
            "ready": None if last_wish is None else last_wish.ready,
            "reason": "" if last_wish is None else last_wish.reason,
            **({} if last_wish is None else dict(last_wish.status)),
        },
    }
