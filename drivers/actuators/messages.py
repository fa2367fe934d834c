"""The messages of the actuator boards (docs/protocols/actuator-boards.md), in SI units.

Each message is a frozen dataclass whose fields carry their unit in their name; the wire
holds fixed-point integers (``_urad``, ``_mNm``, ``_cpct``), converted here and nowhere
else. Encoding checks ranges, so an out-of-range or NaN command raises
:class:`ActuatorProtocolError` instead of reaching a board; decoding checks lengths, enums
and reserved bits, so a frame we do not fully understand is refused, never half-used.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag, StrEnum
from typing import Final

from drivers.actuators.framing import ActuatorProtocolError


class BoardKind(StrEnum):
    STEERING = "steering"
    THROTTLE = "throttle"
    BRAKE = "brake"
    PANEL = "panel"


class SteeringMode(IntEnum):
    RELEASE = 0  # clutch out: the wheel is the operator's
    POSITION = 1
    TORQUE = 2


class BoardStatus(IntFlag):
    NONE = 0
    ENGAGED = 0x01
    LATCHED = 0x02  # in its safe default after a timeout, power-on or e-stop
    ESTOP = 0x04
    FAULT = 0x08
    OPERATOR_OVERRIDE = 0x10


class FaultCode(IntEnum):
    NONE = 0
    COMMAND_TIMEOUT = 1
    ESTOP = 2
    OVERCURRENT = 3
    POSITION_ERROR = 4
    POT_OUT_OF_RANGE = 5
    SUPPLY_UNDERVOLTAGE = 6
    OVERTEMPERATURE = 7
    INTERNAL = 8


class Buttons(IntFlag):
    NONE = 0
    ENGAGE = 0x01
    SPEED_PLUS = 0x02
    SPEED_MINUS = 0x04
    MANUAL_OVERRIDE = 0x08
    ESTOP = 0x10


BUTTON_ORDER: Final = (
    Buttons.ENGAGE,
    Buttons.SPEED_PLUS,
    Buttons.SPEED_MINUS,
    Buttons.MANUAL_OVERRIDE,
    Buttons.ESTOP,
)


class Lamps(IntFlag):
    NONE = 0
    OVERRIDE = 0x01
    WARNING = 0x02
    ENGAGED = 0x04


MAX_WHEEL_ANGLE_RAD: Final = 20.0
MAX_TORQUE_NM: Final = 30.0
MAX_DISPLAY_CHARS: Final = 32
POT_FULL_SCALE_COUNTS: Final = 4095
NO_PEDAL_CPCT: Final = 0xFFFF


# ---- commands (host -> board) ----------------------------------------------------------
@dataclass(frozen=True)
class SteeringCommand:
    mode: SteeringMode
    wheel_angle_setpoint_rad: float = 0.0  # servo encoder frame (relative), wheel side
    torque_setpoint_nm: float = 0.0


@dataclass(frozen=True)
class ThrottleCommand:
    enable: bool
    position_pct: float = 0.0


@dataclass(frozen=True)
class BrakeCommand:
    enable: bool
    position_pct: float = 0.0


@dataclass(frozen=True)
class PanelCommand:
    lamps: Lamps = Lamps.NONE
    display_text: str = ""


# ---- telemetry (board -> host) ---------------------------------------------------------
@dataclass(frozen=True)
class SteeringTelemetry:
    status: BoardStatus
    fault: FaultCode
    command_seq_echo: int
    servo_position_rad: float
    motor_current_a: float
    motor_torque_nm: float
    pot_raw_counts: int  # 12-bit ADC, uncalibrated
    supply_voltage_v: float


@dataclass(frozen=True)
class ThrottleTelemetry:
    status: BoardStatus
    fault: FaultCode
    command_seq_echo: int
    actuator_position_pct: float
    pedal_position_pct: float | None  # None: the board has no pedal sensor


@dataclass(frozen=True)
class BrakeTelemetry:
    status: BoardStatus
    fault: FaultCode
    command_seq_echo: int
    actuator_position_pct: float
    pedal_position_pct: float | None  # at least the actuator's; more = the operator's foot


@dataclass(frozen=True)
class PanelTelemetry:
    status: BoardStatus
    fault: FaultCode
    command_seq_echo: int
    buttons_down: Buttons
    press_counts: tuple[int, int, int, int, int]  # per BUTTON_ORDER, mod 256

    def press_count(self, button: Buttons) -> int:
        return self.press_counts[BUTTON_ORDER.index(button)]


Command = SteeringCommand | ThrottleCommand | BrakeCommand | PanelCommand
Telemetry = SteeringTelemetry | ThrottleTelemetry | BrakeTelemetry | PanelTelemetry
Message = Command | Telemetry

# Type byte: bit 7 direction (1 = board -> host), bits 6..4 board, bits 3..0 message number.
MESSAGE_TYPES: Final[dict[type[Message], int]] = {
    SteeringCommand: 0x11,
    ThrottleCommand: 0x21,
    BrakeCommand: 0x31,
    PanelCommand: 0x41,
    SteeringTelemetry: 0x91,
    ThrottleTelemetry: 0xA1,
    BrakeTelemetry: 0xB1,
    PanelTelemetry: 0xC1,
}
TYPES_BY_CODE: Final[dict[int, type[Message]]] = {v: k for k, v in MESSAGE_TYPES.items()}
BOARD_MESSAGES: Final[dict[BoardKind, tuple[type[Command], type[Telemetry]]]] = {
    BoardKind.STEERING: (SteeringCommand, SteeringTelemetry),
    BoardKind.THROTTLE: (ThrottleCommand, ThrottleTelemetry),
    BoardKind.BRAKE: (BrakeCommand, BrakeTelemetry),
    BoardKind.PANEL: (PanelCommand, PanelTelemetry),
}
COMMAND_TYPES: Final = tuple(pair[0] for pair in BOARD_MESSAGES.values())
TELEMETRY_TYPES: Final = tuple(pair[1] for pair in BOARD_MESSAGES.values())


def board_of(message_type: type[object]) -> BoardKind:
    for board, pair in BOARD_MESSAGES.items():
        if message_type in pair:
            return board
    raise ActuatorProtocolError("type", f"{message_type.__name__} is not a board message")


_HEADER = struct.Struct("<BBB")
_STEERING_CMD = struct.Struct("<Bih")
_STEERING_TLM = struct.Struct("<BBBihhHH")
_PEDAL_CMD = struct.Struct("<BH")
_PEDAL_TLM = struct.Struct("<BBBHH")
_PANEL_CMD_HEAD = struct.Struct("<BB")
_PANEL_TLM = struct.Struct("<BBBB5B")


def _fixed(value: float, scale: float, low: float, high: float, name: str) -> int:
    """SI value -> wire integer, refusing NaN and anything outside [low, high]."""
    if not math.isfinite(value) or not low <= value <= high:
        raise ActuatorProtocolError("range", f"{name}={value!r} outside [{low}, {high}]")
    return round(value * scale)


def _pct(value: float, name: str) -> int:
    return _fixed(value, 100.0, 0.0, 100.0, name)


def _status_fields(status: BoardStatus, fault: FaultCode, echo: int) -> tuple[int, int, int]:
    if not 0 <= echo <= 255:
        raise ActuatorProtocolError("range", f"command_seq_echo={echo} outside [0, 255]")
    _header(int(status), int(fault))
    return int(status), int(fault), echo


def encode_payload(message: Message) -> bytes:
    """The payload bytes of ``message`` (without type, seq or CRC)."""
    try:
        return _encode_payload(message)
    except (struct.error, ValueError, OverflowError) as exc:  # belt and braces: one error type
        raise ActuatorProtocolError("range", f"cannot encode {message!r}: {exc}") from exc


def _encode_payload(message: Message) -> bytes:
    match message:
        case SteeringCommand(mode, angle, torque):
            if mode not in SteeringMode._value2member_map_:
                raise ActuatorProtocolError("enum", f"unknown steering mode {mode!r}")
            return _STEERING_CMD.pack(
                int(mode),
                _fixed(angle, 1e6, -MAX_WHEEL_ANGLE_RAD, MAX_WHEEL_ANGLE_RAD, "wheel_angle"),
                _fixed(torque, 1e3, -MAX_TORQUE_NM, MAX_TORQUE_NM, "torque_setpoint_nm"),
            )
        case ThrottleCommand(enable, position) | BrakeCommand(enable, position):
            return _PEDAL_CMD.pack(1 if enable else 0, _pct(position, "position_pct"))
        case PanelCommand(lamps, text):
            if len(text) > MAX_DISPLAY_CHARS or not all(" " <= c <= "~" for c in text):
                raise ActuatorProtocolError(
                    "range", f"display_text must be ≤{MAX_DISPLAY_CHARS} printable ASCII"
                )
            if int(lamps) & ~0x07:
                raise ActuatorProtocolError("range", f"unknown lamp bits {int(lamps):#x}")
            return _PANEL_CMD_HEAD.pack(int(lamps), len(text)) + text.encode("ascii")
        case SteeringTelemetry():
            return _STEERING_TLM.pack(
                *_status_fields(message.status, message.fault, message.command_seq_echo),
                _fixed(message.servo_position_rad, 1e6, -2147.0, 2147.0, "servo_position"),
                _fixed(message.motor_current_a, 1e3, -32.0, 32.0, "motor_current_a"),
                _fixed(message.motor_torque_nm, 1e3, -32.0, 32.0, "motor_torque_nm"),
                _fixed(message.pot_raw_counts, 1, 0, POT_FULL_SCALE_COUNTS, "pot_raw_counts"),
                _fixed(message.supply_voltage_v, 1e3, 0.0, 65.0, "supply_voltage_v"),
            )
        case ThrottleTelemetry() | BrakeTelemetry():
            pedal = message.pedal_position_pct
            return _PEDAL_TLM.pack(
                *_status_fields(message.status, message.fault, message.command_seq_echo),
                _pct(message.actuator_position_pct, "actuator_position_pct"),
                NO_PEDAL_CPCT if pedal is None else _pct(pedal, "pedal_position_pct"),
            )
        case PanelTelemetry():
            counts = message.press_counts
            if len(counts) != 5 or not all(0 <= c <= 255 for c in counts):
                raise ActuatorProtocolError("range", f"press_counts must be 5 x u8: {counts}")
            return _PANEL_TLM.pack(
                *_status_fields(message.status, message.fault, message.command_seq_echo),
                int(message.buttons_down),
                *counts,
            )
    raise ActuatorProtocolError("type", f"not an actuator message: {message!r}")


def _check_length(payload: bytes, layout: struct.Struct, name: str) -> None:
    if len(payload) != layout.size:
        raise ActuatorProtocolError(
            "length", f"{name} payload is {len(payload)} bytes, expected {layout.size}"
        )


def _header(status: int, fault: int) -> tuple[BoardStatus, FaultCode]:
    if status & ~0x1F:
        raise ActuatorProtocolError("reserved", f"reserved status bits set: {status:#x}")
    if fault not in FaultCode._value2member_map_:
        raise ActuatorProtocolError("enum", f"unknown fault code {fault}")
    return BoardStatus(status), FaultCode(fault)


def _decode_pct(cpct: int, name: str, allow_none: bool = False) -> float | None:
    if allow_none and cpct == NO_PEDAL_CPCT:
        return None
    if cpct > 10000:
        raise ActuatorProtocolError("range", f"{name} {cpct} above 100.00 %")
    return cpct / 100.0


def decode_payload(message_type: type[Message], payload: bytes) -> Message:
    """Inverse of :func:`encode_payload`, strict about every byte."""
    name = message_type.__name__
    if message_type is SteeringCommand:
        _check_length(payload, _STEERING_CMD, name)
        mode, angle, torque = _STEERING_CMD.unpack(payload)
        if mode not in SteeringMode._value2member_map_:
            raise ActuatorProtocolError("enum", f"unknown steering mode {mode}")
        if abs(angle) > MAX_WHEEL_ANGLE_RAD * 1e6 or abs(torque) > MAX_TORQUE_NM * 1e3:
            raise ActuatorProtocolError("range", "steering setpoint out of range")
        return SteeringCommand(SteeringMode(mode), angle / 1e6, torque / 1e3)
    if message_type is ThrottleCommand or message_type is BrakeCommand:
        _check_length(payload, _PEDAL_CMD, name)
        flags, cpct = _PEDAL_CMD.unpack(payload)
        if flags & ~0x01:
            raise ActuatorProtocolError("reserved", f"reserved command flags set: {flags:#x}")
        position = _decode_pct(cpct, "position")
        assert position is not None
        cls = ThrottleCommand if message_type is ThrottleCommand else BrakeCommand
        return cls(bool(flags & 0x01), position)
    if message_type is PanelCommand:
        if len(payload) < _PANEL_CMD_HEAD.size:
            raise ActuatorProtocolError("length", "PanelCommand payload too short")
        lamps, text_len = _PANEL_CMD_HEAD.unpack_from(payload)
        text = payload[_PANEL_CMD_HEAD.size :]
        if lamps & ~0x07:
            raise ActuatorProtocolError("reserved", f"unknown lamp bits {lamps:#x}")
        if text_len != len(text) or text_len > MAX_DISPLAY_CHARS:
            raise ActuatorProtocolError("length", "PanelCommand text length mismatch")
        if not all(0x20 <= c <= 0x7E for c in text):
            raise ActuatorProtocolError("range", "display text is not printable ASCII")
        return PanelCommand(Lamps(lamps), text.decode("ascii"))
    if message_type is SteeringTelemetry:
        _check_length(payload, _STEERING_TLM, name)
        status, fault, echo, pos, amps, torque, pot, volts = _STEERING_TLM.unpack(payload)
        if pot > POT_FULL_SCALE_COUNTS:
            raise ActuatorProtocolError("range", f"pot reading {pot} exceeds 12 bits")
        return SteeringTelemetry(
            *_header(status, fault), echo, pos / 1e6, amps / 1e3, torque / 1e3, pot, volts / 1e3
        )
    if message_type is ThrottleTelemetry or message_type is BrakeTelemetry:
        _check_length(payload, _PEDAL_TLM, name)
        status, fault, echo, actuator, pedal = _PEDAL_TLM.unpack(payload)
        actuator_pct = _decode_pct(actuator, "actuator position")
        assert actuator_pct is not None
        pedal_pct = _decode_pct(pedal, "pedal position", allow_none=True)
        cls_t = ThrottleTelemetry if message_type is ThrottleTelemetry else BrakeTelemetry
        return cls_t(*_header(status, fault), echo, actuator_pct, pedal_pct)
    if message_type is PanelTelemetry:
        _check_length(payload, _PANEL_TLM, name)
        status, fault, echo, down, *counts = _PANEL_TLM.unpack(payload)
        if down & ~0x1F:
            raise ActuatorProtocolError("reserved", f"unknown button bits {down:#x}")
        c0, c1, c2, c3, c4 = counts
        return PanelTelemetry(*_header(status, fault), echo, Buttons(down), (c0, c1, c2, c3, c4))
    raise ActuatorProtocolError("type", f"no decoder for {name}")
