"""CAN over a serial line (SLCAN, the Lawicel ASCII protocol), both ends of it.

Why it is here: a kit without a CAN controller on its PC reaches the PC104 through a
USB-CAN adapter that speaks SLCAN (CANable, Lawicel CANUSB, USBtin...), and the built-in
simulated vehicle, which runs in a process of its own, needs a CAN link that crosses
processes on machines whose kernel has no CAN at all. python-can's ``slcan`` interface is
that link on the daemon's side; the simulated vehicle plays the adapter on a pty.

* :class:`SlcanHostBus` is python-can's ``slcanBus`` with two fixes the control loop
  needs: it reads everything waiting in one call and never waits for more (python-can
  reads one byte per system call, ~270 us per frame measured here, and waits up to its
  1 ms read timeout when nothing is there, all on the event loop), and it never blocks on a
  full transmit buffer (python-can writes with no timeout, so a wedged adapter would
  freeze the daemon): a frame that does not fit is dropped and reported as ``ENOBUFS``,
  exactly as socketcan reports a full queue, and a line cut short is finished first.
* :class:`SlcanAdapterBus` is the adapter: a ``can.BusABC`` over the master side of a pty,
  answering the host's commands (open, close, bitrate, version) as a Lawicel adapter does
  and forwarding data frames between the line and the twin.

The codec below is sans-I/O. SLCAN has no error frames: an adapter cannot forward bus
errors over it, so neither end pretends to.
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
from collections import deque
from typing import Any, NamedTuple

import can
import serial  # type: ignore[import-untyped]
from can.interfaces.slcan import slcanBus

from drivers.ptylink import PtyLink

OK = b"\r"
ERROR = b"\a"
TERMINATORS = (0x0D, 0x07)  # CR ends a line; BEL is the adapter's "error" answer
READ_CHUNK_BYTES = 4096  # one read takes what a pty or a USB tty holds at once
MAX_LINE_BYTES = 64  # the longest classic line ("T" + 8 + 1 + 16 = 26) with room to spare
HEX_DIGITS = frozenset(b"0123456789ABCDEFabcdef")
FRAME_KINDS = frozenset(b"tTrRdDbB"[i : i + 1] for i in range(8))
BITRATE_CODES = {
    10_000: "S0",
    20_000: "S1",
    50_000: "S2",
    100_000: "S3",
    125_000: "S4",
    250_000: "S5",
    500_000: "S6",
    750_000: "S7",
    1_000_000: "S8",
}


class SlcanError(Exception):
    """A line that is not a valid SLCAN frame."""


def encode_frame(arbitration_id: int, data: bytes, *, extended: bool = False) -> bytes:
    """One classic data frame as an SLCAN line (``t1238...\\r``)."""
    if len(data) > 8:
        raise SlcanError(f"classic CAN carries at most 8 bytes (got {len(data)})")
    if extended:
        if not 0 <= arbitration_id <= 0x1FFF_FFFF:
            raise SlcanError(f"extended id out of range: {arbitration_id:#x}")
        head = f"T{arbitration_id:08X}{len(data)}"
    else:
        if not 0 <= arbitration_id <= 0x7FF:
            raise SlcanError(f"standard id out of range: {arbitration_id:#x}")
        head = f"t{arbitration_id:03X}{len(data)}"
    return head.encode("ascii") + data.hex().upper().encode("ascii") + OK


class SlcanFrame(NamedTuple):
    arbitration_id: int
    data: bytes
    extended: bool
    remote: bool
    dlc: int


def parse_frame(line: bytes) -> SlcanFrame:
    """The frame one line carries (the line without its CR); SlcanError if it carries none."""
    if not line:
        raise SlcanError("empty line")
    kind = chr(line[0])
    if kind not in "tTrR":
        raise SlcanError(f"not a frame line: {line[:16]!r}")
    extended = kind in "TR"
    id_len = 8 if extended else 3
    if not HEX_DIGITS.issuperset(line[1:]):  # int() would take "+", "_" and spaces too
        raise SlcanError(f"not hex in frame line {line[:32]!r}")
    try:
        text = line.decode("ascii")
        arbitration_id = int(text[1 : 1 + id_len], 16)
        dlc = int(text[1 + id_len], 16)
    except (UnicodeDecodeError, ValueError, IndexError) as exc:
        raise SlcanError(f"malformed frame line {line[:32]!r}: {exc}") from None
    if len(text[1 : 1 + id_len]) != id_len or dlc > 8:
        raise SlcanError(f"malformed frame line {line[:32]!r}")
    if not extended and arbitration_id > 0x7FF:
        raise SlcanError(f"standard id out of range in {line[:32]!r}")
    remote = kind in "rR"
    if remote:
        if len(text) != 2 + id_len:
            raise SlcanError(f"remote frame with trailing bytes: {line[:32]!r}")
        return SlcanFrame(arbitration_id, b"", extended, True, dlc)
    payload = text[2 + id_len :]
    if len(payload) != 2 * dlc:
        raise SlcanError(f"data length {len(payload) // 2} != dlc {dlc} in {line[:32]!r}")
    try:
        data = bytes.fromhex(payload)
    except ValueError:
        raise SlcanError(f"data is not hex in {line[:32]!r}") from None
    return SlcanFrame(arbitration_id, data, extended, False, dlc)


class LineSplitter:
    """Bytes in, complete lines out (terminator kept apart); bounded like every parser here.

    A line longer than ``MAX_LINE_BYTES`` is garbage (noise on the line, a wrong baud
    rate): it is dropped up to its terminator and counted, never buffered without end.
    """

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._discarding = False
        self.dropped_lines = 0

    def reset(self) -> None:
        self._buffer.clear()
        self._discarding = False

    def feed(self, data: bytes) -> list[tuple[bytes, int]]:
        """Every line completed by ``data``, as ``(line, terminator)`` pairs."""
        lines: list[tuple[bytes, int]] = []
        for byte in data:
            if byte in TERMINATORS:
                if self._discarding:
                    self._discarding = False
                    self.dropped_lines += 1
                else:
                    lines.append((bytes(self._buffer), byte))
                self._buffer.clear()
            elif not self._discarding:
                self._buffer.append(byte)
                if len(self._buffer) > MAX_LINE_BYTES:
                    self._buffer.clear()
                    self._discarding = True
        return lines


class SlcanHostBus(slcanBus):
    """python-can's SLCAN bus, reading in bulk and never blocking on send."""

    def __init__(self, channel: str, **kwargs: Any) -> None:
        kwargs.setdefault("sleep_after_open", 0.0)  # no Arduino here to wait for
        self._splitter = LineSplitter()
        self._lines: deque[str] = deque()
        self._unsent = b""
        super().__init__(channel, **kwargs)
        # A new session starts empty: what the adapter sent while nobody had the port open
        # (a pty keeps it; a USB tty would not) is old news, and so are its answers to
        # the set-up commands above.
        with contextlib.suppress(OSError, serial.SerialException):
            self.serialPortOrig.reset_input_buffer()

    def _read(self, timeout: float | None) -> str | None:
        if self._lines:
            return self._lines.popleft()
        try:
            fd = self.serialPortOrig.fileno()
            # Readiness first, even for a poll: pyserial sets the tty's VMIN to 0, where a
            # read of nothing returns b"" rather than EAGAIN, so only "readable and empty"
            # tells a hang-up from a quiet line.
            readable, _, _ = select.select([fd], [], [], timeout)
            if not readable:
                return None
            # The descriptor itself, not pyserial's read(): python-can opens the port with
            # a 1 ms read timeout, so read(1) with nothing waiting blocked the event loop
            # 1.1 ms (median; 790 times in 15 s) on every drain of the notifier.
            chunk = os.read(fd, READ_CHUNK_BYTES)  # pyserial opened it O_NONBLOCK
        except BlockingIOError:
            return None
        except (OSError, serial.SerialException) as exc:
            raise can.CanOperationError(
                f"SLCAN adapter unreachable: {exc}", error_code=errno.EIO
            ) from exc
        if not chunk:  # readable and empty: the adapter was unplugged (a pty: hung up)
            raise can.CanOperationError(
                "SLCAN adapter unreachable: end of file on the line", error_code=errno.EIO
            )
        for line, terminator in self._splitter.feed(chunk):
            # Only frames: the adapter's answers to our commands (CR, BEL, "z") carry none.
            if terminator == 0x0D and line[:1] in FRAME_KINDS:
                self._lines.append(line.decode("ascii", errors="replace") + "\r")
        return self._lines.popleft() if self._lines else None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_error_frame:
            raise can.CanOperationError("SLCAN carries no error frames")
        if msg.is_fd or msg.is_remote_frame:
            super().send(msg, timeout)
            return
        try:
            line = encode_frame(msg.arbitration_id, bytes(msg.data), extended=msg.is_extended_id)
        except SlcanError as exc:
            raise can.CanOperationError(str(exc), error_code=errno.EINVAL) from exc
        fd = self.serialPortOrig.fileno()
        if self._unsent:  # finish the line a full buffer cut short, or the adapter sees junk
            self._unsent = self._unsent[self._write_some(fd, self._unsent) :]
            if self._unsent:
                raise can.CanOperationError("SLCAN transmit buffer full", error_code=errno.ENOBUFS)
        written = self._write_some(fd, line)
        if written == 0:
            raise can.CanOperationError("SLCAN transmit buffer full", error_code=errno.ENOBUFS)
        self._unsent = line[written:]

    def shutdown(self) -> None:
        """Close the channel if the line still answers, then the port, whatever happened."""
        if self._is_shutdown:
            return
        with contextlib.suppress(can.CanError, OSError, serial.SerialException):
            self.close()  # "C": fails on a line that hung up, which is why we are here
        can.BusABC.shutdown(self)
        with contextlib.suppress(OSError, serial.SerialException):
            self.serialPortOrig.close()

    @staticmethod
    def _write_some(fd: int, data: bytes) -> int:
        try:
            return os.write(fd, data)  # pyserial opened the tty O_NONBLOCK
        except BlockingIOError:
            return 0
        except OSError as exc:
            raise can.CanOperationError(
                f"SLCAN adapter unreachable: {exc}", error_code=exc.errno
            ) from exc


class SlcanAdapterBus(can.BusABC):
    """A simulated USB-CAN adapter: the bus on one side, SLCAN on a pty on the other.

    ``link_path`` is where the tty appears (a symlink, like ``/dev/serial/by-id/...``).
    Like a Lawicel adapter it forwards nothing until the host opens the channel (``O``),
    answers every command with CR or BEL, and drops what the host does not read in time.
    """

    def __init__(self, link_path: str, **kwargs: Any) -> None:
        self.link = PtyLink(link_path)
        self._splitter = LineSplitter()
        self._received: deque[can.Message] = deque()
        self.is_open = False
        self.bitrate_code = ""
        self.bad_lines = 0
        self.frames_refused = 0  # frames the host sent while the channel was closed
        super().__init__(channel=link_path, **kwargs)
        self.channel_info = f"simulated SLCAN adapter on {link_path}"

    def fileno(self) -> int:
        fd = self.link.master_fd
        if fd is None:
            raise can.CanOperationError("adapter unplugged", error_code=errno.ENODEV)
        return fd

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._received:
            fd = self.link.master_fd
            if fd is None:
                raise can.CanOperationError("adapter unplugged", error_code=errno.ENODEV)
            if timeout is None or timeout > 0:
                select.select([fd], [], [], timeout)
            self._take(self.link.read())
        if self._received:
            return self._received.popleft(), False
        return None, False

    def _take(self, data: bytes) -> None:
        answers = bytearray()
        for line, _terminator in self._splitter.feed(data):
            answers += self._answer(line)
        if answers:
            self.link.write(bytes(answers))

    def _answer(self, line: bytes) -> bytes:
        if not line:
            return OK  # a bare CR (python-can sends some to clear the adapter's buffer)
        command = chr(line[0])
        if command in "tTrR":
            if not self.is_open:
                self.frames_refused += 1
                return ERROR
            try:
                frame = parse_frame(line)
            except SlcanError:
                self.bad_lines += 1
                return ERROR
            self._received.append(
                can.Message(
                    arbitration_id=frame.arbitration_id,
                    data=frame.data,
                    is_extended_id=frame.extended,
                    is_remote_frame=frame.remote,
                    dlc=frame.dlc,
                    channel=self.channel_info,
                )
            )
            return b"z\r" if command in "tr" else b"Z\r"  # Lawicel's "frame queued"
        if command in "OL":
            self.is_open = True
            return OK
        if command == "C":
            self.is_open = False
            return OK
        if command == "S" and line.decode("ascii", "replace") in BITRATE_CODES.values():
            self.bitrate_code = line.decode("ascii")
            return OK
        if command == "V":
            return b"V1013\r"
        if command == "N":
            return b"NDBW1\r"
        if command in "FZMms":  # status flags, timestamps, acceptance filters, BTR
            return b"F00\r" if command == "F" else OK
        self.bad_lines += 1
        return ERROR

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if msg.is_error_frame or not self.is_open:
            return  # SLCAN cannot carry bus errors; a closed channel forwards nothing
        try:
            line = encode_frame(msg.arbitration_id, bytes(msg.data), extended=msg.is_extended_id)
        except SlcanError as exc:
            raise can.CanOperationError(str(exc), error_code=errno.EINVAL) from exc
        self.link.write(line)  # what the host does not read in time is lost, as on a UART

    def shutdown(self) -> None:
        with contextlib.suppress(OSError):
            self.link.unplug()
        super().shutdown()
