"""The codec against the DBC: CRC, round trips, refusals, and fuzzing of the decoder."""

from __future__ import annotations

import math

import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.pc104 import protocol
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
    pulse_delta,
)
from drivers.pc104.protocol import (
    CommandRefused,
    ErrorReason,
    Pc104ProtocolError,
    crc8_j1850,
    decode,
    encode,
    frame_crc,
)


def test_crc8_j1850_check_value() -> None:
    assert crc8_j1850(b"123456789") == 0x4B


def test_crc8_of_empty_input_is_init_xor_final() -> None:
    assert crc8_j1850(b"") == 0x00


def test_crc_covers_the_identifier_so_a_misrouted_frame_fails() -> None:
    arbitration_id, data = encode(MotorPulses(1, 2, 3, 4), counter=7)
    other_id = protocol.spec_for(WheelAngles).frame_id
    assert protocol.spec_for(WheelAngles).length == len(data)
    assert frame_crc(arbitration_id, data[:-1]) != frame_crc(other_id, data[:-1])
    with pytest.raises(Pc104ProtocolError) as info:
        decode(other_id, data, 0.0)
    assert info.value.reason is ErrorReason.CRC


def test_the_dbc_is_versioned_commented_and_timed() -> None:
    db = protocol.DATABASE
    assert db.version
    assert set(protocol.HL_IDS) == {0x100, 0x101, 0x102, 0x103}
    assert set(protocol.PC104_IDS) == {0x110, 0x111, 0x112, 0x113, 0x114}
    for message in db.messages:
        assert message.comment, message.name
        assert message.cycle_time in (20, 100), message.name
        for signal in message.signals:
            assert signal.comment, f"{message.name}.{signal.name}"
            assert signal.minimum is not None and signal.maximum is not None
    assert protocol.spec_for(Pc104Status).period_s == pytest.approx(0.02)
    assert protocol.spec_for(MotionCommand).period_s == pytest.approx(0.02)


def test_an_independent_cantools_decode_agrees_with_the_codec() -> None:
    db = cantools.database.load_file(str(protocol.DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    command = MotionCommand(MotionPattern.OBLIQUE, -1.25, 0.2, -0.1, level_platform=True)
    arbitration_id, data = encode(command, counter=9)
    values = db.get_message_by_frame_id(arbitration_id).decode_simple(data)
    assert str(values["MotionPattern"]) == "OBLIQUE"
    assert values["Counter"] == 9
    assert values["SpeedSetpoint"] == pytest.approx(-1.25)
    assert values["CRC"] == crc8_j1850(bytes([0x01, 0x00]) + data[:-1])


# ---- round trips over all in-range values -----------------------------------------------
def _in_range(message: str, signal: str) -> st.SearchStrategy[float]:
    dbc_signal = protocol.DATABASE.get_message_by_name(message).get_signal_by_name(signal)
    assert dbc_signal.minimum is not None and dbc_signal.maximum is not None
    return st.floats(float(dbc_signal.minimum), float(dbc_signal.maximum))


_rows = st.tuples(*[_in_range("PC104_WheelAngles", f"Row{r}Angle") for r in range(1, 5)])
_counts = st.integers(0, 4095)
MESSAGES: st.SearchStrategy[Message] = st.one_of(
    st.builds(
        MotionCommand,
        st.sampled_from(MotionPattern),
        _in_range("HL_MotionCommand", "SpeedSetpoint"),
        _in_range("HL_MotionCommand", "FrontSteerSetpoint"),
        _in_range("HL_MotionCommand", "RearSteerSetpoint"),
        st.booleans(),
    ),
    st.builds(HlHeartbeat, st.sampled_from(HighLevelState), st.integers(0, 255)),
    st.builds(
        HlPose,
        _in_range("HL_Pose", "PoseX"),
        _in_range("HL_Pose", "PoseY"),
        _in_range("HL_Pose", "PoseYaw"),
        st.sampled_from(PoseState),
    ),
    st.builds(
        HlExpectedPose,
        _in_range("HL_ExpectedPose", "ExpectedX"),
        _in_range("HL_ExpectedPose", "ExpectedY"),
        _in_range("HL_ExpectedPose", "ExpectedYaw"),
        st.sampled_from(SteeringLoop),
    ),
    st.builds(
        Pc104Status,
        st.sampled_from(MotionPattern),
        st.booleans(),
        st.sampled_from(ControlSource),
        st.booleans(),
        st.booleans(),
        st.booleans(),
        st.builds(Pc104Faults, *[st.booleans()] * 8),
        _in_range("PC104_Status", "MeasuredSpeed"),
        st.integers(0, 255),
    ),
    st.builds(WheelAngles, _rows, st.tuples(*[st.booleans()] * 4)),
    st.builds(MotorPulses, _counts, _counts, _counts, _counts),
    st.builds(
        Inclinometer,
        _in_range("PC104_Inclinometer", "Pitch"),
        _in_range("PC104_Inclinometer", "Roll"),
        st.booleans(),
    ),
    st.builds(
        Pc104Heartbeat, st.sampled_from(Pc104State), st.integers(0, 65535), st.integers(0, 255)
    ),
)


def _close(sent: object, received: object, resolution: float) -> bool:
    if isinstance(sent, float):
        assert isinstance(received, float)
        return abs(sent - received) <= resolution / 2 + 1e-9
    if isinstance(sent, tuple):
        assert isinstance(received, tuple)
        return all(_close(a, b, resolution) for a, b in zip(sent, received, strict=True))
    return sent == received


@settings(max_examples=400, deadline=None)
@given(MESSAGES, st.integers(0, 15), st.floats(0, 1e6))
def test_every_in_range_message_round_trips_within_resolution(
    message: Message, counter: int, now_s: float
) -> None:
    arbitration_id, data = encode(message, counter)
    spec = protocol.spec_for(type(message))
    assert (arbitration_id, len(data)) == (spec.frame_id, spec.length)
    frame = decode(arbitration_id, data, now_s)
    assert (frame.counter, frame.received_s, frame.arbitration_id) == (
        counter,
        now_s,
        arbitration_id,
    )
    resolution = max(s.scale for s in spec.dbc.signals)
    for name in type(message).__dataclass_fields__:
        sent, received = getattr(message, name), getattr(frame.message, name)
        assert _close(sent, received, resolution), (name, sent, received)


# ---- refusals ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("command", "signal"),
    [
        (MotionCommand(MotionPattern.STRAIGHT, speed_mps=10.01), "SpeedSetpoint"),
        (MotionCommand(MotionPattern.STRAIGHT, speed_mps=-25.0), "SpeedSetpoint"),
        (MotionCommand(MotionPattern.FRONT_STEER, front_steer_rad=1.1), "FrontSteerSetpoint"),
        (MotionCommand(MotionPattern.REAR_STEER, rear_steer_rad=-1.05), "RearSteerSetpoint"),
        (MotionCommand(MotionPattern.STRAIGHT, speed_mps=math.nan), "SpeedSetpoint"),
        (MotionCommand(MotionPattern.STRAIGHT, speed_mps=math.inf), "SpeedSetpoint"),
        (MotionCommand(MotionPattern.OBLIQUE, front_steer_rad=-math.inf), "FrontSteerSetpoint"),
    ],
)
def test_out_of_range_commands_are_refused_naming_signal_and_range(
    command: MotionCommand, signal: str
) -> None:
    with pytest.raises(CommandRefused) as info:
        encode(command, 0)
    assert info.value.signal == signal
    assert info.value.reason is ErrorReason.REFUSED
    text = str(info.value)
    assert signal in text and "allowed" in text and "[" in text


def test_a_value_at_the_limit_is_accepted() -> None:
    encode(MotionCommand(MotionPattern.STRAIGHT, speed_mps=10.0, front_steer_rad=-1.0472), 0)


@pytest.mark.parametrize("counter", [-1, 16, 1.0, True])
def test_bad_counters_are_refused(counter: object) -> None:
    with pytest.raises(CommandRefused):
        encode(MotionCommand.stop(), counter)  # type: ignore[arg-type]


def test_garbage_messages_are_refused_with_the_one_error() -> None:
    with pytest.raises(CommandRefused):
        encode("STOP", 0)  # type: ignore[arg-type]
    with pytest.raises(CommandRefused):
        encode(MotionCommand("fly", 1.0), 0)  # type: ignore[arg-type]
    with pytest.raises(CommandRefused):
        encode(MotionCommand(MotionPattern.STRAIGHT, "fast"), 0)  # type: ignore[arg-type]
    with pytest.raises(CommandRefused):
        encode(MotorPulses(4096, 0, 0, 0), 0)


def test_refused_is_a_protocol_error() -> None:
    assert issubclass(CommandRefused, Pc104ProtocolError)


# ---- decoding bad input -----------------------------------------------------------------
def test_wrong_length_is_rejected() -> None:
    arbitration_id, data = encode(Pc104Status(MotionPattern.STOP, False, ControlSource.CAB), 0)
    with pytest.raises(Pc104ProtocolError) as info:
        decode(arbitration_id, data[:2], 0.0)
    assert info.value.reason is ErrorReason.LENGTH


def test_unknown_identifier_is_rejected() -> None:
    with pytest.raises(Pc104ProtocolError) as info:
        decode(0x7FF, bytes(8), 0.0)
    assert info.value.reason is ErrorReason.UNKNOWN_ID


def _with_crc(arbitration_id: int, body: bytes) -> bytes:
    return body + bytes([frame_crc(arbitration_id, body)])


def test_values_outside_the_contract_are_rejected_even_with_a_good_crc() -> None:
    status_id = protocol.spec_for(Pc104Status).frame_id
    control_source_3 = bytes([0x00, 0x03, 0, 0, 0, 0, 0])
    with pytest.raises(Pc104ProtocolError) as info:
        decode(status_id, _with_crc(status_id, control_source_3), 0.0)
    assert (info.value.reason, info.value.signal) == (ErrorReason.RANGE, "ControlSource")
    pattern_7 = bytes([0x07, 0x02, 0, 0, 0, 0, 0])
    with pytest.raises(Pc104ProtocolError) as info:
        decode(status_id, _with_crc(status_id, pattern_7), 0.0)
    assert info.value.signal == "ActivePattern"
    wheels_id = protocol.spec_for(WheelAngles).frame_id
    row1_2047_mrad = bytes([0x0F, 0xFF, 0x07, 0, 0, 0, 0])
    with pytest.raises(Pc104ProtocolError) as info:
        decode(wheels_id, _with_crc(wheels_id, row1_2047_mrad), 0.0)
    assert info.value.signal == "Row1Angle"


@settings(max_examples=2000, deadline=None)
@given(
    st.one_of(st.sampled_from(sorted(protocol.SPECS_BY_ID)), st.integers(0, 0x1FFFFFFF)),
    st.binary(max_size=16),
)
def test_any_frame_decodes_or_raises_the_one_error(arbitration_id: int, data: bytes) -> None:
    try:
        frame = decode(arbitration_id, data, 0.0)
    except Pc104ProtocolError:
        return
    assert frame.arbitration_id == arbitration_id
    assert len(data) == protocol.SPECS_BY_ID[arbitration_id].length


@settings(max_examples=1000, deadline=None)
@given(st.sampled_from(sorted(protocol.SPECS_BY_ID)), st.data())
def test_frames_with_a_valid_crc_decode_or_raise_the_one_error(
    arbitration_id: int, data: st.DataObject
) -> None:
    length = protocol.SPECS_BY_ID[arbitration_id].length
    body = data.draw(st.binary(min_size=length - 1, max_size=length - 1))
    try:
        frame = decode(arbitration_id, _with_crc(arbitration_id, body), 0.0)
    except Pc104ProtocolError as exc:
        reason = exc.reason
    else:
        # Whatever decodes must re-encode: the decoder never returns something out of contract.
        encode(frame.message, frame.counter)
        return
    assert reason is ErrorReason.RANGE


def test_pulse_delta_wraps() -> None:
    assert pulse_delta(4090, 5) == 11
    assert pulse_delta(100, 100) == 0
    assert pulse_delta(0, 4095) == 4095


def test_the_pose_frames_decode_independently_and_refuse_what_they_cannot_carry() -> None:
    db = cantools.database.load_file(str(protocol.DBC_PATH))
    assert isinstance(db, cantools.database.can.Database)
    pose = HlPose(-14.2, 0.0132, -math.pi, PoseState.DEGRADED)
    arbitration_id, data = encode(pose, counter=5)
    values = db.get_message_by_frame_id(arbitration_id).decode_simple(data)
    assert (arbitration_id, str(values["PoseState"]), values["Counter"]) == (0x102, "DEGRADED", 5)
    assert values["PoseX"] == pytest.approx(-14.2)
    assert values["PoseY"] == pytest.approx(0.013)
    assert values["PoseYaw"] == pytest.approx(-math.pi, abs=5e-5)
    expected = HlExpectedPose(-6.0, 0.0, 0.0, SteeringLoop.PC104)
    arbitration_id, data = encode(expected, counter=0)
    values = db.get_message_by_frame_id(arbitration_id).decode_simple(data)
    assert (arbitration_id, str(values["SteeringLoop"])) == (0x103, "PC104")
    # 40 m from the site's origin does not fit in 16 bits at 1 mm: refused, never wrapped.
    with pytest.raises(CommandRefused) as info:
        encode(HlPose(40.0, 0.0, 0.0), 0)
    assert info.value.signal == "PoseX"
    # A pose state the DBC does not define, with a good CRC, is a range error.
    pose_id = protocol.spec_for(HlPose).frame_id
    with pytest.raises(Pc104ProtocolError) as rejected:
        decode(pose_id, _with_crc(pose_id, bytes([0x03, 0, 0, 0, 0, 0, 0])), 0.0)
    assert (rejected.value.reason, rejected.value.signal) == (ErrorReason.RANGE, "PoseState")
