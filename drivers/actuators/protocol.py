"""Sans-I/O codec of the actuator boards: bytes in, typed messages out; messages in, bytes out.

One class serves both ends of a link, after h11's client/server roles: the host encodes
commands and decodes telemetry, a board (the twin, or firmware tests) the reverse. Receiving
a message of the wrong direction is a protocol error, because a host that decodes a
*command* is listening to something that is not a board.

``next_event`` returns a message or ``NEED_DATA``; a bad frame raises
:class:`ActuatorProtocolError` once, after it has been discarded and counted, and the next
call carries on with the following frame. Nothing here reads a clock or touches a port.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum, StrEnum
from typing import Final

from drivers.actuators.framing import (
    DEFAULT_MAX_BUFFER_BYTES,
    ActuatorProtocolError,
    FrameDecoder,
    FramingStats,
    frame,
)
from drivers.actuators.messages import (
    COMMAND_TYPES,
    MESSAGE_TYPES,
    TELEMETRY_TYPES,
    TYPES_BY_CODE,
    Message,
    decode_payload,
    encode_payload,
)


class NeedData(Enum):
    NEED_DATA = "NEED_DATA"


NEED_DATA: Final = NeedData.NEED_DATA


class Role(StrEnum):
    HOST = "host"  # sends commands, receives telemetry
    BOARD = "board"  # sends telemetry, receives commands


@dataclass
class MessageStats:
    """Counters above the framing layer."""

    messages_ok: int = 0
    message_errors: int = 0  # good CRC, but unknown type, wrong direction, bad length/values
    seq_gaps: int = 0  # frames the peer sent that never arrived (or arrived corrupted)


class ActuatorCodec:
    """Both directions of one serial link, with sequence numbering and counters."""

    def __init__(self, role: Role, *, max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES) -> None:
        self.role = role
        self._decoder = FrameDecoder(max_buffer_bytes)
        self._incoming_types = TELEMETRY_TYPES if role is Role.HOST else COMMAND_TYPES
        self._outgoing_types = COMMAND_TYPES if role is Role.HOST else TELEMETRY_TYPES
        self._tx_seq = 0
        self.last_received_seq: int | None = None
        self.message_stats = MessageStats()

    @property
    def framing_stats(self) -> FramingStats:
        return self._decoder.stats

    @property
    def buffered_bytes(self) -> int:
        return self._decoder.buffered_bytes

    @property
    def next_tx_seq(self) -> int:
        return self._tx_seq

    def reset(self) -> None:
        """A new connection: drop buffered bytes and the sequence history, keep counters."""
        self._decoder.reset()
        self.last_received_seq = None

    def receive_data(self, data: bytes) -> None:
        self._decoder.receive_data(data)

    def next_event(self) -> Message | NeedData:
        body = self._decoder.next_packet()
        if body is None:
            return NEED_DATA
        type_code, seq, payload = body[0], body[1], body[2:]
        self._track_seq(seq)
        message_type = TYPES_BY_CODE.get(type_code)
        try:
            if message_type is None:
                raise ActuatorProtocolError("type", f"unknown message type 0x{type_code:02x}")
            if message_type not in self._incoming_types:
                raise ActuatorProtocolError(
                    "direction", f"{message_type.__name__} is not for a {self.role.value}"
                )
            message = decode_payload(message_type, payload)
        except ActuatorProtocolError:
            self.message_stats.message_errors += 1
            raise
        self.message_stats.messages_ok += 1
        return message

    def encode(self, message: Message) -> bytes:
        """Wire bytes for ``message`` with the next sequence number; range-checked."""
        type_code = MESSAGE_TYPES.get(type(message))
        if type_code is None or type(message) not in self._outgoing_types:
            raise ActuatorProtocolError(
                "direction", f"a {self.role.value} does not send {type(message).__name__}"
            )
        payload = encode_payload(message)
        seq = self._tx_seq
        self._tx_seq = (seq + 1) & 0xFF
        return frame(bytes((type_code, seq)) + payload)

    def _track_seq(self, seq: int) -> None:
        last = self.last_received_seq
        if last is not None:
            self.message_stats.seq_gaps += (seq - last - 1) & 0xFF
        self.last_received_seq = seq
