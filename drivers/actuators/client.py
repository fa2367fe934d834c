"""The asyncio side of one actuator board: a read-feed-drain loop around the sans-I/O codec.

The port is served as every serial device is (`drivers.serial_link`: no thread, no
executor): bytes are decoded the moment they arrive and each telemetry message is
published to a latest-value topic stamped with its receive time.

Three duties beyond that, each for safety:

* **Feed the board's watchdog.** The latest command is re-sent every ``command_period_s``
  (and at once when it changes), so the board's own timeout only fires if this process or
  the link dies. Until told what to send, nothing is sent: the board stays in its safe
  default (deny by default).
* **Know when the board is silent.** Telemetry older than ``max_age_s`` makes the link
  stale; consumers see it through ``is_stale``/``health`` and the topic's age, and the
  loop wakes up exactly when the age limit passes so the transition is logged on time.
* **Survive unplugging.** EOF, EIO or a vanished device ends the episode with one warning;
  the port is reopened with exponential backoff (quietly), and the current command is
  re-sent at once when it is back.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import structlog
from structlog.typing import FilteringBoundLogger

from drivers.actuators.framing import ActuatorProtocolError
from drivers.actuators.messages import (
    BOARD_MESSAGES,
    BoardKind,
    Command,
    Telemetry,
    board_of,
    encode_payload,
)
from drivers.actuators.protocol import NEED_DATA, ActuatorCodec, Role
from drivers.ptylink import SIM_PORT_PREFIX
from drivers.serial_link import SerialLink, open_serial
from drivers.topics import Topic

log: FilteringBoundLogger = structlog.get_logger(component="actuators")

TelemetryT = TypeVar("TelemetryT", bound=Telemetry)

DEFAULT_COMMAND_PERIOD_S = 0.02  # 50 Hz: five commands per board timeout of 0.1 s


@dataclass(frozen=True)
class LinkHealth:
    """A snapshot for status views and the safety layer."""

    board: BoardKind
    port: str
    connected: bool
    stale: bool
    telemetry_age_s: float
    frames_per_s: float
    frames_ok: int
    crc_errors: int
    framing_errors: int
    resyncs: int
    message_errors: int
    seq_gaps: int
    wrong_board_frames: int
    commands_sent: int
    commands_dropped: int
    reconnects: int
    stale_episodes: int
    last_error: str
    # Times a command's lease ran out before the next one came (a control loop that hung).
    lease_expiries: int = 0

    @property
    def healthy(self) -> bool:
        return self.connected and not self.stale


class ActuatorClient(SerialLink, Generic[TelemetryT]):
    """One board on one serial port; ``run`` is the supervised service.

    ``beat`` (see `SerialLink.run`) is called at least at the command rate while the link
    is connected and fresh: a board that is unplugged or silent stops the heartbeat and
    its supervisor decides (restart, then latch an error), which is right for a critical
    actuator.
    """

    stale_event = "telemetry_stale"
    fresh_event = "telemetry_fresh"

    def __init__(
        self,
        telemetry_type: type[TelemetryT],
        port: str,
        *,
        baudrate_bps: int = 115_200,
        max_age_s: float = 0.1,
        command_period_s: float = DEFAULT_COMMAND_PERIOD_S,
        topic: Topic[TelemetryT] | None = None,
        backoff_initial_s: float = 0.05,
        backoff_cap_s: float = 1.0,
        beat_while_reconnecting: bool = False,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if port.startswith(SIM_PORT_PREFIX):
            raise ValueError(f"{port!r} must be resolved to a tty path (ActuatorTwins.port_path)")
        super().__init__(
            port,
            baudrate_bps=baudrate_bps,
            max_age_s=max_age_s,
            backoff_initial_s=backoff_initial_s,
            backoff_cap_s=backoff_cap_s,
            beat_while_reconnecting=beat_while_reconnecting,
            clock=clock,
        )
        self.board = board_of(telemetry_type)
        self.telemetry_type = telemetry_type
        self.command_type = BOARD_MESSAGES[self.board][0]
        self.command_period_s = command_period_s
        self.telemetry: Topic[TelemetryT] = (
            topic if topic is not None else Topic(f"{self.board.value}.telemetry")
        )
        self.codec = ActuatorCodec(Role.HOST)
        self._command: Command | None = None
        self._lease_until_s: float | None = None
        self._lease_expired_logged = False
        self.lease_expiries = 0
        self._next_send_s = 0.0
        self.commands_sent = 0
        self.commands_dropped = 0
        self.wrong_board_frames = 0

    # ---- what the rest of the daemon calls -----------------------------------------------
    @property
    def command(self) -> Command | None:
        return self._command

    def set_command(self, command: Command, lease_s: float | None = None) -> None:
        """Make ``command`` the one re-sent every period; send it now if connected.

        ``lease_s``: re-send it only this long unless it is set again. The control loop
        leases every command for a few cycles, so a hung loop does not keep a board
        steering on its last set-point: once the lease runs out nothing is sent and the
        board's own timeout puts it in its safe default. No lease (the safe-stop hook)
        re-sends until replaced. Raises ActuatorProtocolError for another board's command
        or an out-of-range value, before anything is sent.
        """
        if not isinstance(command, self.command_type):
            raise ActuatorProtocolError(
                "direction", f"{type(command).__name__} is not a {self.board.value} command"
            )
        encode_payload(command)  # range check up front, not at the next tick
        self._command = command
        now_s = self._clock()
        self._lease_until_s = None if lease_s is None else now_s + lease_s
        self._lease_expired_logged = False
        self._send_current(now_s)

    def clear_command(self) -> None:
        """Stop commanding: the board's own timeout puts it in its safe default."""
        self._command = None

    def age_s(self, now_s: float) -> float:
        return self.telemetry.age_s(now_s)

    def health(self, now_s: float | None = None) -> LinkHealth:
        now = self._clock() if now_s is None else now_s
        framing, messages = self.codec.framing_stats, self.codec.message_stats
        return LinkHealth(
            board=self.board,
            port=self.port,
            connected=self.connected,
            stale=self.is_stale(now),
            telemetry_age_s=self.telemetry.age_s(now),
            frames_per_s=self._rate_per_s,
            frames_ok=messages.messages_ok,
            crc_errors=framing.crc_errors,
            framing_errors=framing.framing_errors,
            resyncs=framing.resyncs,
            message_errors=messages.message_errors,
            seq_gaps=messages.seq_gaps,
            wrong_board_frames=self.wrong_board_frames,
            commands_sent=self.commands_sent,
            commands_dropped=self.commands_dropped,
            reconnects=self.reconnects,
            stale_episodes=self.stale_episodes,
            last_error=self.last_error,
            lease_expiries=self.lease_expiries,
        )

    # ---- the link -------------------------------------------------------------------------
    def _logger(self) -> FilteringBoundLogger:
        # Bound per event (they are rare), so a reconfigured structlog applies at once.
        return log.bind(board=self.board.value, port=self.port)

    def _open_port(self) -> Any:
        return open_serial(self.port, self.baudrate_bps, write_timeout=0)

    def _opened(self) -> None:
        self.codec.reset()
        self._next_send_s = self._clock()

    def _received(self, data: bytes, now_s: float) -> None:
        codec = self.codec
        codec.receive_data(data)
        while True:
            try:
                event = codec.next_event()
            except ActuatorProtocolError as exc:
                self.last_error = f"{exc.kind}: {exc}"
                continue
            if event is NEED_DATA:
                return
            if not isinstance(event, self.telemetry_type):
                self.wrong_board_frames += 1
                self.last_error = f"{type(event).__name__} on the {self.board.value} port"
                continue
            self._counted()
            self.telemetry.publish(event, now_s)
            self._fresh()

    def _send_current(self, now_s: float) -> None:
        command, fd = self._command, self._fd
        if command is None or fd is None or self._lost.is_set():
            return
        if self._lease_until_s is not None and now_s > self._lease_until_s:
            if not self._lease_expired_logged:
                self._lease_expired_logged = True
                self.lease_expiries += 1
                self._logger().error("command_lease_expired", command=type(command).__name__)
            return
        data = self.codec.encode(command)
        try:
            written = os.write(fd, data)
        except BlockingIOError:
            written = 0
        except OSError as exc:
            self._mark_lost(f"write failed: {exc}")
            return
        if written == len(data):
            self.commands_sent += 1
        else:  # the board sees a torn frame, drops it, and the next one is 20 ms away
            self.commands_dropped += 1

    def _tick(self, now_s: float) -> float:
        """The command re-sent when its period has come; the next send is the next wake-up."""
        if now_s >= self._next_send_s:
            self._send_current(now_s)
            self._next_send_s += self.command_period_s
            if self._next_send_s <= now_s:
                self._next_send_s = now_s + self.command_period_s
        return self._next_send_s
