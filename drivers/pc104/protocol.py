"""The sans-I/O codec of the PC104 link: typed messages <-> (identifier, payload).

``pc104.dbc`` is the contract and this module only applies it (:mod:`.dbc` loads it once
and maps the typed messages to its signals). No sockets, no clock, no asyncio: the caller
passes the receive time in.

Both directions are range-checked against the DBC. On the way out an out-of-range (or
non-finite) value raises :class:`CommandRefused` naming the signal and the allowed range,
so a bad command never reaches the bus; on the way in a value outside the contract is as
bad as a broken CRC. Every kind of bad input raises :class:`Pc104ProtocolError` (of
which ``CommandRefused`` is a subclass) and nothing else.

The CRC-8 is SAE J1850 (poly 0x1D, init 0xFF, xorout 0xFF) over the identifier (two
bytes, big-endian) and the payload without the CRC byte: including the identifier, as
opendbc's checksums do, makes a frame whose identifier was corrupted or misrouted fail
its check instead of being read as another message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import cantools

from drivers.pc104.dbc import (
    DATABASE,
    DBC_PATH,
    HL_IDS,
    PC104_IDS,
    SPECS,
    SPECS_BY_ID,
    MessageSpec,
    spec_for,
)
from drivers.pc104.messages import Message

COUNTER_MODULO = 16


class ErrorReason(StrEnum):
    UNKNOWN_ID = "unknown_id"  # not a frame of this contract
    LENGTH = "length"  # DLC differs from the DBC
    CRC = "crc"
    RANGE = "range"  # a decoded value outside the DBC's range or value table
    REFUSED = "refused"  # an outgoing message that must not reach the bus


class Pc104ProtocolError(Exception):
    """Any bad input to the codec: a frame that is not a valid PC104 frame, or a refused
    outgoing message. ``reason`` says which rule failed; ``signal`` names the signal
    when one is to blame."""

    def __init__(
        self,
        message: str,
        *,
        reason: ErrorReason,
        arbitration_id: int | None = None,
        signal: str | None = None,
    ) -> None:
        super().__init__(message)
        self.reason = reason
        self.arbitration_id = arbitration_id
        self.signal = signal


class CommandRefused(Pc104ProtocolError):
    """An outgoing message was refused before it reached the bus (out of range, NaN)."""


# ---- CRC-8 SAE J1850 -------------------------------------------------------------------
def _crc8_table(poly: int) -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ poly) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


_J1850_TABLE = _crc8_table(0x1D)


def crc8_j1850(data: bytes) -> int:
    """CRC-8 SAE J1850: poly 0x1D, init 0xFF, final XOR 0xFF (check("123456789") = 0x4B)."""
    crc = 0xFF
    for byte in data:
        crc = _J1850_TABLE[crc ^ byte]
    return crc ^ 0xFF


def frame_crc(arbitration_id: int, payload_without_crc: bytes) -> int:
    """The CRC byte of a frame: over the 11-bit identifier (2 bytes, big-endian) + payload."""
    return crc8_j1850(arbitration_id.to_bytes(2, "big") + payload_without_crc)


# ---- encode / decode ----------------------------------------------------------------------
def _within(value: float, minimum: float, maximum: float, scale: float) -> bool:
    # cantools' own tolerance, so that our check and its strict check agree at the edges.
    slack = abs(scale) * 1e-6
    return minimum - slack <= value <= maximum + slack


def encode(message: Message, counter: int) -> tuple[int, bytes]:
    """Encode ``message`` with rolling ``counter`` into ``(arbitration_id, payload)``.

    Raises :class:`CommandRefused` for anything outside the contract.
    """
    spec = SPECS.get(type(message))
    if spec is None:
        raise CommandRefused(f"not a PC104 message: {message!r}", reason=ErrorReason.REFUSED)
    if isinstance(counter, bool) or not isinstance(counter, int):
        raise CommandRefused(f"counter must be an int, got {counter!r}", reason=ErrorReason.REFUSED)
    try:
        signals = spec.to_signals(message)
    except (KeyError, TypeError, ValueError) as exc:  # e.g. a str where an enum belongs
        raise CommandRefused(
            f"{spec.name}: cannot encode {message!r}: {exc}",
            reason=ErrorReason.REFUSED,
            arbitration_id=spec.frame_id,
        ) from exc
    signals["Counter"] = counter
    signals["CRC"] = 0
    for signal in spec.dbc.signals:
        value = signals[signal.name]
        unit = f" {signal.unit}" if signal.unit else ""
        allowed = f"[{signal.minimum}, {signal.maximum}]{unit}"
        if (
            isinstance(value, bool)
            or not isinstance(value, int | float)
            or not math.isfinite(value)
        ):
            problem = f"{value!r} is not a finite number"
        elif signal.minimum is None or signal.maximum is None:  # pragma: no cover - DBC has all
            continue
        elif not _within(value, signal.minimum, signal.maximum, signal.scale):
            problem = f"{value}{unit} is out of range"
        else:
            continue
        raise CommandRefused(
            f"{spec.name}.{signal.name} = {problem} (allowed: {allowed}); "
            "refused before it reached the bus",
            reason=ErrorReason.REFUSED,
            arbitration_id=spec.frame_id,
            signal=signal.name,
        )
    try:
        payload = spec.dbc.encode(signals, strict=True)
    except (cantools.database.EncodeError, ValueError, OverflowError) as exc:
        raise CommandRefused(
            f"{spec.name}: {exc}", reason=ErrorReason.REFUSED, arbitration_id=spec.frame_id
        ) from exc
    body = payload[:-1]
    return spec.frame_id, body + bytes([frame_crc(spec.frame_id, body)])


@dataclass(frozen=True)
class DecodedFrame:
    """A valid frame: the typed message plus its framing, stamped with the receive time."""

    message: Message
    counter: int
    received_s: float
    arbitration_id: int


def decode(arbitration_id: int, data: bytes | bytearray, now_s: float) -> DecodedFrame:
    """Check and decode one frame received at ``now_s``; raises only Pc104ProtocolError."""
    spec = SPECS_BY_ID.get(arbitration_id)
    if spec is None:
        raise Pc104ProtocolError(
            f"identifier 0x{arbitration_id:X} is not in {DBC_PATH.name}",
            reason=ErrorReason.UNKNOWN_ID,
            arbitration_id=arbitration_id,
        )
    payload = bytes(data)
    if len(payload) != spec.length:
        raise Pc104ProtocolError(
            f"{spec.name}: {len(payload)} bytes, expected {spec.length}",
            reason=ErrorReason.LENGTH,
            arbitration_id=arbitration_id,
        )
    expected_crc = frame_crc(arbitration_id, payload[:-1])
    if payload[-1] != expected_crc:
        raise Pc104ProtocolError(
            f"{spec.name}: CRC 0x{payload[-1]:02X}, expected 0x{expected_crc:02X}",
            reason=ErrorReason.CRC,
            arbitration_id=arbitration_id,
            signal="CRC",
        )
    values = spec.dbc.decode_simple(payload, decode_choices=False, scaling=True)
    signals: dict[str, float] = {}
    for signal in spec.dbc.signals:
        value = values[signal.name]
        if not isinstance(value, int | float) or (
            signal.minimum is not None
            and signal.maximum is not None
            and not _within(value, signal.minimum, signal.maximum, signal.scale)
        ):
            raise Pc104ProtocolError(
                f"{spec.name}.{signal.name} = {value!r} is outside "
                f"[{signal.minimum}, {signal.maximum}]",
                reason=ErrorReason.RANGE,
                arbitration_id=arbitration_id,
                signal=signal.name,
            )
        signals[signal.name] = value
    try:
        message = spec.from_signals(signals)
    except KeyError as exc:  # a code missing from a value table
        raise Pc104ProtocolError(
            f"{spec.name}: value {exc} is not in the DBC's value table",
            reason=ErrorReason.RANGE,
            arbitration_id=arbitration_id,
        ) from exc
    return DecodedFrame(message, int(signals["Counter"]), now_s, arbitration_id)


__all__ = [  # the contract's tables are re-exported: callers need one import for the link
    "COUNTER_MODULO",
    "DATABASE",
    "DBC_PATH",
    "HL_IDS",
    "PC104_IDS",
    "SPECS",
    "SPECS_BY_ID",
    "CommandRefused",
    "DecodedFrame",
    "ErrorReason",
    "MessageSpec",
    "Pc104ProtocolError",
    "crc8_j1850",
    "decode",
    "encode",
    "frame_crc",
    "spec_for",
]
