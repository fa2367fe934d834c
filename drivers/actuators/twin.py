"""Simulated actuator boards on pseudo-terminals: the daemon cannot tell them from hardware.

Each twin owns the master side of a pty pair and publishes the slave through a stable
symlink (as udev's ``/dev/serial/by-id/...`` does for a USB-serial adapter), so the client
opens a real tty with pyserial, and an unplug is a real one: the twin closes the master and
removes the link, the client's reads hit EOF and its writes EIO, reopening fails with
ENOENT until :meth:`BoardTwin.replug` makes a new pty and points the link at it.

A twin is stepped with explicit time (``step(now_s)``), like the firmware's main loop: it
reads the commands that arrived, applies the board's timeout and latch rules
(docs/protocols/actuator-boards.md section 3), moves its physics and, every telemetry
period, writes a frame. ``run`` paces the same step in real time for the daemon.
"""

from __future__ import annotations

import asyncio
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar, Generic, TypeVar

from drivers.actuators.framing import (
    ActuatorProtocolError,
    cobs_decode,
    frame_packet,
)
from drivers.actuators.messages import (
    BoardKind,
    BoardStatus,
    Command,
    FaultCode,
    Telemetry,
)
from drivers.actuators.protocol import NEED_DATA, ActuatorCodec, Role
from drivers.ptylink import PtyLink

CommandT = TypeVar("CommandT", bound=Command)


class BoardTwin(ABC, Generic[CommandT]):
    """What every board does: timeout, latch, e-stop, telemetry pacing, fault injection."""

    board: ClassVar[BoardKind]
    command_type: ClassVar[type[Command]]
    latches: ClassVar[bool] = True  # the panel does not: its lamps just follow commands

    def __init__(
        self,
        link_path: str,
        *,
        command_timeout_s: float = 0.1,
        telemetry_period_s: float = 0.01,
    ) -> None:
        self.link = PtyLink(link_path)
        self.codec = ActuatorCodec(Role.BOARD)
        self.command_timeout_s = command_timeout_s
        self.telemetry_period_s = telemetry_period_s
        self.command: CommandT | None = None  # the command being followed; None: safe default
        self.latched = self.latches  # power-on is a timeout
        self.host_lost = True  # no valid command within the timeout (the panel shows it)
        self.latch_reason = FaultCode.COMMAND_TIMEOUT
        self.estop_active = False
        self.stalled = False
        self.commands_received = 0
        self.commands_ignored = 0  # valid, but refused by the latch or the e-stop
        self.rx_errors = 0
        self.telemetry_sent = 0
        # Benchmark hook: when set, (seq, tx_clock()) is recorded as each frame is written.
        self.tx_clock: Callable[[], float] | None = None
        self.tx_log: list[tuple[int, float]] = []
        self._command_seq_echo = 0
        self._last_command_s: float | None = None
        self._last_step_s: float | None = None
        self._next_telemetry_s: float | None = None
        self._corrupt_frames = 0

    # ---- fault injection -----------------------------------------------------------------
    def unplug(self) -> None:
        """Pull the USB cable: the client sees EOF/EIO, the path disappears."""
        self.link.unplug()
        self.codec.reset()

    def replug(self) -> None:
        """Plug it back in: a new tty behind the same link path."""
        self.link.plug()

    def inject_noise(self, data: bytes) -> None:
        self.link.write(data)

    def corrupt_next_frames(self, count: int) -> None:
        """The next ``count`` telemetry frames go out with a wrong CRC."""
        self._corrupt_frames += count

    def stall(self, stalled: bool = True) -> None:
        """Stop (or resume) sending telemetry; commands are still processed."""
        self.stalled = stalled

    def set_estop(self, active: bool) -> None:
        """The hard-wired e-stop loop opened (True) or closed again (False)."""
        if active and not self.estop_active:
            self._latch(FaultCode.ESTOP)
        self.estop_active = active

    # ---- stepping ------------------------------------------------------------------------
    def step(self, now_s: float) -> None:
        dt_s = 0.0 if self._last_step_s is None else max(0.0, now_s - self._last_step_s)
        self._last_step_s = now_s
        self._receive(now_s)
        last = self._last_command_s
        self.host_lost = last is None or now_s - last > self.command_timeout_s
        if self.host_lost and not (self.latched and self.command is None):
            self._latch(FaultCode.COMMAND_TIMEOUT)
        self._update(now_s, dt_s)
        if self._next_telemetry_s is None:
            self._next_telemetry_s = now_s
        # A tenth of a period of slack: a step that wakes a hair early must not skip a frame.
        if now_s >= self._next_telemetry_s - 0.1 * self.telemetry_period_s:
            self._next_telemetry_s += self.telemetry_period_s
            if self._next_telemetry_s <= now_s:  # fell behind: do not burst to catch up
                self._next_telemetry_s = now_s + self.telemetry_period_s
            if not self.stalled:
                self._send_telemetry()

    async def run(self, clock: Callable[[], float] = time.monotonic) -> None:
        """Step in real time until cancelled."""
        while True:
            self.step(clock())
            assert self._next_telemetry_s is not None
            await asyncio.sleep(max(0.0, self._next_telemetry_s - clock()))

    def close(self) -> None:
        self.link.unplug()

    # ---- the board's rules ---------------------------------------------------------------
    def _latch(self, reason: FaultCode) -> None:
        if self.latches:
            self.latched = True
            self.latch_reason = reason
        self.command = None

    def _receive(self, now_s: float) -> None:
        data = self.link.read()
        if data:
            self.codec.receive_data(data)
        while True:
            try:
                event = self.codec.next_event()
            except ActuatorProtocolError:
                self.rx_errors += 1
                continue
            if event is NEED_DATA:
                return
            if not isinstance(event, self.command_type):
                self.rx_errors += 1  # another board's command: never act on it
                continue
            self._accept(event, now_s)  # type: ignore[arg-type]

    def _accept(self, command: CommandT, now_s: float) -> None:
        self._last_command_s = now_s  # any valid command proves the host is alive
        self.commands_received += 1
        self._command_seq_echo = self.codec.last_received_seq or 0
        if self.estop_active or (self.latched and not self.is_release(command)):
            self.commands_ignored += 1
            return
        self.latched = False
        self.command = command

    def _status(self) -> tuple[BoardStatus, FaultCode]:
        status = BoardStatus.NONE
        hardware = self.hardware_fault()
        fault = FaultCode.NONE
        if hardware is not FaultCode.NONE:
            status |= BoardStatus.FAULT
            fault = hardware
        if self.latched:
            status |= BoardStatus.LATCHED
            fault = self.latch_reason
        elif self.host_lost:
            fault = FaultCode.COMMAND_TIMEOUT
        if self.estop_active:
            status |= BoardStatus.ESTOP
            fault = FaultCode.ESTOP
        if not self.latched and self.command is not None and self.is_engaging(self.command):
            status |= BoardStatus.ENGAGED
        if self.operator_override():
            status |= BoardStatus.OPERATOR_OVERRIDE
        return status, fault

    def _send_telemetry(self) -> None:
        status, fault = self._status()
        data = self.codec.encode(self.telemetry(status, fault, self._command_seq_echo))
        if self._corrupt_frames > 0:
            self._corrupt_frames -= 1
            packet = bytearray(cobs_decode(data[1:-1]))
            packet[-1] ^= 0x5A
            data = frame_packet(bytes(packet))
        if self.tx_clock is not None:
            self.tx_log.append(((self.codec.next_tx_seq - 1) & 0xFF, self.tx_clock()))
        self.link.write(data)
        self.telemetry_sent += 1

    # ---- per board -----------------------------------------------------------------------
    @abstractmethod
    def is_release(self, command: CommandT) -> bool:
        """A command that hands the control back to the operator (unlatches the board)."""

    @abstractmethod
    def is_engaging(self, command: CommandT) -> bool: ...

    @abstractmethod
    def telemetry(self, status: BoardStatus, fault: FaultCode, echo: int) -> Telemetry: ...

    @abstractmethod
    def _update(self, now_s: float, dt_s: float) -> None:
        """Move the board's physics by ``dt_s`` under ``self.command`` (None: safe default)."""

    def hardware_fault(self) -> FaultCode:
        return FaultCode.NONE

    def operator_override(self) -> bool:
        return False
