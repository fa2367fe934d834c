"""The asyncio side of a GNSS/INS receiver: a serial read-feed-drain loop around `NmeaReceiver`.

The port is opened with pyserial (baud rate, raw 8N1, exclusive lock) and served with
``loop.add_reader`` on its non-blocking descriptor, as the actuator boards are: no thread, no
executor, so each sentence is parsed the moment its line end arrives and handed on stamped
with that receive time (the fix estimate subtracts the receiver's latency from it). The client
sends nothing: a receiver is configured once, with its own tool, and then only talks.

What it owes the rest of the daemon:

* **Every event, with its receive time**, to the ``publish(event, stamp_s)`` it was given
  (``Topic.publish`` fits), in the order the lines arrived.
* **Survive the cable.** EOF, EIO or a vanished device ends the episode with one warning and
  a reason; the port is reopened with exponential backoff (quietly) and counted as a
  reconnect when it is back. Garbage and damaged lines never stop it: `NmeaReceiver` counts
  them by reason, and those counts survive reconnects.
* **Say how it is doing**: `health()` for ``dbw status`` and the safety layer: connected,
  age of the newest event, events per second and per sentence, rejects by reason, the last
  bad line, bytes, reconnects.

Whether a fix is good enough to steer by is not decided here: quality, sigma and age travel
with the events to the safety layer.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Final

import serial  # type: ignore[import-untyped]
import structlog
from structlog.typing import FilteringBoundLogger

from drivers.gnss.nmea import NmeaReceiver, Reject
from drivers.gnss.sentences import GgaFix, GstError, Heading, NmeaEvent, RmcFix, VtgVelocity
from drivers.ptylink import SIM_PORT_PREFIX
from drivers.wakeup import Wakeup

log: FilteringBoundLogger = structlog.get_logger(component="gnss")

# The rates NMEA 0183 receivers offer: 4800 is the standard's, the rest what GNSS/INS units
# are set to for 10-20 Hz output with several sentences per epoch.
BAUDRATES_BPS: Final = (4800, 9600, 19200, 38400, 57600, 115_200, 230_400, 460_800, 921_600)
DEFAULT_BAUDRATE_BPS: Final = 115_200
READ_CHUNK_BYTES: Final = 4096
BEAT_PERIOD_S: Final = 0.2  # well inside the supervisor's driver heartbeat deadline


_SENTENCE_OF_EVENT: Final[Mapping[type[Any], str]] = {
    GgaFix: "GGA",
    RmcFix: "RMC",
    VtgVelocity: "VTG",
    GstError: "GST",
}


def sentence_name(event: NmeaEvent) -> str:
    """The sentence type an event came from: GGA, RMC, VTG, HDT, THS or GST."""
    if isinstance(event, Heading):
        return event.sentence
    return _SENTENCE_OF_EVENT[type(event)]


def open_port(port: str, baudrate_bps: int) -> Any:
    """The port as the client opens it (8N1, non-blocking, exclusive), stale input dropped.

    Raises `serial.SerialException` or `OSError` with the system's reason; ``dbw gnss probe``
    calls it too, so what it reports is what the daemon will meet.
    """
    if baudrate_bps not in BAUDRATES_BPS:
        raise ValueError(f"baud rate {baudrate_bps} is not one of {BAUDRATES_BPS}")
    handle = serial.Serial(
        port,
        baudrate_bps,
        bytesize=serial.EIGHTBITS,
        parity=serial.PARITY_NONE,
        stopbits=serial.STOPBITS_ONE,
        timeout=0,
        exclusive=True,
    )
    try:
        handle.reset_input_buffer()  # whatever queued while nobody listened is old news
    except (serial.SerialException, OSError):
        handle.close()
        raise
    return handle


@dataclass(frozen=True)
class GnssHealth:
    """A snapshot for ``dbw status`` and the safety layer. Counts run since the client was
    made, across reconnects."""

    port: str
    connected: bool
    stale: bool
    last_event_age_s: float  # infinite before the first event
    events_per_s: float
    events_ok: int
    events_by_sentence: Mapping[str, int]
    rejects: Mapping[str, int]  # by `Reject` reason, ``ignored_type`` included
    error_count: int  # rejects except ``ignored_type``
    last_bad_line: str
    last_bad_reason: str
    bytes_received: int
    garbage_bytes: int
    reconnects: int
    last_error: str

    @property
    def healthy(self) -> bool:
        return self.connected and not self.stale


class GnssClient:
    """One receiver on one serial port; ``run(beat)`` is the supervised service."""

    def __init__(
        self,
        port: str,
        publish: Callable[[NmeaEvent, float], object],
        *,
        baudrate_bps: int = DEFAULT_BAUDRATE_BPS,
        max_age_s: float = 0.5,
        backoff_initial_s: float = 0.05,
        backoff_cap_s: float = 1.0,
        beat_while_reconnecting: bool = False,
        tap: Callable[[bytes, float], None] | None = None,
        on_link: Callable[[bool, str, float], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        """``publish(event, receive_time_s)`` gets every event; ``tap(data, receive_time_s)``
        every chunk as read (for a raw recorder); ``on_link(up, reason, now_s)`` each time the
        port opens or is lost. ``max_age_s``: older than this, the stream is stale."""
        if port.startswith(SIM_PORT_PREFIX):
            raise ValueError(f"{port!r} must be resolved to a tty path (the twin's port_path)")
        if baudrate_bps not in BAUDRATES_BPS:
            raise ValueError(f"baud rate {baudrate_bps} is not one of {BAUDRATES_BPS}")
        self.port = port
        self.baudrate_bps = baudrate_bps
        self.max_age_s = max_age_s
        self.backoff_initial_s = backoff_initial_s
        self.backoff_cap_s = backoff_cap_s
        self.beat_while_reconnecting = beat_while_reconnecting
        self._publish = publish
        self._tap = tap
        # Called with every chunk of bytes as read, and its receive time (the recorder).
        self.raw_listeners: list[Callable[[bytes, float], None]] = []
        self._on_link = on_link
        self._clock = clock
        self.receiver = NmeaReceiver()
        self._earlier_rejects: Counter[str] = Counter()  # of the receivers of past connections
        self._earlier_garbage_bytes = 0
        self._earlier_bad: tuple[bytes, str] | None = None
        self._serial: Any = None
        self._fd: int | None = None
        self._lost = Wakeup()
        self._lost_reason = ""
        self._connected_s = 0.0
        self._last_event_s = -math.inf
        self._stale_reported = False
        self._window_start_s = clock()
        self._window_events = 0
        self._events_per_s = 0.0
        self.events_by_sentence: Counter[str] = Counter()
        self.bytes_received = 0
        self.reconnects = 0
        self.last_error = ""

    # ---- what the rest of the daemon calls -----------------------------------------------
    @property
    def connected(self) -> bool:
        return self._fd is not None

    def last_event_age_s(self, now_s: float) -> float:
        return now_s - self._last_event_s

    def is_stale(self, now_s: float) -> bool:
        return self.last_event_age_s(now_s) > self.max_age_s

    def rejects(self) -> Counter[str]:
        """Rejected lines by reason, over every connection so far."""
        return self._earlier_rejects + self.receiver.counts

    def health(self, now_s: float | None = None) -> GnssHealth:
        now = self._clock() if now_s is None else now_s
        rejects = self.rejects()
        bad_line, bad_reason = b"", ""
        if self.receiver.last_bad_line is not None:
            bad_line, bad_reason = self.receiver.last_bad_line, str(self.receiver.last_bad_reason)
        elif self._earlier_bad is not None:
            bad_line, bad_reason = self._earlier_bad
        return GnssHealth(
            port=self.port,
            connected=self.connected,
            stale=self.is_stale(now),
            last_event_age_s=self.last_event_age_s(now),
            events_per_s=self._events_per_s,
            events_ok=sum(self.events_by_sentence.values()),
            events_by_sentence=MappingProxyType(dict(self.events_by_sentence)),
            rejects=MappingProxyType(dict(rejects)),
            error_count=sum(n for r, n in rejects.items() if r != Reject.IGNORED_TYPE),
            last_bad_line=bad_line.decode("ascii", "backslashreplace"),
            last_bad_reason=bad_reason,
            bytes_received=self.bytes_received,
            garbage_bytes=self._earlier_garbage_bytes + self.receiver.garbage_bytes,
            reconnects=self.reconnects,
            last_error=self.last_error,
        )

    async def run(self, beat: Callable[[], None]) -> None:
        """Connect, serve, reconnect, until cancelled.

        ``beat`` is called (every `BEAT_PERIOD_S` at least) while events arrive in time. A
        receiver that is unplugged or silent stops the heartbeat and the supervisor decides;
        ``beat_while_reconnecting=True`` beats through outages instead, for a daemon that
        judges the fix by its age in the safety layer rather than by service restarts.
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
                if self._on_link is not None:
                    self._on_link(True, "open", self._connected_s)
                backoff_s, attempts = self.backoff_initial_s, 0
                reason = await self._serve(beat)
                self._close()
                self.last_error = reason
                down_since_s = self._clock()
                self._logger().warning("link_lost", error=reason)
                if self._on_link is not None:
                    self._on_link(False, reason, down_since_s)
        finally:
            self._close()

    # ---- transport -----------------------------------------------------------------------
    def _logger(self) -> FilteringBoundLogger:
        return log.bind(port=self.port)

    def _open(self) -> None:
        port = open_port(self.port, self.baudrate_bps)
        self._serial = port
        self._fd = port.fileno()
        self._new_receiver()
        self._lost.clear()
        self._connected_s = self._clock()
        asyncio.get_running_loop().add_reader(self._fd, self._on_readable)

    def _new_receiver(self) -> None:
        """A fresh parser per connection (a line cut by the unplug must not be glued to the
        first bytes after it), with the old one's counts kept."""
        old = self.receiver
        self._earlier_rejects += old.counts
        self._earlier_garbage_bytes += old.garbage_bytes
        if old.last_bad_line is not None:
            self._earlier_bad = (old.last_bad_line, str(old.last_bad_reason))
        self.receiver = NmeaReceiver()

    def _close(self) -> None:
        if self._fd is not None:
            asyncio.get_running_loop().remove_reader(self._fd)
            self._fd = None
        if self._serial is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                self._serial.close()  # the device may be gone already
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
        self.bytes_received += len(data)
        if self._tap is not None:
            self._tap(data, now_s)
        for listener in self.raw_listeners:
            listener(data, now_s)
        receiver = self.receiver
        receiver.receive_data(data)
        while (event := receiver.next_event()) is not None:
            self.events_by_sentence[sentence_name(event)] += 1
            self._window_events += 1
            self._last_event_s = now_s
            self._publish(event, now_s)
        if self._stale_reported and self._last_event_s == now_s:
            self._stale_reported = False
            self._logger().info("nmea_fresh")

    # ---- the served connection -----------------------------------------------------------
    async def _serve(self, beat: Callable[[], None]) -> str:
        while True:
            now_s = self._clock()
            self._update_rate(now_s)
            stale = self._check_stale(now_s)
            if self._lost.is_set():
                return self._lost_reason
            if not stale or self.beat_while_reconnecting:
                beat()
            wake_s = now_s + BEAT_PERIOD_S
            if not stale:  # wake exactly when the newest event goes stale, to log it on time
                wake_s = min(wake_s, self._last_event_s + self.max_age_s)
            await self._lost.wait(max(0.0, wake_s - self._clock()) + 1e-4)

    def _check_stale(self, now_s: float) -> bool:
        stale = self.is_stale(now_s)
        if stale and not self._stale_reported and now_s - self._connected_s > self.max_age_s:
            self._stale_reported = True
            age_s = self.last_event_age_s(now_s)
            self._logger().warning(
                "nmea_stale",
                age_s=round(age_s, 3) if math.isfinite(age_s) else None,
                limit_s=self.max_age_s,
            )
        return stale

    def _update_rate(self, now_s: float) -> None:
        elapsed_s = now_s - self._window_start_s
        if elapsed_s >= 1.0:
            self._events_per_s = self._window_events / elapsed_s
            self._window_start_s, self._window_events = now_s, 0
