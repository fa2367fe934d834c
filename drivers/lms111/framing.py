"""Sans-I/O framing of SOPAS CoLa telegrams, both dialects, both directions.

Format (SICK "Telegram Listing Ranging sensors", part 8014631, and the LMS1xx/LMS4000
operating instructions; cross-checked against Wireshark's ``packet-cola.c`` and the
ColaAscii/ColaBinary test vectors in SICK's ``sick_scan_xd``):

* CoLa-A: ``STX (0x02)`` + ASCII payload + ``ETX (0x03)``. The payload is printable, so a
  0x02 inside a telegram can only mean the previous one was cut off.
* CoLa-B: magic ``02 02 02 02`` + payload length (uint32, big endian) + payload + one byte,
  the XOR of all payload bytes. The payload is binary, so the magic may occur inside it by
  chance; the length cap and the checksum are what reject a false start.

The framer is h11-shaped: feed bytes with `receive_data`, then call `next_event` until it
returns `NEED_DATA`. It never touches a socket or a clock.

Resynchronisation rules (a scanner stream must survive a corrupted telegram):

* bytes before a start marker are garbage: dropped silently and counted in `garbage_bytes`
  (a connection usually starts mid-telegram);
* CoLa-A: a new STX before the ETX means the telegram was truncated. It is dropped, counted
  in `malformed_telegrams`, and `TruncatedTelegram` (a `ProtocolError`) is raised; the framer
  has already resynced on the new STX, so the next `next_event()` continues with it. A device
  ignores such a frame silently (a CoLa-B request looks like one), hence the distinct type;
* CoLa-B: a length of 0 or above ``max_telegram_bytes``, or a bad checksum, drops the frame
  the same way. After a bad checksum, if the bytes right after the frame start a magic the
  whole frame is skipped (the payload was corrupted); otherwise the length itself is suspect
  and the search restarts one byte after the bad magic, so a good telegram hidden inside the
  bogus length still comes out;
* a telegram longer than ``max_telegram_bytes`` is dropped (ProtocolError); the buffer never
  holds more than ``max_buffer_bytes``: past that the oldest bytes are dropped and counted as
  garbage (only a caller that stops draining can get there).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np

from drivers.lms111.errors import ProtocolError, TruncatedTelegram

STX: Final = 0x02
ETX: Final = 0x03
COLA_B_MAGIC: Final = b"\x02\x02\x02\x02"
COLA_B_HEADER_BYTES: Final = 8
DEFAULT_MAX_TELEGRAM_BYTES: Final = 64 * 1024
DEFAULT_MAX_BUFFER_BYTES: Final = 256 * 1024


class Dialect(enum.Enum):
    """The two SOPAS encodings. The LMS111 talks CoLa-A unless switched by ``EIHstCola``."""

    COLA_A = "CoLa-A"
    COLA_B = "CoLa-B"


class _Sentinel(enum.Enum):
    NEED_DATA = "NEED_DATA"

    def __repr__(self) -> str:
        return self.value


NEED_DATA: Final = _Sentinel.NEED_DATA
"""Returned by `next_event` when the buffer holds no complete telegram (h11's sentinel)."""

NeedData = Literal[_Sentinel.NEED_DATA]


@dataclass(frozen=True)
class Telegram:
    """One framed telegram: the payload between the markers, framing stripped."""

    dialect: Dialect
    payload: bytes


def xor_checksum(payload: bytes) -> int:
    """CoLa-B checksum: XOR of every payload byte (numpy: a 5 kB scan costs microseconds)."""
    if not payload:
        return 0
    return int(np.bitwise_xor.reduce(np.frombuffer(payload, dtype=np.uint8)))


def frame(dialect: Dialect, payload: bytes) -> bytes:
    """Wrap a payload for the wire; the inverse of what `ColaFramer` strips."""
    if not payload:
        raise ProtocolError("a CoLa telegram cannot be empty")
    if dialect is Dialect.COLA_A:
        if STX in payload or ETX in payload:
            raise ProtocolError("a CoLa-A payload cannot contain STX or ETX")
        return b"\x02" + payload + b"\x03"
    if len(payload) > 0xFFFFFFFF:
        raise ProtocolError("CoLa-B payload longer than a uint32 length can say")
    return (
        COLA_B_MAGIC
        + len(payload).to_bytes(4, "big")
        + payload
        + xor_checksum(payload).to_bytes(1, "big")
    )


class ColaFramer:
    """Bytes in, `Telegram` out, for one dialect at a time.

    ``max_telegram_bytes`` bounds one payload (the longest LMS111 telegram, a 1,081-point
    CoLa-A scan with RSSI, is about 11 kB); ``max_buffer_bytes`` bounds the buffer whatever the
    caller does.
    """

    def __init__(
        self,
        dialect: Dialect = Dialect.COLA_A,
        *,
        max_telegram_bytes: int = DEFAULT_MAX_TELEGRAM_BYTES,
        max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
    ) -> None:
        if max_telegram_bytes < 1 or max_buffer_bytes < max_telegram_bytes + 9:
            raise ValueError("need 1 <= max_telegram_bytes and room for one framed telegram")
        self._dialect = dialect
        self._max_telegram_bytes = max_telegram_bytes
        self._max_buffer_bytes = max_buffer_bytes
        self._buf = bytearray()
        self._scanned = 0  # CoLa-A: bytes after STX already searched for STX/ETX
        self._garbage_bytes = 0
        self._malformed_telegrams = 0

    @property
    def dialect(self) -> Dialect:
        return self._dialect

    @property
    def garbage_bytes(self) -> int:
        """Bytes dropped outside any telegram, including those dropped on buffer overflow."""
        return self._garbage_bytes

    @property
    def malformed_telegrams(self) -> int:
        """Telegrams dropped for truncation, bad length, bad checksum or excessive size."""
        return self._malformed_telegrams

    @property
    def buffered_bytes(self) -> int:
        return len(self._buf)

    def reset(self) -> None:
        """Forget buffered bytes and counters (a new connection)."""
        self._buf.clear()
        self._scanned = 0
        self._garbage_bytes = 0
        self._malformed_telegrams = 0

    def switch_dialect(self, dialect: Dialect) -> None:
        """Frame what follows in another dialect (after ``sWA EIHstCola``); keeps the buffer."""
        self._dialect = dialect
        self._scanned = 0

    def receive_data(self, data: bytes) -> None:
        """Append bytes from the transport; never raises on content."""
        self._buf += data
        excess = len(self._buf) - self._max_buffer_bytes
        if excess > 0:
            del self._buf[:excess]
            self._garbage_bytes += excess
            self._scanned = 0

    def next_event(self) -> Telegram | NeedData:
        """The next complete telegram, or `NEED_DATA`.

        Raises `ProtocolError` for a malformed telegram *after* discarding it: call again to
        continue with what followed it.
        """
        if self._dialect is Dialect.COLA_A:
            return self._next_cola_a()
        return self._next_cola_b()

    def _drop_front(self, count: int) -> None:
        del self._buf[:count]
        self._scanned = 0

    def _malformed(
        self, drop: int, why: str, error: type[ProtocolError] = ProtocolError
    ) -> ProtocolError:
        self._drop_front(drop)
        self._malformed_telegrams += 1
        return error(why)

    def _next_cola_a(self) -> Telegram | NeedData:
        buf = self._buf
        start = buf.find(STX)
        if start < 0:
            self._garbage_bytes += len(buf)
            self._drop_front(len(buf))
            return NEED_DATA
        if start > 0:
            self._garbage_bytes += start
            self._drop_front(start)
        search_from = max(1, self._scanned)
        etx = buf.find(ETX, search_from)
        stx = buf.find(STX, search_from, etx if etx >= 0 else len(buf))
        if stx >= 0:
            why = f"CoLa-A telegram truncated after {stx - 1} bytes"
            raise self._malformed(stx, why, TruncatedTelegram)
        if etx < 0:
            if len(buf) - 1 > self._max_telegram_bytes:
                raise self._malformed(len(buf), "CoLa-A telegram exceeds the size limit")
            self._scanned = len(buf)
            return NEED_DATA
        if etx == 1:
            raise self._malformed(2, "empty CoLa-A telegram")
        if etx - 1 > self._max_telegram_bytes:
            raise self._malformed(etx + 1, "CoLa-A telegram exceeds the size limit")
        with memoryview(buf) as view:
            payload = bytes(view[1:etx])
        self._drop_front(etx + 1)
        return Telegram(Dialect.COLA_A, payload)

    def _next_cola_b(self) -> Telegram | NeedData:
        buf = self._buf
        start = buf.find(COLA_B_MAGIC)
        if start < 0:
            # Keep a trailing run of 0x02 (at most 3): it may be the start of a magic.
            keep = min(3, len(buf) - len(buf.rstrip(b"\x02")))
            self._garbage_bytes += len(buf) - keep
            self._drop_front(len(buf) - keep)
            return NEED_DATA
        if start > 0:
            self._garbage_bytes += start
            self._drop_front(start)
        if len(buf) < COLA_B_HEADER_BYTES:
            return NEED_DATA
        length = int.from_bytes(buf[4:8], "big")
        if length == 0 or length > self._max_telegram_bytes:
            raise self._malformed(1, f"CoLa-B length {length} out of range")
        end = COLA_B_HEADER_BYTES + length + 1
        if len(buf) < end:
            return NEED_DATA
        with memoryview(buf) as view:
            payload = bytes(view[COLA_B_HEADER_BYTES : end - 1])
        checksum = buf[end - 1]
        if xor_checksum(payload) != checksum:
            after = bytes(buf[end : end + 4])
            drop = end if COLA_B_MAGIC.startswith(after) else 1
            raise self._malformed(drop, "CoLa-B checksum mismatch")
        self._drop_front(end)
        return Telegram(Dialect.COLA_B, payload)
