"""One cycle's view of the vehicle: fresh measurements, e-stop, fault conditions.

Everything here reads :class:`ControlInputs` and the config and returns plain values;
nothing changes state except the small rule objects the core passes in. A measurement
is only used when its input is fresh (the staleness rule decides), and a measurement we
cannot convert (a pot reading outside the calibrated range, no calibration) is None:
nothing downstream may treat "unknown" as "zero".
"""

from __future__ import annotations

from dataclasses import dataclass

from appliance.config.calibration import Calibration
from appliance.core.inputs import ControlInputs
from drivers.actuators.messages import BoardStatus, Buttons, FaultCode
from drivers.pc104.messages import ControlSource

# Board fault codes that are states we cause or expect rather than hardware faults: a
# board latches on power-on and on command timeouts until we release it, and the e-stop
# has its own path.
NON_HARDWARE_FAULTS = frozenset({FaultCode.NONE, FaultCode.COMMAND_TIMEOUT, FaultCode.ESTOP})


@dataclass(frozen=True)
class Measurements:
    """Fresh, converted measurements; None where unknown."""

    steer_tyre_rad: float | None
    steer_wheel_rad: float | None
    servo_position_rad: float | None
    servo_torque_nm: float
    speed_mps: float | None
    brake_pedal_pct: float | None
    brake_actuator_pct: float
    throttle_pedal_pct: float | None
    throttle_actuator_pct: float
    estop_reasons: tuple[str, ...]
    pc104_source: ControlSource | None
    pc104_ready: bool
    # The panel is fresh: its e-stop button's state is seen, not assumed. An e-stop is
    # reset only on a release seen; a silent panel's last word may be the mushroom down.
    panel_fresh: bool = False


def measure(
    inputs: ControlInputs, fresh: frozenset[str], calibration: Calibration | None
) -> Measurements:
    steering = inputs.steering if {"board.steering", "steering.pot"} <= fresh else None
    wheel_rad = tyre_rad = None
    if steering is not None and calibration is not None:
        wheel_rad = calibration.wheel_rad_from_counts(steering.pot_raw_counts)
        tyre_rad = calibration.tyre_rad_from_counts(steering.pot_raw_counts)
    brake = inputs.brake if "board.brake" in fresh else None
    throttle = inputs.throttle if "board.throttle" in fresh else None
    status = inputs.pc104_status if "pc104.status" in fresh else None
    return Measurements(
        steer_tyre_rad=tyre_rad,
        steer_wheel_rad=wheel_rad,
        servo_position_rad=None if steering is None else steering.servo_position_rad,
        servo_torque_nm=0.0 if steering is None else steering.motor_torque_nm,
        speed_mps=None if status is None else status.measured_speed_mps,
        brake_pedal_pct=None if brake is None else brake.pedal_position_pct,
        brake_actuator_pct=0.0 if brake is None else brake.actuator_position_pct,
        throttle_pedal_pct=None if throttle is None else throttle.pedal_position_pct,
        throttle_actuator_pct=0.0 if throttle is None else throttle.actuator_position_pct,
        estop_reasons=estop_reasons(inputs),
        pc104_source=None if status is None else status.control_source,
        # A PC104 that reports it does not hear our commands is not ready to follow them.
        pc104_ready=status is not None and status.ready and not status.faults.command_timeout,
        panel_fresh="board.panel" in fresh,
    )


def estop_reasons(inputs: ControlInputs) -> tuple[str, ...]:
    """Every e-stop signal we can see, fresh or not: an old e-stop is still an e-stop."""
    reasons: list[str] = []
    if inputs.panel is not None and inputs.panel.buttons_down & Buttons.ESTOP:
        reasons.append("panel e-stop button")
    for name, telemetry in (
        ("steering", inputs.steering),
        ("throttle", inputs.throttle),
        ("brake", inputs.brake),
        ("panel", inputs.panel),
    ):
        if telemetry is not None and telemetry.status & BoardStatus.ESTOP:
            reasons.append(f"e-stop loop open at the {name} board")
    if inputs.pc104_status is not None and inputs.pc104_status.emergency_stop:
        reasons.append("PC104 emergency stop")
    return tuple(dict.fromkeys(reasons))


def board_faults(inputs: ControlInputs, steering_engaged: bool) -> dict[str, str]:
    """Hardware faults the boards report; a latched steering board while we steer."""
    faults: dict[str, str] = {}
    for name, telemetry in (
        ("steering", inputs.steering),
        ("throttle", inputs.throttle),
        ("brake", inputs.brake),
        ("panel", inputs.panel),
    ):
        if telemetry is None:
            continue
        if telemetry.fault not in NON_HARDWARE_FAULTS:
            faults[f"board.{name}:{telemetry.fault.name.lower()}"] = (
                f"{name} board reports {telemetry.fault.name}"
            )
    steering = inputs.steering
    if steering_engaged and steering is not None and steering.status & BoardStatus.LATCHED:
        faults["board.steering:latched"] = (
            f"steering board latched in its safe default ({steering.fault.name}) while steering"
        )
    return faults


def pc104_faults(
    inputs: ControlInputs, fresh: frozenset[str], actuating: bool = True
) -> dict[str, str]:
    """What the PC104 reports; its command timeout only while we are actuating.

    A PC104 that has not heard from us says so (``command_timeout``) until our first
    commands arrive: on every boot, before the link is up. That is the boards'
    COMMAND_TIMEOUT, not a hardware fault; while we steer or hold speed it means our
    commands are not getting through, and then it is one.
    """
    status = inputs.pc104_status if "pc104.status" in fresh else None
    if status is None or not status.faults.any:
        return {}
    names = [
        name
        for name in status.faults.__dataclass_fields__
        if getattr(status.faults, name) and (actuating or name != "command_timeout")
    ]
    if not names:
        return {}
    return {"pc104:faults": "PC104 reports " + ", ".join(names)}
