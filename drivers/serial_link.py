"""One device on one serial port, served on the event loop: open, read, notice silence,
survive the cable. The part every serial driver shares (the actuator boards, the GNSS/INS
receiver); what the bytes mean is the subclass's.

The port is opened with pyserial (it configures the tty: baud rate, raw 8N1, exclusive
lock) and served with ``loop.add_reader`` on its non-blocking descriptor, so no thread and
no executor: bytes are handed on the moment they arrive, stamped with their receive time.

Why one class and not two copies: the reconnect loop is where a driver's worst day is
decided (EOF, EIO, a device that vanished and comes back as another node), and a fix
made in one copy and not the other is a board that recovers from an unplug while the
receiver beside it does not.

* **Survive unplugging.** EOF, EIO or a vanished device ends the episode with one warning
  and a reason; the port is reopened with exponential backoff (quietly), counted as a
  reconnect when it is back.
* **Know when the device is silent.** Input older than ``max_age_s`` makes the link stale:
  ``is_stale`` says so, and the serve loop wakes exactly when the age limit passes, so the
  transition is logged on time, once per episode.
* **Beat only while healthy.** ``run(beat)`` calls ``beat`` while the link is connected and
  fresh, so a silent or unplugged device stops its supervisor's heartbeat;
  ``beat_while_reconnecting=True`` beats through outages instead, for a service whose
  health is judged elsewhere.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import os
from collections.abc import Callable
from typing import Any

import serial  # type: ignore[import-untyped]
from structlog.typing import FilteringBoundLogger

from drivers.wakeup import Wakeup

READ_CHUNK_BYTES = 4096
# A device the link cannot open (unplugged, another process holds it) is also a reason.
OPEN_ERRORS = (serial.SerialException, OSError)


def open_serial(port: str, baudrate_bps: int, **options: Any) -> Any:
    """``port`` opened non-blocking and exclusive, whatever queued before dropped (it is
    stale: nobody was listening). Raises `serial.SerialException` or `OSError` with the
    system's reason."""
    handle = serial.Serial(port, baudrate_bps, timeout=0, exclusive=True, **options)
    try:
        handle.reset_input_buffer()
    except OPEN_ERRORS:
        handle.close()
        raise
    return handle


class SerialLink(abc.ABC):
    """The connection, the reconnects and the staleness of one serial device; ``run`` is
    the supervised service.

    A subclass says how to open the port (`_open_port`), what a fresh connection resets
    (`_opened`), what the bytes are (`_received`, which calls `_counted` per message and
    `_fresh` when input is news), how old its newest input is (`age_s`), and what it does
    on each wake-up besides (`_tick`, which returns when it next needs one)."""

    stale_event = "input_stale"
    fresh_event = "input_fresh"

    def __init__(
        self,
        port: str,
        *,
        baudrate_bps: int,
        max_age_s: float,
        backoff_initial_s: float,
        backoff_cap_s: float,
        beat_while_reconnecting: bool,
        clock: Callable[[], float],
    ) -> None:
        self.port = port
        self.baudrate_bps = baudrate_bps
        self.max_age_s = max_age_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_cap_s = backoff_cap_s
        self.beat_while_reconnecting = beat_while_reconnecting
        self._clock = clock
        # Called with every chunk of bytes as read, and its receive time (the recorder).
        self.raw_listeners: list[Callable[[bytes, float], None]] = []
        # Called with (up, reason, time) each time the port opens or is lost.
        self.on_link: Callable[[bool, str, float], None] | None = None
        self._serial: Any = None
        self._fd: int | None = None
        self._lost = Wakeup()
        self._lost_reason = ""
        self._connected_s = 0.0
        self._stale_reported = False
        self._window_start_s = clock()
        self._window_count = 0
        self._rate_per_s = 0.0
        self.reconnects = 0
        self.stale_episodes = 0
        self.last_error = ""

    # ---- what a subclass says ------------------------------------------------------------
    @abc.abstractmethod
    def age_s(self, now_s: float) -> float:
        """How old the newest input is (infinite before the first)."""

    @abc.abstractmethod
    def _open_port(self) -> Any:
        """The port opened (`open_serial` with the device's options)."""

    @abc.abstractmethod
    def _received(self, data: bytes, now_s: float) -> None:
        """Bytes as read, with their receive time."""

    @abc.abstractmethod
    def _logger(self) -> FilteringBoundLogger:
        """The logger with the device's names bound."""

    @abc.abstractmethod
    def _opened(self) -> None:
        """A connection begins: parser state of the last one goes (a line or frame cut by
        the unplug must not be glued to the first bytes after it)."""

    @abc.abstractmethod
    def _tick(self, now_s: float) -> float:
        """The link's own duty at each wake-up (the actuators re-send their command); the
        time of the next wake-up it needs."""

    # ---- what the rest of the daemon calls -----------------------------------------------
    @property
    def connected(self) -> bool:
        return self._fd is not None

    def is_stale(self, now_s: float) -> bool:
        return self.age_s(now_s) > self.max_age_s

    async def run(self, beat: Callable[[], None]) -> None:
        """Connect, serve, reconnect, until cancelled."""
        backoff_s = self.backoff_initial_s
        down_since_s: float | None = None
        attempts = 0
        try:
            while True:
                try:
                    self._open()
                except OPEN_ERRORS as exc:
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
                if self.on_link is not None:
                    self.on_link(True, "open", self._connected_s)
                backoff_s, attempts = self.backoff_initial_s, 0
                reason = await self._serve(beat)
                self._close()
                self.last_error = reason
                down_since_s = self._clock()
                self._logger().warning("link_lost", error=reason)
                if self.on_link is not None:
                    self.on_link(False, reason, down_since_s)
        finally:
            self._close()

    # ---- for subclasses ------------------------------------------------------------------
    def _counted(self) -> None:
        """One message received (for the rate in ``health``)."""
        self._window_count += 1

    def _fresh(self) -> None:
        """Input arrived: a stale episode, if any, is over (logged now, not at the next
        wake-up: recovery is news now)."""
        if self._stale_reported:
            self._stale_reported = False
            self._logger().info(self.fresh_event)

    def _mark_lost(self, reason: str) -> None:
        if self._fd is not None:
            # Stop the callback now: a hung-up tty stays readable (EOF) forever.
            asyncio.get_running_loop().remove_reader(self._fd)
        self._lost_reason = reason
        self._lost.set()

    # ---- transport -----------------------------------------------------------------------
    def _open(self) -> None:
        port = self._open_port()
        self._serial = port
        self._fd = port.fileno()
        self._lost.clear()
        self._connected_s = self._clock()
        self._opened()
        asyncio.get_running_loop().add_reader(self._fd, self._on_readable)

    def _close(self) -> None:
        if self._fd is not None:
            asyncio.get_running_loop().remove_reader(self._fd)
            self._fd = None
        if self._serial is not None:
            # The device may already be gone; there is nothing left to release then.
            with contextlib.suppress(*OPEN_ERRORS):
                self._serial.close()
            self._serial = None

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
        self._received(data, now_s)

    # ---- the served connection -----------------------------------------------------------
    async def _serve(self, beat: Callable[[], None]) -> str:
        while True:
            now_s = self._clock()
            wake_s = self._tick(now_s)
            self._update_rate(now_s)
            stale = self._check_stale(now_s)
            if self._lost.is_set():
                return self._lost_reason
            if not stale or self.beat_while_reconnecting:
                beat()
            if not stale:  # wake exactly when the newest input goes stale, to log it on time
                wake_s = min(wake_s, now_s + self.max_age_s - self.age_s(now_s))
            await self._lost.wait(max(0.0, wake_s - self._clock()) + 1e-4)

    def _check_stale(self, now_s: float) -> bool:
        stale = self.is_stale(now_s)
        if stale and not self._stale_reported and now_s - self._connected_s > self.max_age_s:
            self._stale_reported = True
            self.stale_episodes += 1
            self._logger().warning(
                self.stale_event, age_s=round(self.age_s(now_s), 3), limit_s=self.max_age_s
            )
        return stale

    def _update_rate(self, now_s: float) -> None:
        elapsed_s = now_s - self._window_start_s
        if elapsed_s >= 1.0:
            self._rate_per_s = self._window_count / elapsed_s
            self._window_start_s, self._window_count = now_s, 0
