"""The codec: every message round-trips, bad input only ever raises ActuatorProtocolError."""

from __future__ import annotations

import math
import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.actuators.framing import ActuatorProtocolError, frame
from drivers.actuators.messages import (
    BoardStatus,
    BrakeCommand,
    BrakeTelemetry,
    Buttons,
    FaultCode,
    Lamps,
    Message,
    PanelCommand,
    PanelTelemetry,
    SteeringCommand,
    SteeringMode,
    SteeringTelemetry,
    ThrottleCommand,
    ThrottleTelemetry,
)
from drivers.actuators.protocol import NEED_DATA, ActuatorCodec, Role


def fixed(low: int, high: int, scale: float) -> st.SearchStrategy[float]:
    """Values exactly representable on the wire, so round trips compare equal."""
    return st.integers(low, high).map(lambda n: n / scale)


statuses = st.integers(0, 0x1F).map(BoardStatus)
faults = st.sampled_from(FaultCode)
echo = st.integers(0, 255)
pct = fixed(0, 10000, 100.0)

commands = st.one_of(
    st.builds(
        SteeringCommand,
        st.sampled_from(SteeringMode),
        fixed(-20_000_000, 20_000_000, 1e6),
        fixed(-30_000, 30_000, 1e3),
    ),
    st.builds(ThrottleCommand, st.booleans(), pct),
    st.builds(BrakeCommand, st.booleans(), pct),
    st.builds(
        PanelCommand,
        st.integers(0, 7).map(Lamps),
        st.text(st.characters(min_codepoint=0x20, max_codepoint=0x7E), max_size=32),
    ),
)
telemetry = st.one_of(
    st.builds(
        SteeringTelemetry,
        statuses,
        faults,
        echo,
        fixed(-2_147_000_000, 2_147_000_000, 1e6),
        fixed(-32_000, 32_000, 1e3),
        fixed(-32_000, 32_000, 1e3),
        st.integers(0, 4095),
        fixed(0, 65_000, 1e3),
    ),
    st.builds(ThrottleTelemetry, statuses, faults, echo, pct, st.none() | pct),
    st.builds(BrakeTelemetry, statuses, faults, echo, pct, st.none() | pct),
    st.builds(
        PanelTelemetry,
        statuses,
        faults,
        echo,
        st.integers(0, 0x1F).map(Buttons),
        st.tuples(*[st.integers(0, 255)] * 5),
    ),
)


def decode_all(codec: ActuatorCodec, data: bytes) -> list[Message]:
    codec.receive_data(data)
    events: list[Message] = []
    while (event := codec.next_event()) is not NEED_DATA:
        assert not isinstance(event, type(NEED_DATA))
        events.append(event)
    return events


@given(st.lists(commands, min_size=1, max_size=5))
def test_commands_round_trip(messages: list[Message]) -> None:
    host, board = ActuatorCodec(Role.HOST), ActuatorCodec(Role.BOARD)
    wire = b"".join(host.encode(m) for m in messages)
    assert decode_all(board, wire) == messages
    assert board.message_stats.seq_gaps == 0


@given(st.lists(telemetry, min_size=1, max_size=5))
def test_telemetry_round_trips(messages: list[Message]) -> None:
    host, board = ActuatorCodec(Role.HOST), ActuatorCodec(Role.BOARD)
    wire = b"".join(board.encode(m) for m in messages)
    assert decode_all(host, wire) == messages


@given(
    st.floats(-20.0, 20.0),
    st.floats(-30.0, 30.0),
    st.floats(0.0, 100.0),
)
def test_arbitrary_floats_are_quantised_once(angle: float, torque: float, position: float) -> None:
    host, board = ActuatorCodec(Role.HOST), ActuatorCodec(Role.BOARD)
    sent: list[Message] = [
        SteeringCommand(SteeringMode.POSITION, angle, torque),
        BrakeCommand(True, position),
    ]
    steering, brake = decode_all(board, b"".join(host.encode(m) for m in sent))
    assert isinstance(steering, SteeringCommand) and isinstance(brake, BrakeCommand)
    assert abs(steering.wheel_angle_setpoint_rad - angle) <= 0.5e-6 + 1e-12
    assert abs(steering.torque_setpoint_nm - torque) <= 0.5e-3 + 1e-12
    assert abs(brake.position_pct - position) <= 0.005 + 1e-9
    again = decode_all(board, host.encode(steering) + host.encode(brake))
    assert again == [steering, brake]


@pytest.mark.parametrize(
    "bad",
    [
        ThrottleCommand(True, 100.01),
        ThrottleCommand(True, -0.1),
        BrakeCommand(True, math.nan),
        SteeringCommand(SteeringMode.POSITION, 21.0),
        SteeringCommand(SteeringMode.TORQUE, 0.0, math.inf),
        PanelCommand(Lamps.NONE, "x" * 33),
        PanelCommand(Lamps.NONE, "ümlaut"),
        PanelCommand(Lamps(8), ""),
    ],
)
def test_out_of_range_commands_never_reach_the_wire(bad: Message) -> None:
    with pytest.raises(ActuatorProtocolError):
        ActuatorCodec(Role.HOST).encode(bad)


def test_each_role_sends_only_its_own_direction() -> None:
    tlm = BrakeTelemetry(BoardStatus.NONE, FaultCode.NONE, 0, 0.0, None)
    with pytest.raises(ActuatorProtocolError):
        ActuatorCodec(Role.HOST).encode(tlm)
    with pytest.raises(ActuatorProtocolError):
        ActuatorCodec(Role.BOARD).encode(BrakeCommand(False))
    host = ActuatorCodec(Role.HOST)
    host.receive_data(ActuatorCodec(Role.HOST).encode(BrakeCommand(False)))
    with pytest.raises(ActuatorProtocolError) as error:
        host.next_event()
    assert error.value.kind == "direction"


@pytest.mark.parametrize(
    ("body", "kind"),
    [
        (b"\x77\x00", "type"),
        (b"\x31\x00" + struct.pack("<BH", 0x02, 10), "reserved"),
        (b"\x31\x00" + struct.pack("<BH", 0x01, 10001), "range"),
        (b"\x31\x00\x01", "length"),
        (b"\x11\x00" + struct.pack("<Bih", 3, 0, 0), "enum"),
        (b"\x41\x00\x00\x05abc", "length"),
        (b"\x41\x00\x00\x01\x07", "range"),
    ],
)
def test_strict_decoding(body: bytes, kind: str) -> None:
    board = ActuatorCodec(Role.BOARD)
    board.receive_data(frame(body) + frame(b"\x31\x01" + struct.pack("<BH", 0, 0)))
    with pytest.raises(ActuatorProtocolError) as error:
        board.next_event()
    assert error.value.kind == kind
    assert board.next_event() == BrakeCommand(False, 0.0)  # still usable
    assert board.message_stats.message_errors == 1


def test_sequence_gaps_are_counted_across_the_wrap() -> None:
    host, board = ActuatorCodec(Role.HOST), ActuatorCodec(Role.BOARD)
    wires = [host.encode(ThrottleCommand(False)) for _ in range(300)]
    kept = [w for i, w in enumerate(wires) if i % 50 != 7]  # lose 6 frames, across 255 -> 0
    assert len(decode_all(board, b"".join(kept))) == 294
    assert board.message_stats.seq_gaps == 6


def test_reset_forgets_the_partial_frame_and_the_sequence() -> None:
    host, board = ActuatorCodec(Role.HOST), ActuatorCodec(Role.BOARD)
    wire = host.encode(ThrottleCommand(True, 5.0))
    board.receive_data(wire[:4])
    board.reset()
    assert board.buffered_bytes == 0
    assert decode_all(board, wire[4:] + host.encode(ThrottleCommand(True, 6.0))) == [
        ThrottleCommand(True, 6.0)
    ]


def test_panel_press_count_lookup() -> None:
    panel = PanelTelemetry(BoardStatus.NONE, FaultCode.NONE, 0, Buttons.NONE, (1, 2, 3, 4, 5))
    assert panel.press_count(Buttons.SPEED_MINUS) == 3
    assert panel.press_count(Buttons.ESTOP) == 5


@given(
    st.lists(st.binary(max_size=120), max_size=12),
    st.sampled_from(Role),
)
def test_fuzz_codec_events_or_the_one_error(chunks: list[bytes], role: Role) -> None:
    """Arbitrary bytes, in arbitrary chunks: messages or ActuatorProtocolError, nothing else."""
    codec = ActuatorCodec(role, max_buffer_bytes=512)
    for chunk in chunks:
        codec.receive_data(chunk)
        assert codec.buffered_bytes <= 512
        while True:
            try:
                event = codec.next_event()
            except ActuatorProtocolError:
                continue
            if event is NEED_DATA:
                break


@given(st.lists(telemetry, min_size=1, max_size=4), st.binary(max_size=100), st.data())
def test_fuzz_valid_frames_with_noise_and_one_byte_chunks(
    messages: list[Message], noise: bytes, data: st.DataObject
) -> None:
    board, host = ActuatorCodec(Role.BOARD), ActuatorCodec(Role.HOST)
    wire = noise + b"".join(board.encode(m) for m in messages)
    cut = data.draw(st.integers(0, len(wire)))
    events: list[Message] = []
    for piece in (wire[:cut], *[wire[i : i + 1] for i in range(cut, len(wire))]):
        host.receive_data(piece)
        while True:
            try:
                event = host.next_event()
            except ActuatorProtocolError:
                continue
            if event is NEED_DATA:
                break
            events.append(event)
    assert events[-len(messages) :] == messages
