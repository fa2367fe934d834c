"""The asyncio LMS111 client: one scanner, forever, through whatever the link does.

``run(beat)`` is the supervised service: connect (with a timeout), log in, wait until the
scanner is up, configure, start, subscribe (`handshake.start_streaming`), then a
read-feed-drain loop around the sans-I/O core that publishes every scan as a `MountedScan`
and beats once per scan. What users of existing LMS1xx drivers report going wrong, and what
this loop does about it:

* **Link drops and silent stalls** (clearpath LMS1xx #23: "the node won't report an error,
  exit, nor reconnect"; #11: connected but never publishing): every read has a deadline of
  ``read_deadline_periods`` scan periods since the last *scan* (bytes that are not scans do
  not keep a dead stream alive); past it the session is dropped and rebuilt.
* **Reconnect** with exponential backoff (``backoff_initial_s`` doubling to
  ``backoff_cap_s``, reset once scans flow again), then log in and configure again: the
  device forgets subscriptions and user level with the TCP session.
* **A scanner still booting** refuses TCP or accepts and stays silent for up to ~30 s
  (sick_scan_xd #383): within ``boot_wait_s`` that is logged once at info level and retried
  quietly; an outage longer than that is logged once more, as an error.
* **Not ready** (``STlms`` not measuring): polled every ``ready_poll_s`` on the same
  connection, reported once, in `health` and `last_error`.
* **Refusals** (``sFA`` while configuring, a refused login, a rejected scan configuration)
  raise `Lms111ConfigError` out of ``run`` at once, naming the command and the SOPAS
  meaning, so the supervisor sees a crash with a reason rather than an endless reconnect
  loop (sick_scan_xd #227). "Server busy" is the exception: it is retried.
* **Damaged streams**: partial telegrams, several per read, garbage, truncated telegrams and
  bad checksums are the core's business (framing with resync); the client counts them and
  the scan counter gaps they leave (`dropped_scans`), and logs each kind once per episode
  (an episode ends after ``episode_quiet_s`` without a recurrence), never once per telegram.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final, Protocol

import structlog
from structlog.typing import FilteringBoundLogger

from drivers.lms111.cola import ErrorReply, ScanTelegram
from drivers.lms111.commands import ScanDataConfig
from drivers.lms111.errors import ProtocolError
from drivers.lms111.framing import Dialect
from drivers.lms111.handshake import StreamSettings, start_streaming
from drivers.lms111.mounted import MountedScan, SensorMount, mount_pose
from drivers.lms111.replies import DeviceStatus, LmsState, ScanConfig
from drivers.lms111.scan import Scan
from drivers.lms111.session import (
    BytesHook,
    Gate,
    Lms111ConfigError,
    Lms111LinkError,
    Lms111LoginError,
    Lms111Session,
)
from drivers.lms111.timebase import DeviceTimeUnwrapper
from drivers.topics import Topic

log: FilteringBoundLogger = structlog.get_logger(component="lms111")

Beat = Callable[[], None]
RATE_WINDOW_S: Final = 1.0
COUNTER_MODULUS: Final = 1 << 16

__all__ = ["Lms111Client", "Lms111ConfigError", "Lms111Health", "Lms111LoginError"]


@dataclass(frozen=True)
class Lms111Health:
    """A snapshot for status views and the safety layer."""

    connected: bool
    configured: bool  # logged in, configured, subscribed: scans are expected
    scans_per_s: float  # over the last second
    scans_total: int
    dropped_scans: int  # scan counter gaps (corrupted, skipped or lost telegrams)
    malformed_telegrams: int
    garbage_bytes: int
    reconnects: int  # times the stream came back after being lost
    last_error: str
    state: str = "starting"  # connecting, booting, not_ready, configuring, streaming, backoff
    scan_age_s: float = float("inf")  # since the last scan was received


class _Episodes:
    """Log a recurring condition once when it starts, not every time it recurs."""

    def __init__(self, scanner: str, quiet_s: float) -> None:
        self.scanner = scanner
        self.quiet_s = quiet_s
        self._last_s: dict[str, float] = {}
        self._counts: dict[str, int] = {}

    def occurred(self, key: str, now_s: float, event: str, **fields: Any) -> None:
        last_s = self._last_s.get(key)
        self._last_s[key] = now_s
        if last_s is not None and now_s - last_s <= self.quiet_s:
            self._counts[key] += 1
            return
        previous = self._counts.get(key, 0)
        self._counts[key] = 1
        log.warning(event, scanner=self.scanner, previous_episode_count=previous, **fields)


class Lms111Endpoint(Protocol):
    """The scanner's address and scan mode, as a vehicle file states them
    (``devices.lms111_left``); a protocol, so the driver names what it reads."""

    @property
    def host(self) -> str: ...

    @property
    def port(self) -> int: ...

    @property
    def scan_frequency_hz(self) -> int: ...

    @property
    def angular_resolution_deg(self) -> float: ...


class Lms111Client:
    """One LMS111 endpoint; ``run`` is the service, ``health`` the status."""

    def __init__(
        self,
        name: str,
        endpoint: Lms111Endpoint,
        mount: SensorMount,
        topic: Topic[MountedScan],
        *,
        dialect: Dialect = Dialect.COLA_A,
        clock: Callable[[], float] = time.monotonic,
        connect_timeout_s: float = 2.0,
        request_timeout_s: float = 2.0,
        boot_wait_s: float = 30.0,
        read_deadline_periods: float = 3,
        backoff_initial_s: float = 0.1,
        backoff_cap_s: float = 1.0,
        ready_poll_s: float = 1.0,
        episode_quiet_s: float = 5.0,
        beat_while_waiting: bool = False,
        before_decode: Gate | None = None,
    ) -> None:
        if read_deadline_periods <= 0 or backoff_initial_s <= 0:
            raise ValueError("read_deadline_periods and backoff_initial_s must be positive")
        self.name = name
        self.endpoint = endpoint
        self.mount = mount_pose(mount)
        self.topic = topic
        self.dialect = dialect
        self.before_decode = before_decode
        # Called with every chunk of bytes as read, and its receive time (the recorder).
        self.raw_listeners: list[BytesHook] = []
        self.settings = StreamSettings(
            endpoint.scan_frequency_hz,
            endpoint.angular_resolution_deg,
            data=ScanDataConfig(remission=True, remission_16bit=True),
        )
        self.connect_timeout_s = connect_timeout_s
        self.request_timeout_s = request_timeout_s
        self.boot_wait_s = boot_wait_s
        self.read_deadline_periods = read_deadline_periods
        self.backoff_initial_s = backoff_initial_s
        self.backoff_cap_s = backoff_cap_s
        self.ready_poll_s = ready_poll_s
        self.beat_while_waiting = beat_while_waiting
        self._clock = clock
        self._episodes = _Episodes(name, episode_quiet_s)
        self._unwrapper = DeviceTimeUnwrapper()
        self._session: Lms111Session | None = None
        self._state = "starting"
        self._connected = False
        self._configured = False
        self._scans_total = 0
        self._dropped_scans = 0
        self._malformed_before = 0  # from sessions that have ended
        self._garbage_before = 0
        self._garbage_seen = 0
        self._reconnects = 0
        self._last_error = ""
        self._last_counter: int | None = None
        self._last_scan_s: float | None = None
        self._recent_s: deque[float] = deque()
        self._streamed_ever = False
        self._outage_since_s: float | None = None
        self._outage_escalated = False
        self._not_ready_since_s: float | None = None
        self._not_ready_escalated = False
        self._backoff_s = 0.0
        self.applied_config: ScanConfig | None = None

    # ---- status ----------------------------------------------------------------------
    @property
    def health(self) -> Lms111Health:
        now_s = self._clock()
        self._prune_rate(now_s)
        connection = self._session.connection if self._session is not None else None
        return Lms111Health(
            connected=self._connected,
            configured=self._configured,
            scans_per_s=len(self._recent_s) / RATE_WINDOW_S,
            scans_total=self._scans_total,
            dropped_scans=self._dropped_scans,
            malformed_telegrams=self._malformed_before
            + (connection.malformed_telegrams if connection else 0),
            garbage_bytes=self._garbage_before + (connection.garbage_bytes if connection else 0),
            reconnects=self._reconnects,
            last_error=self._last_error,
            state=self._state,
            scan_age_s=now_s - self._last_scan_s if self._last_scan_s is not None else float("inf"),
        )

    def _prune_rate(self, now_s: float) -> None:
        while self._recent_s and self._recent_s[0] <= now_s - RATE_WINDOW_S:
            self._recent_s.popleft()

    # ---- the service -----------------------------------------------------------------
    async def run(self, beat: Beat) -> None:
        """Stream scans until cancelled; `Lms111ConfigError` if the scanner refuses us."""
        log.info(
            "lms111_starting",
            scanner=self.name,
            endpoint=f"{self.endpoint.host}:{self.endpoint.port}",
            dialect=self.dialect.value,
            scan_frequency_hz=self.settings.scan_frequency_hz,
            angular_resolution_deg=self.settings.angular_resolution_deg,
        )
        try:
            while True:
                if self._backoff_s > 0:
                    self._state = "backoff"
                    await self._wait(self._backoff_s, beat)
                try:
                    await self._one_session(beat)
                except Lms111ConfigError as exc:
                    self._last_error = str(exc)
                    self._state = "failed"
                    log.error(
                        "lms111_refused",
                        scanner=self.name,
                        command=exc.command,
                        code=exc.code,
                        meaning=exc.meaning,
                    )
                    raise
                except Lms111LinkError as exc:
                    self._link_failed(str(exc))
                self._backoff_s = min(
                    self.backoff_cap_s, max(self.backoff_initial_s, 2.0 * self._backoff_s)
                )
        finally:
            self._connected = self._configured = False

    async def _wait(self, seconds: float, beat: Beat) -> None:
        """Sleep; when told to, keep beating so the supervisor sees a live service."""
        if not self.beat_while_waiting:
            await asyncio.sleep(seconds)
            return
        end_s = self._clock() + seconds
        while (left_s := end_s - self._clock()) > 0:
            beat()
            await asyncio.sleep(min(left_s, 0.25))
        beat()

    def _on_bytes(self, data: bytes, receive_time_s: float) -> None:
        for listener in self.raw_listeners:
            listener(data, receive_time_s)

    async def _one_session(self, beat: Beat) -> None:
        self._state = "booting" if not self._streamed_ever else "connecting"
        session = await Lms111Session.connect(
            self.endpoint.host,
            self.endpoint.port,
            self.dialect,
            connect_timeout_s=self.connect_timeout_s,
            clock=self._clock,
            request_timeout_s=self.request_timeout_s,
            on_protocol_error=self._on_protocol_error,
            on_bytes=self._on_bytes,
        )
        self._session = session
        session.before_decode = self.before_decode
        self._connected = True
        self._garbage_seen = 0
        self._last_counter = None  # counters restart meaning with every session
        try:
            self._state = "configuring"
            self.applied_config = await start_streaming(
                session,
                self.settings,
                ready_poll_s=self.ready_poll_s,
                on_not_ready=lambda status: self._on_not_ready(status, beat),
                scanner=self.name,
            )
            self._configured = True
            self._ready_again()
            await self._stream(session, self.applied_config, beat)
        finally:
            self._connected = self._configured = False
            self._malformed_before += session.connection.malformed_telegrams
            self._garbage_before += session.connection.garbage_bytes
            self._session = None
            await session.close()

    async def _stream(self, session: Lms111Session, applied: ScanConfig, beat: Beat) -> None:
        period_s = 100.0 / applied.scan_frequency_100th_hz
        deadline_s = self.read_deadline_periods * period_s
        # The first scan may take a little longer than a period after the subscription.
        last_scan_s = self._clock() + max(deadline_s, self.request_timeout_s) - deadline_s
        while session.queued_scans:
            self._publish(session.queued_scans.popleft(), beat)
            last_scan_s = self._clock()
        while True:
            remaining_s = last_scan_s + deadline_s - self._clock()
            try:
                events = await session.read_events(remaining_s)
            except TimeoutError:
                # If this process's event loop was blocked past the deadline, the timer can
                # fire before data that did arrive is read: look once more, without waiting,
                # so only the scanner's silence counts as a stall, not our own.
                try:
                    events = await session.read_events(0.0)
                except TimeoutError:
                    raise Lms111LinkError(
                        f"stalled: no scan for {self.read_deadline_periods:g} scan periods "
                        f"({deadline_s * 1e3:.0f} ms)"
                    ) from None
            for event in events:
                if isinstance(event, ScanTelegram):
                    self._publish(event.scan, beat)
                    last_scan_s = self._clock()
                elif isinstance(event, ErrorReply):
                    self._episodes.occurred(
                        "sfa", self._clock(), "lms111_unsolicited_sfa", meaning=event.meaning
                    )
            garbage = session.connection.garbage_bytes
            if garbage > self._garbage_seen:
                self._episodes.occurred(
                    "garbage", self._clock(), "lms111_garbage", bytes_dropped=garbage
                )
                self._garbage_seen = garbage

    # ---- events ------------------------------------------------------------------------
    def _publish(self, scan: Scan, beat: Beat) -> None:
        now_s = scan.host_receive_time_s if scan.host_receive_time_s is not None else self._clock()
        if self._last_counter is not None:
            gap = (scan.scan_counter - self._last_counter - 1) % COUNTER_MODULUS
            if 0 < gap < COUNTER_MODULUS // 2:
                self._dropped_scans += gap
                self._episodes.occurred(
                    "dropped", now_s, "lms111_scans_dropped", missing=gap, at=scan.scan_counter
                )
            elif gap:
                self._episodes.occurred(
                    "counter", now_s, "lms111_scan_counter_jumped_back", at=scan.scan_counter
                )
        self._last_counter = scan.scan_counter
        device_time_us = self._unwrapper.update(scan.device_time_us, now_s)
        if self._state != "streaming":
            self._first_scan(now_s)
        self._scans_total += 1
        self._last_scan_s = now_s
        self._recent_s.append(now_s)
        self._prune_rate(now_s)
        mounted = MountedScan(scan, self.name, self.mount, now_s, device_time_us)
        self.topic.publish(mounted, now_s)
        beat()

    def _first_scan(self, now_s: float) -> None:
        """Scans flow (again): close the outage, reset the backoff, say so once."""
        self._state = "streaming"
        self._backoff_s = 0.0
        outage_s = now_s - self._outage_since_s if self._outage_since_s is not None else 0.0
        if self._streamed_ever:
            self._reconnects += 1
        log.info(
            "lms111_streaming",
            scanner=self.name,
            reconnect=self._streamed_ever,
            outage_s=round(outage_s, 3),
            scan_frequency_hz=self.applied_config.scan_frequency_hz if self.applied_config else 0,
            angular_resolution_deg=(
                self.applied_config.angular_resolution_deg if self.applied_config else 0
            ),
        )
        self._streamed_ever = True
        self._outage_since_s = None
        self._outage_escalated = False

    def _link_failed(self, reason: str) -> None:
        now_s = self._clock()
        self._last_error = reason
        self._state = "backoff"
        if self._outage_since_s is None:
            self._outage_since_s = now_s
            self._outage_escalated = False
            if self._streamed_ever:
                log.warning("lms111_link_lost", scanner=self.name, reason=reason)
            else:  # at power-up the scanner boots for up to ~30 s: expected, not a fault
                log.info(
                    "lms111_waiting_for_scanner",
                    scanner=self.name,
                    reason=reason,
                    boot_wait_s=self.boot_wait_s,
                )
        elif not self._outage_escalated and now_s - self._outage_since_s > self.boot_wait_s:
            self._outage_escalated = True
            log.error(
                "lms111_unreachable",
                scanner=self.name,
                for_s=round(now_s - self._outage_since_s, 1),
                reason=reason,
            )
        else:
            log.debug("lms111_retry", scanner=self.name, reason=reason)

    def _on_not_ready(self, status: DeviceStatus, beat: Beat) -> None:
        now_s = self._clock()
        try:
            state_name = LmsState(status.state).name.lower()
        except ValueError:
            state_name = "unknown"
        self._state = "not_ready"
        self._last_error = f"not ready: STlms state {status.state} ({state_name})"
        if self.beat_while_waiting:
            beat()
        if self._not_ready_since_s is None:
            self._not_ready_since_s = now_s
            self._not_ready_escalated = False
            log.warning(
                "lms111_not_ready", scanner=self.name, state=status.state, state_name=state_name
            )
        elif not self._not_ready_escalated and now_s - self._not_ready_since_s > self.boot_wait_s:
            self._not_ready_escalated = True
            log.error(
                "lms111_still_not_ready",
                scanner=self.name,
                for_s=round(now_s - self._not_ready_since_s, 1),
                state=status.state,
            )

    def _ready_again(self) -> None:
        if self._not_ready_since_s is not None:
            log.info("lms111_ready", scanner=self.name)
        self._not_ready_since_s = None

    def _on_protocol_error(self, exc: ProtocolError) -> None:
        self._episodes.occurred(
            "malformed", self._clock(), "lms111_malformed_telegram", error=str(exc)
        )
