"""The contract as the code uses it: ``pc104.dbc`` loaded once, and the typed messages'
mapping to its signals.

Identifiers, lengths, periods (``GenMsgCycleTime``), scaling, ranges and the enum codes
(``VAL_`` tables, matched to the Python enums by member name) all come from the DBC. The
module refuses to import if the DBC breaks a rule the code relies on: the counter in bits
4-7 of byte 0, the CRC in the last byte, standard identifiers, a cycle time, value tables
that match the enums. A DBC edit that breaks the framing fails at start-up, not on the
vehicle.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any, TypeVar

import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from drivers.pc104.messages import (
    ControlSource,
    HighLevelState,
    HlExpectedPose,
    HlHeartbeat,
    HlPose,
    Inclinometer,
    Message,
    MotionCommand,
    MotionPattern,
    MotorPulses,
    Pc104Faults,
    Pc104Heartbeat,
    Pc104State,
    Pc104Status,
    PoseState,
    SteeringLoop,
    WheelAngles,
)

DBC_PATH = Path(__file__).with_name("pc104.dbc")


def _load_database() -> Database:
    db = cantools.database.load_file(DBC_PATH, strict=True)
    if not isinstance(db, Database):  # pragma: no cover - a .dbc is always a CAN database
        raise TypeError(f"{DBC_PATH} is not a CAN database")
    return db


DATABASE = _load_database()
E = TypeVar("E", bound=Enum)


def _codes(message: str, signal: str, enum_cls: type[E]) -> tuple[dict[E, int], dict[int, E]]:
    """Enum <-> wire code from the DBC's VAL_ table, matched by member name."""
    choices: Mapping[Any, Any] = (
        DATABASE.get_message_by_name(message).get_signal_by_name(signal).choices or {}
    )
    from_code = {int(code): enum_cls[str(name)] for code, name in choices.items()}
    if set(from_code.values()) != set(enum_cls):
        raise RuntimeError(f"{DBC_PATH}: VAL_ of {message}.{signal} does not match {enum_cls}")
    return {member: code for code, member in from_code.items()}, from_code


_PATTERN_TO_CODE, _CODE_TO_PATTERN = _codes("HL_MotionCommand", "MotionPattern", MotionPattern)
if _codes("PC104_Status", "ActivePattern", MotionPattern)[0] != _PATTERN_TO_CODE:
    raise RuntimeError(f"{DBC_PATH}: ActivePattern and MotionPattern have different codes")
_SOURCE_TO_CODE, _CODE_TO_SOURCE = _codes("PC104_Status", "ControlSource", ControlSource)
_HL_STATE_TO_CODE, _CODE_TO_HL_STATE = _codes("HL_Heartbeat", "State", HighLevelState)
_PC_STATE_TO_CODE, _CODE_TO_PC_STATE = _codes("PC104_Heartbeat", "State", Pc104State)
_POSE_STATE_TO_CODE, _CODE_TO_POSE_STATE = _codes("HL_Pose", "PoseState", PoseState)
_LOOP_TO_CODE, _CODE_TO_LOOP = _codes("HL_ExpectedPose", "SteeringLoop", SteeringLoop)

Signals = dict[str, float]
_FAULT_SIGNALS = {
    "command_timeout": "FaultCommandTimeout",
    "command_invalid": "FaultCommandInvalid",
    "hydraulic": "FaultHydraulic",
    "steering": "FaultSteering",
    "encoder": "FaultEncoder",
    "inclinometer": "FaultInclinometer",
    "motor_pulses": "FaultMotorPulses",
    "pose": "FaultPose",
}
_ROWS = range(1, 5)


def _command_signals(m: MotionCommand) -> Signals:
    return {
        "MotionPattern": _PATTERN_TO_CODE[m.pattern],
        "LevelPlatform": int(m.level_platform),
        "SpeedSetpoint": m.speed_mps,
        "FrontSteerSetpoint": m.front_steer_rad,
        "RearSteerSetpoint": m.rear_steer_rad,
    }


def _command(s: Mapping[str, float]) -> MotionCommand:
    return MotionCommand(
        pattern=_CODE_TO_PATTERN[int(s["MotionPattern"])],
        speed_mps=s["SpeedSetpoint"],
        front_steer_rad=s["FrontSteerSetpoint"],
        rear_steer_rad=s["RearSteerSetpoint"],
        level_platform=bool(s["LevelPlatform"]),
    )


def _pose_signals(m: HlPose) -> Signals:
    return {
        "PoseState": _POSE_STATE_TO_CODE[m.state],
        "PoseX": m.x_m,
        "PoseY": m.y_m,
        "PoseYaw": m.yaw_rad,
    }


def _pose(s: Mapping[str, float]) -> HlPose:
    state = _CODE_TO_POSE_STATE[int(s["PoseState"])]
    return HlPose(s["PoseX"], s["PoseY"], s["PoseYaw"], state)


def _expected_signals(m: HlExpectedPose) -> Signals:
    return {
        "SteeringLoop": _LOOP_TO_CODE[m.loop],
        "ExpectedX": m.x_m,
        "ExpectedY": m.y_m,
        "ExpectedYaw": m.yaw_rad,
    }


def _expected(s: Mapping[str, float]) -> HlExpectedPose:
    loop = _CODE_TO_LOOP[int(s["SteeringLoop"])]
    return HlExpectedPose(s["ExpectedX"], s["ExpectedY"], s["ExpectedYaw"], loop)


def _status_signals(m: Pc104Status) -> Signals:
    signals: Signals = {
        "ActivePattern": _PATTERN_TO_CODE[m.active_pattern],
        "Ready": int(m.ready),
        "ControlSource": _SOURCE_TO_CODE[m.control_source],
        "PlatformLeveling": int(m.platform_leveling),
        "EmergencyStop": int(m.emergency_stop),
        "StopRequired": int(m.stop_required),
        "MeasuredSpeed": m.measured_speed_mps,
        "BadCommandFrames": m.bad_command_frames,
    }
    for field, name in _FAULT_SIGNALS.items():
        signals[name] = int(getattr(m.faults, field))
    return signals


def _status(s: Mapping[str, float]) -> Pc104Status:
    return Pc104Status(
        active_pattern=_CODE_TO_PATTERN[int(s["ActivePattern"])],
        ready=bool(s["Ready"]),
        control_source=_CODE_TO_SOURCE[int(s["ControlSource"])],
        platform_leveling=bool(s["PlatformLeveling"]),
        emergency_stop=bool(s["EmergencyStop"]),
        stop_required=bool(s["StopRequired"]),
        faults=Pc104Faults(**{f: bool(s[name]) for f, name in _FAULT_SIGNALS.items()}),
        measured_speed_mps=s["MeasuredSpeed"],
        bad_command_frames=int(s["BadCommandFrames"]),
    )


def _wheel_signals(m: WheelAngles) -> Signals:
    signals: Signals = {}
    for row, angle, valid in zip(_ROWS, m.row_angles_rad, m.row_valid, strict=True):
        signals[f"Row{row}Angle"] = angle
        signals[f"Row{row}Valid"] = int(valid)
    return signals


def _wheels(s: Mapping[str, float]) -> WheelAngles:
    a = [s[f"Row{row}Angle"] for row in _ROWS]
    v = [bool(s[f"Row{row}Valid"]) for row in _ROWS]
    return WheelAngles((a[0], a[1], a[2], a[3]), (v[0], v[1], v[2], v[3]))


_PULSE_SIGNALS = {
    "front_left_counts": "FrontLeftPulses",
    "front_right_counts": "FrontRightPulses",
    "rear_left_counts": "RearLeftPulses",
    "rear_right_counts": "RearRightPulses",
}


def _pulse_signals(m: MotorPulses) -> Signals:
    return {name: getattr(m, field) for field, name in _PULSE_SIGNALS.items()}


def _pulses(s: Mapping[str, float]) -> MotorPulses:
    return MotorPulses(**{field: int(s[name]) for field, name in _PULSE_SIGNALS.items()})


def _incl_signals(m: Inclinometer) -> Signals:
    return {"Pitch": m.pitch_rad, "Roll": m.roll_rad, "InclinometerValid": int(m.valid)}


def _incl(s: Mapping[str, float]) -> Inclinometer:
    return Inclinometer(s["Pitch"], s["Roll"], bool(s["InclinometerValid"]))


def _hl_beat_signals(m: HlHeartbeat) -> Signals:
    return {"State": _HL_STATE_TO_CODE[m.state], "ProtocolVersion": m.protocol_version}


def _hl_beat(s: Mapping[str, float]) -> HlHeartbeat:
    return HlHeartbeat(_CODE_TO_HL_STATE[int(s["State"])], int(s["ProtocolVersion"]))


def _pc_beat_signals(m: Pc104Heartbeat) -> Signals:
    return {
        "State": _PC_STATE_TO_CODE[m.state],
        "ProtocolVersion": m.protocol_version,
        "Uptime": m.uptime_s,
    }


def _pc_beat(s: Mapping[str, float]) -> Pc104Heartbeat:
    return Pc104Heartbeat(
        _CODE_TO_PC_STATE[int(s["State"])], int(s["Uptime"]), int(s["ProtocolVersion"])
    )


@dataclass(frozen=True)
class MessageSpec:
    """One message of the contract as the code uses it."""

    name: str
    frame_id: int
    length: int
    period_s: float
    dbc: DbcMessage
    to_signals: Callable[[Any], Signals]
    from_signals: Callable[[Mapping[str, float]], Message]


def _spec(name: str, to: Callable[[Any], Signals], frm: Callable[..., Message]) -> MessageSpec:
    dbc = DATABASE.get_message_by_name(name)
    counter, crc = dbc.get_signal_by_name("Counter"), dbc.get_signal_by_name("CRC")
    framing_ok = (counter.start, counter.length, crc.start, crc.length) == (
        4,
        4,
        8 * (dbc.length - 1),
        8,
    )
    if not framing_ok or dbc.is_extended_frame or not dbc.cycle_time:
        raise RuntimeError(f"{DBC_PATH}: {name} breaks the framing rules this code relies on")
    return MessageSpec(name, dbc.frame_id, dbc.length, dbc.cycle_time / 1000.0, dbc, to, frm)


SPECS: dict[type, MessageSpec] = {
    MotionCommand: _spec("HL_MotionCommand", _command_signals, _command),
    HlHeartbeat: _spec("HL_Heartbeat", _hl_beat_signals, _hl_beat),
    HlPose: _spec("HL_Pose", _pose_signals, _pose),
    HlExpectedPose: _spec("HL_ExpectedPose", _expected_signals, _expected),
    Pc104Status: _spec("PC104_Status", _status_signals, _status),
    WheelAngles: _spec("PC104_WheelAngles", _wheel_signals, _wheels),
    MotorPulses: _spec("PC104_MotorPulses", _pulse_signals, _pulses),
    Inclinometer: _spec("PC104_Inclinometer", _incl_signals, _incl),
    Pc104Heartbeat: _spec("PC104_Heartbeat", _pc_beat_signals, _pc_beat),
}
SPECS_BY_ID: dict[int, MessageSpec] = {spec.frame_id: spec for spec in SPECS.values()}
HL_IDS = frozenset(SPECS[t].frame_id for t in (MotionCommand, HlHeartbeat, HlPose, HlExpectedPose))
PC104_IDS = frozenset(SPECS_BY_ID) - HL_IDS


def spec_for(message_type: type) -> MessageSpec:
    return SPECS[message_type]
