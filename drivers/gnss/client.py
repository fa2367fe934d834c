"""The asyncio side of a GNSS/INS receiver: a serial read-feed-drain loop around `NmeaReceiver`.

The port is served as the actuator boards' are (`drivers.serial_link`: no thread, no
executor), so each sentence is parsed the moment its line end arrives and handed on stamped
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

import math
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
from drivers.serial_link import SerialLink, open_serial

log: FilteringBoundLogger = structlog.get_logger(component="gnss")

# The rates NMEA 0183 receivers offer: 4800 is the standard's, the rest what GNSS/INS units
# are set to for 10-20 Hz output with several sentences per epoch.
BAUDRATES_BPS: Final = (4800, 9600, 19200, 38400, 57600, 115_200, 230_400, 460_800, 921_600)
DEFAULT_BAUDRATE_BPS: Final = 115_200
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
    return open_serial(
        port,
        baudrate_bps,
        bytesize=serial.EIGHTBITS,
        parity=serial.PARITY_NONE,
        stopbits=serial.STOPBITS_ONE,
    )


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


class GnssClient(SerialLink):
    """One receiver on one serial port; ``run(beat)`` is the supervised service.

    ``beat`` (see `SerialLink.run`) is called every `BEAT_PERIOD_S` at least while events
    arrive in time; ``beat_while_reconnecting=True`` suits a daemon that judges the fix by
    its age in the safety layer rather than by service restarts.
    """

    stale_event = "nmea_stale"
    fresh_event = "nmea_fresh"

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
        super().__init__(
            port,
            baudrate_bps=baudrate_bps,
            max_age_s=max_age_s,
            backoff_initial_s=backoff_initial_s,
            backoff_cap_s=backoff_cap_s,
            beat_while_reconnecting=beat_while_reconnecting,
            clock=clock,
        )
        self._publish = publish
        if tap is not None:
            self.raw_listeners.append(tap)
        self.on_link = on_link
        self.receiver = NmeaReceiver()
        self._earlier_rejects: Counter[str] = Counter()  # of the receivers of past connections
        self._earlier_garbage_bytes = 0
        self._earlier_bad: tuple[bytes, str] | None = None
        self._last_event_s = -math.inf
        self.events_by_sentence: Counter[str] = Counter()
        self.bytes_received = 0

    # ---- what the rest of the daemon calls -----------------------------------------------
    def age_s(self, now_s: float) -> float:
        return now_s - self._last_event_s

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
            last_event_age_s=self.age_s(now),
            events_per_s=self._rate_per_s,
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

    # ---- the link -------------------------------------------------------------------------
    def _logger(self) -> FilteringBoundLogger:
        return log.bind(port=self.port)

    def _open_port(self) -> Any:
        return open_port(self.port, self.baudrate_bps)

    def _opened(self) -> None:
        self._new_receiver()

    def _new_receiver(self) -> None:
        """A fresh parser per connection (a line cut by the unplug must not be glued to the
        first bytes after it), with the old one's counts kept."""
        old = self.receiver
        self._earlier_rejects += old.counts
        self._earlier_garbage_bytes += old.garbage_bytes
        if old.last_bad_line is not None:
            self._earlier_bad = (old.last_bad_line, str(old.last_bad_reason))
        self.receiver = NmeaReceiver()

    def _received(self, data: bytes, now_s: float) -> None:
        self.bytes_received += len(data)
        receiver = self.receiver
        receiver.receive_data(data)
        while (event := receiver.next_event()) is not None:
            self.events_by_sentence[sentence_name(event)] += 1
            self._counted()
            self._last_event_s = now_s
            self._publish(event, now_s)
        if self._last_event_s == now_s:
            self._fresh()

    def _tick(self, now_s: float) -> float:
        return now_s + BEAT_PERIOD_S
