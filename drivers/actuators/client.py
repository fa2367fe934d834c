"""The asyncio side of one actuator board: a read-feed-drain loop around the sans-I/O codec.

The port is opened with pyserial (it configures the tty: baud rate, raw 8N1, exclusive
lock) and then served with ``loop.add_reader`` on its non-blocking descriptor, so no thread
and no executor: bytes are decoded the moment they arrive and each telemetry message is
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

import asyncio
import contextlib
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

import serial  # type: ignore[import-untyped]
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
from drivers.topics import Topic
from drivers.wakeup import Wakeup

log: FilteringBoundLogger = structlog.get_logger(component="actuators")

TelemetryT = TypeVar("TelemetryT", bound=Telemetry)

DEFAULT_COMMAND_PERIOD_S = 0.02  # 50 Hz: five commands per board timeout of 0.1 s
READ_CHUNK_BYTES = 4096


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


class ActuatorClient(Generic[TelemetryT]):
    """One board on one serial port; ``run`` is the supervised service."""

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
        self.board = board_of(telemetry_type)
        self.telemetry_type = telemetry_type
        self.command_type = BOARD_MESSAGES[self.board][0]
        self.port = port
        self.baudrate_bps = baudrate_bps
        self.max_age_s = max_age_s
        self.command_period_s = command_period_s
        self.telemetry: Topic[TelemetryT] = (
            topic if topic is not None else Topic(f"{self.board.value}.telemetry")
        )
        self.backoff_initial_s = backoff_initial_s
        self.backoff_cap_s = backoff_cap_s
        self.beat_while_reconnecting = beat_while_reconnecting
        self._clock = clock
        self.codec = ActuatorCodec(Role.HOST)
        # Called with every chunk of bytes as read, and its receive time (the recorder).
        self.raw_listeners: list[Callable[[bytes, float], None]] = []
        self._serial: Any = None
        self._fd: int | None = None
        self._lost = Wakeup()
        self._lost_reason = ""
        self._command: Command | None = None
        self._lease_until_s: float | None = None
        self._lease_expired_logged = False
        self.lease_expiries = 0
        self._connected_s = 0.0
        self._stale_reported = False
        self._window_start_s = clock()
        self._window_frames = 0
        self._frames_per_s = 0.0
        self.commands_sent = 0
        self.commands_dropped = 0
        self.wrong_board_frames = 0
        self.reconnects = 0
        self.stale_episodes = 0
        self.last_error = ""

    # ---- what the rest of the daemon calls -----------------------------------------------
    @property
    def connected(self) -> bool:
        return self._fd is not None

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

    def is_stale(self, now_s: float) -> bool:
        return self.telemetry.age_s(now_s) > self.max_age_s

    def health(self, now_s: float | None = None) -> LinkHealth:
        now = self._clock() if now_s is None else now_s
        framing, messages = self.codec.framing_stats, self.codec.message_stats
        return LinkHealth(
            board=self.board,
            port=self.port,
            connected=self.connected,
            stale=self.is_stale(now),
            telemetry_age_s=self.telemetry.age_s(now),
            frames_per_s=self._frames_per_s,
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

    async def run(self, beat: Callable[[], None]) -> None:
        """Connect, serve, reconnect, until cancelled.

        ``beat`` is called (at least at the command rate) only while the link is healthy:
        connected and fresh. A board that is unplugged or silent therefore stops the
        heartbeat and its supervisor decides (restart, then latch an error), which is right
        for a critical actuator. ``beat_while_reconnecting=True`` keeps beating through
        outages instead, for a service whose health is judged from ``health()`` alone.
        """
        backoff_s = self.backoff_initial_s
        down_since_s: float | None = None
        attempts = 0
        try:
            while True:
                try:
                    self._open()
                except (serial.SerialException, OSError) as exc:
                    attempts += 1
                    self.last_error = f"open failed: {exc}"
                    if attempts == 1 and down_since_s is None:
                        self._logger().warning("link_unavailable", error=str(exc))
                    else:
                        self._logger().debug("link_retry", attempt=attempts, error=str(exc))
                    if self.beat_while_reconnecting:
                        beat()
                    await asyncio.sleep(backoff_s)
                    backoff_s = min(self.backoff_cap_s, backoff_s * 2.0)
                    continue
                if down_since_s is not None:
                    self.reconnects += 1
                    down_s = round(self._clock() - down_since_s, 3)
                    self._logger().info("link_restored", down_s=down_s, attempts=attempts + 1)
                else:
                    self._logger().info("link_open", baudrate_bps=self.baudrate_bps)
                backoff_s, attempts = self.backoff_initial_s, 0
                reason = await self._serve(beat)
                self._close()
                self.last_error = reason
                down_since_s = self._clock()
                self._logger().warning("link_lost", error=reason)
        finally:
            self._close()

    # ---- transport -----------------------------------------------------------------------
    def _logger(self) -> FilteringBoundLogger:
        # Bound per event (they are rare), so a reconfigured structlog applies at once.
        return log.bind(board=self.board.value, port=self.port)

    def _open(self) -> None:
        port = serial.Serial(
            self.port, self.baudrate_bps, timeout=0, write_timeout=0, exclusive=True
        )
        try:
            port.reset_input_buffer()  # whatever queued while we were away is stale
        except (serial.SerialException, OSError):
            port.close()
            raise
        self._serial = port
        self._fd = port.fileno()
        self.codec.reset()
        self._lost.clear()
        self._connected_s = self._clock()
        asyncio.get_running_loop().add_reader(self._fd, self._on_readable)

    def _close(self) -> None:
        if self._fd is not None:
            asyncio.get_running_loop().remove_reader(self._fd)
            self._fd = None
        if self._serial is not None:
            # The device may already be gone; there is nothing left to release then.
            with contextlib.suppress(serial.SerialException, OSError):
                self._serial.close()
            self._serial = None

    def _mark_lost(self, reason: str) -> None:
        if self._fd is not None:
            # Stop the callback now: a hung-up tty stays readable (EOF) forever.
            asyncio.get_running_loop().remove_reader(self._fd)
        self._lost_reason = reason
        self._lost.set()

    def _on_readable(self) -> None:
        fd = self._fd
        if fd is None or self._lost.is_set():
            return
        try:
            data = os.read(fd, READ_CHUNK_BYTES)
        except BlockingIOError:
            return
        except OSError as exc:
            self._mark_lost(f"read failed: {exc}")
            return
        if not data:
            self._mark_lost("device disconnected (EOF)")
            return
        now_s = self._clock()
        for listener in self.raw_listeners:
            listener(data, now_s)
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
            self._window_frames += 1
            self.telemetry.publish(event, now_s)
            if self._stale_reported:  # logged here, not at the next tick: recovery is news now
                self._stale_reported = False
                self._logger().info("telemetry_fresh")

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

    # ---- the served connection -----------------------------------------------------------
    async def _serve(self, beat: Callable[[], None]) -> str:
        next_send_s = self._clock()
        while True:
            now_s = self._clock()
            if now_s >= next_send_s:
                self._send_current(now_s)
                next_send_s += self.command_period_s
                if next_send_s <= now_s:
                    next_send_s = now_s + self.command_period_s
            self._update_rate(now_s)
            stale = self._check_stale(now_s)
            if self._lost.is_set():
                return self._lost_reason
            if not stale or self.beat_while_reconnecting:
                beat()
            wake_s = next_send_s
            if not stale:  # wake exactly when the newest sample goes stale
                wake_s = min(wake_s, now_s + self.max_age_s - self.telemetry.age_s(now_s))
            await self._lost.wait(max(0.0, wake_s - self._clock()) + 1e-4)

    def _check_stale(self, now_s: float) -> bool:
        stale = self.is_stale(now_s)
        if stale and not self._stale_reported and now_s - self._connected_s > self.max_age_s:
            self._stale_reported = True
            self.stale_episodes += 1
            self._logger().warning(
                "telemetry_stale",
                age_s=round(self.telemetry.age_s(now_s), 3),
                limit_s=self.max_age_s,
            )
        return stale

    def _update_rate(self, now_s: float) -> None:
        elapsed_s = now_s - self._window_start_s
        if elapsed_s >= 1.0:
            self._frames_per_s = self._window_frames / elapsed_s
            self._window_start_s, self._window_frames = now_s, 0
