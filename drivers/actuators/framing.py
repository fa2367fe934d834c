"""Frames on the actuator boards' serial links: COBS, a 0x00 delimiter and CRC-16/CCITT-FALSE.

Why COBS: after COBS a zero byte can only be a frame boundary, so a receiver that lost sync
(noise, a dropped byte, opening the port mid-frame) drops bytes up to the next zero and is
back in step on the next frame. Every frame goes out as ``00 <cobs> 00``: the leading zero
terminates whatever garbage preceded it, so noise costs at most the garbage itself.

This module is sans-I/O: bytes in, packets out. It never reads a clock or a port. Bad input
raises :class:`ActuatorProtocolError`, the one exception of the package, after the bad
bytes have been discarded, so the decoder keeps working on the next call.
"""

from __future__ import annotations

import binascii
from dataclasses import dataclass

DELIMITER = 0
MAX_ENCODED_FRAME_BYTES = 64  # COBS-encoded packet, without delimiters
MIN_PACKET_BYTES = 4  # type, seq, crc16
DEFAULT_MAX_BUFFER_BYTES = 4096


class ActuatorProtocolError(Exception):
    """Bad bytes or an invalid message. ``kind`` names the reason for counting."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


def crc16_ccitt_false(data: bytes) -> int:
    """CRC-16/CCITT-FALSE (poly 0x1021, init 0xFFFF, no reflection, no final XOR).

    ``binascii.crc_hqx`` is the same non-reflected 0x1021 CRC with a caller-chosen start value
    and runs in C, which matters at 4 boards x 100 Hz on a small vehicle computer.
    """
    return binascii.crc_hqx(data, 0xFFFF)


def cobs_encode(data: bytes) -> bytes:
    """COBS-encode ``data``: the result contains no zero byte."""
    out = bytearray()
    for block in data.split(b"\x00"):
        while len(block) >= 254:
            out.append(0xFF)
            out += block[:254]
            block = block[254:]
        out.append(len(block) + 1)
        out += block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Invert :func:`cobs_encode`; raise ActuatorProtocolError on a malformed encoding."""
    if DELIMITER in data:
        raise ActuatorProtocolError("framing", "zero byte inside a COBS frame")
    out = bytearray()
    index = 0
    length = len(data)
    while index < length:
        code = data[index]
        end = index + code
        if end > length:
            raise ActuatorProtocolError("framing", "COBS code points past the end of the frame")
        out += data[index + 1 : end]
        index = end
        if code != 0xFF and index < length:
            out.append(0)
    return bytes(out)


def frame_packet(packet: bytes) -> bytes:
    """Wrap an already checksummed packet for the wire (the twin's fault injection uses it)."""
    return b"\x00" + cobs_encode(packet) + b"\x00"


def frame(body: bytes) -> bytes:
    """``type | seq | payload`` -> wire bytes with CRC (little-endian) and delimiters."""
    return frame_packet(body + crc16_ccitt_false(body).to_bytes(2, "little"))


@dataclass
class FramingStats:
    """Counters for the link's health view; they only ever grow (until ``reset``)."""

    frames_ok: int = 0
    crc_errors: int = 0
    framing_errors: int = 0  # bad COBS or too short
    resyncs: int = 0  # bytes thrown away to find the next delimiter (too long, overflow)
    dropped_bytes: int = 0


class FrameDecoder:
    """Split a byte stream into CRC-checked packet bodies (``type | seq | payload``).

    The buffer is bounded: a run of more than ``MAX_ENCODED_FRAME_BYTES`` without a
    delimiter is noise and is discarded up to the next delimiter; if whole frames pile up
    beyond ``max_buffer_bytes`` (nobody draining), the oldest are dropped first, because for
    100 Hz telemetry the newest frame is the one that matters.
    """

    def __init__(self, max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES) -> None:
        if max_buffer_bytes < 2 * (MAX_ENCODED_FRAME_BYTES + 2):
            raise ValueError(f"max_buffer_bytes too small: {max_buffer_bytes}")
        self.max_buffer_bytes = max_buffer_bytes
        self.stats = FramingStats()
        self._buffer = bytearray()
        self._synced = False  # False: discard everything up to the next delimiter

    def reset(self) -> None:
        """Forget buffered bytes (a new connection); counters are kept."""
        self._buffer.clear()
        self._synced = False

    @property
    def buffered_bytes(self) -> int:
        return len(self._buffer)

    def receive_data(self, data: bytes) -> None:
        self._buffer += data
        excess = len(self._buffer) - self.max_buffer_bytes
        if excess > 0:
            # Drop the oldest bytes, then up to the next delimiter, so we restart on a boundary.
            cut = self._buffer.find(DELIMITER, excess)
            dropped = len(self._buffer) if cut < 0 else cut
            del self._buffer[:dropped]
            self.stats.dropped_bytes += dropped
            self.stats.resyncs += 1
            self._synced = cut >= 0

    def next_packet(self) -> bytes | None:
        """The next good packet body (CRC stripped), or None if more bytes are needed."""
        buffer = self._buffer
        while True:
            end = buffer.find(DELIMITER)
            if end < 0:
                if len(buffer) > MAX_ENCODED_FRAME_BYTES:
                    dropped = len(buffer)
                    buffer.clear()
                    self.stats.dropped_bytes += dropped
                    if self._synced:
                        self._synced = False
                        self.stats.resyncs += 1
                        raise ActuatorProtocolError(
                            "resync", f"{dropped} bytes without a frame delimiter"
                        )
                return None
            encoded = bytes(buffer[:end])
            del buffer[: end + 1]
            if not self._synced:
                self._synced = True
                self.stats.dropped_bytes += len(encoded)
                continue
            if not encoded:
                continue  # "00 00" between back-to-back frames
            return self._check(encoded)

    def _check(self, encoded: bytes) -> bytes:
        if len(encoded) > MAX_ENCODED_FRAME_BYTES:
            self.stats.resyncs += 1
            self.stats.dropped_bytes += len(encoded)
            raise ActuatorProtocolError("resync", f"frame of {len(encoded)} bytes is too long")
        try:
            packet = cobs_decode(encoded)
        except ActuatorProtocolError:
            self.stats.framing_errors += 1
            raise
        if len(packet) < MIN_PACKET_BYTES:
            self.stats.framing_errors += 1
            raise ActuatorProtocolError("framing", f"packet of {len(packet)} bytes is too short")
        body, crc = packet[:-2], int.from_bytes(packet[-2:], "little")
        if crc16_ccitt_false(body) != crc:
            self.stats.crc_errors += 1
            raise ActuatorProtocolError("crc", f"CRC mismatch on type 0x{body[0]:02x} frame")
        self.stats.frames_ok += 1
        return body
