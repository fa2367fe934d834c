"""One cycle's view of the vehicle: fresh measurements, e-stop, fault conditions.

Everything here reads :class:`ControlInputs` and the config and returns plain values;
nothing changes state except the small rule objects the core passes in. A measurement
is only used when its input is fresh (the staleness rule decides), and a measurement we
cannot convert (a pot reading outside the calibrated range, no calibration) is None:
nothing downstream may treat "unknown" as "zero".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from appliance.config.calibration import Calibration
from appliance.core.inputs import ControlInputs
from appliance.localization.gnss_pose import GnssNoFix, GnssPose, HeadingSource
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
    inputs: ControlInputs,
    fresh: frozenset[str],
    calibration: Calibration | None,
    *,
    speed_path: Literal["pc104", "pedals"] = "pc104",
    now_s: float = math.nan,
    gnss_max_age_s: float = 0.0,
) -> Measurements:
    """The cycle's measurements. On the ``pedals`` speed path the vehicle has no PC104:
    its status is not an input (no speed, source or readiness from it, whatever arrives)
    and the speed is the GNSS/INS epoch's (:func:`gnss_speed_mps`)."""
    steering = inputs.steering if {"board.steering", "steering.pot"} <= fresh else None
    wheel_rad = tyre_rad = None
    if steering is not None and calibration is not None:
        wheel_rad = calibration.wheel_rad_from_counts(steering.pot_raw_counts)
        tyre_rad = calibration.tyre_rad_from_counts(steering.pot_raw_counts)
    brake = inputs.brake if "board.brake" in fresh else None
    throttle = inputs.throttle if "board.throttle" in fresh else None
    pedals = speed_path == "pedals"
    status = inputs.pc104_status if "pc104.status" in fresh and not pedals else None
    if pedals:
        speed_mps = gnss_speed_mps(inputs.gnss, now_s, gnss_max_age_s)
    else:
        speed_mps = None if status is None else status.measured_speed_mps
    return Measurements(
        steer_tyre_rad=tyre_rad,
        steer_wheel_rad=wheel_rad,
        servo_position_rad=None if steering is None else steering.servo_position_rad,
        servo_torque_nm=0.0 if steering is None else steering.motor_torque_nm,
        speed_mps=speed_mps,
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


def gnss_speed_mps(
    gnss: GnssPose | GnssNoFix | None, now_s: float, max_age_s: float
) -> float | None:
    """The vehicle's speed from a GNSS/INS epoch, or None (unknown) unless it is fresh.

    Fresh: measured no more than ``max_age_s`` before ``now_s`` and not after it (an epoch
    from the future is a broken clock). Speed over ground is unsigned; it is made negative
    only when the receiver's true heading (HDT/THS) and its course over ground disagree
    by more than 90°, i.e. the vehicle is seen rolling backwards. Without a true heading
    (heading from the course, which assumes forward travel) it stays unsigned: the
    ``pedals`` path drives forward only and refuses any reverse wish, so a backwards roll
    it cannot see is one the operator is driving, not one it commands.
    """
    if not isinstance(gnss, GnssPose) or gnss.speed_mps is None:
        return None
    age_s = now_s - gnss.measurement_time_s
    if not (math.isfinite(age_s) and 0.0 <= age_s <= max_age_s):
        return None
    speed = gnss.speed_mps
    if not (math.isfinite(speed) and speed >= 0.0):
        return None
    course, yaw = gnss.course_yaw_rad, gnss.yaw_rad
    if (
        gnss.heading_source is HeadingSource.TRUE_HEADING
        and course is not None
        and yaw is not None
        and abs(math.remainder(course - yaw, math.tau)) > math.pi / 2.0
    ):
        return -speed
    return speed


def pedal_path_problems(
    m: Measurements, reverse_wished: bool, gnss_max_age_s: float
) -> dict[str, str]:
    """What stops the ``pedals`` speed path from controlling speed, by fault key.

    The core refuses engagement for each of them and, while under automatic control,
    raises them as faults: a speed loop without a speed, or asked to back up on a path
    that only drives forward, must not keep the vehicle moving.
    """
    problems: dict[str, str] = {}
    if m.speed_mps is None:
        problems["speed_unknown"] = (
            f"speed unknown: no GNSS/INS speed within {gnss_max_age_s * 1e3:.0f} ms"
        )
    if reverse_wished:
        problems["reverse_refused"] = (
            "autopilot asks to reverse: the pedals speed path drives forward only"
        )
    return problems


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
