"""One open CAN link on python-can's own plumbing, and the failure rules both ends share.

A :class:`BusLink` is a ``can.Bus`` with a ``can.Notifier`` (on the running loop) feeding a
small buffered reader: with socketcan (and SLCAN) the notifier watches the file
descriptor from the event loop, with ``virtual`` it runs python-can's receive thread.
What python-can leaves to the application is deciding what a failure means:

* A send that fails for want of buffer space (``ENOBUFS``, which socketcan raises as
  ``can.CanOperationError`` when the controller cannot get frames out: bus-off, a
  missing peer, a flooded bus; or python-can's own "Transmit buffer full") is a
  **dropped frame**: counted, never retried. A retried command would be stale anyway;
  the next period brings a fresh one.
* Any other send or receive error (``ENETDOWN`` when the interface goes down, ``ENODEV``
  when an adapter is unplugged, ``EBADF``) means the link is lost: :class:`LinkLost`,
  and the owner closes the bus and opens a new one with backoff.

python-can reports receive errors to listeners only from its receive thread; on the
event-loop path an exception from ``bus.recv`` goes to the loop's exception handler and
the reader waits forever (python-can issue #1865). :class:`_ReportingNotifier` routes it
to the listeners like the threaded path does.
"""

from __future__ import annotations

import asyncio
import errno
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import can
from can.interfaces.virtual import VirtualBus

from drivers.pc104.endpoint import BusEndpoint, CanInterface
from drivers.pc104.slcan import SlcanHostBus
from drivers.wakeup import Wakeup

BusFactory = Callable[[], can.BusABC]
# How often python-can's receive thread (virtual bus) checks whether it should stop.
NOTIFIER_POLL_S = 0.05
# Frames read per readiness callback (see _ReportingNotifier); a bounded turn, so a flood
# cannot hold the loop: 64 frames is a few milliseconds of a saturated 1 Mbit/s bus.
MAX_FRAMES_PER_WAKE = 64
_DROP_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN})


class LinkLost(Exception):
    """The bus failed in a way that only closing and reopening it can fix."""


def bus_factory(endpoint: BusEndpoint, receive_ids: Iterable[int] = ()) -> BusFactory:
    """Open the configured bus. On socketcan the kernel filters for ``receive_ids`` (error
    frames still pass: they come through CAN_RAW_ERR_FILTER); the bitrate is the
    interface's business (systemd-networkd), not ours. On ``virtual`` python-can filters
    in its receive thread, so other nodes' traffic never reaches the event loop (as the
    kernel keeps it away on socketcan); error frames pass, as on socketcan, because the
    twin sends them to play a CAN controller."""
    ids = sorted(set(receive_ids))

    def open_bus() -> can.BusABC:
        filters: list[dict[str, Any]] = [
            {"can_id": i, "can_mask": 0x7FF, "extended": False} for i in ids
        ]
        if endpoint.interface is CanInterface.SOCKETCAN:
            return can.Bus(
                interface="socketcan", channel=endpoint.channel, can_filters=filters or None
            )
        if endpoint.interface is CanInterface.SLCAN:
            # SLCAN carries no error frames, so python-can's software filter loses nothing.
            # No adapter (yet) raises CanInitializationError: the owner retries with backoff.
            return SlcanHostBus(
                endpoint.channel, bitrate=endpoint.bitrate_bps, can_filters=filters or None
            )
        return _VirtualBus(channel=endpoint.channel, can_filters=filters or None)

    return open_bus


class _VirtualBus(VirtualBus):
    """python-can's virtual bus whose filters, like CAN_RAW_ERR_FILTER, pass error frames.

    Filtering matters on a loaded virtual bus: unfiltered, every frame of every node
    is handed from the receive thread to the event loop (``call_soon_threadsafe``, a
    wake-up write each), and a 4,000 frames/s load kept the daemon's loop 95 % busy
    (benchmarks/bench_control.py, profiled).
    """

    def _matches_filters(self, msg: can.Message) -> bool:
        return msg.is_error_frame or super()._matches_filters(msg)


class _ReportingNotifier(can.Notifier):
    """Reports receive errors (above), and reads every waiting frame per wake-up.

    python-can reads one frame per readiness callback, that is one per event-loop turn:
    a loop slowed below the bus's frame rate (a starved CPU, a long callback elsewhere)
    then falls behind for good, the kernel's receive buffer fills (278 frames with the
    default 212 KB, measured on vcan) and overflows, and the client sees counter jumps
    and exhausts its error budget: a link fault made by our own reading. Up to
    ``MAX_FRAMES_PER_WAKE`` per turn keeps up with any bus this side of a flood.
    """

    def _on_message_available(self, bus: can.BusABC) -> None:
        try:
            for _ in range(MAX_FRAMES_PER_WAKE):
                message = bus.recv(0)
                if message is None:
                    return
                self._on_message_received(message)
        except Exception as exc:
            self.exception = exc
            self._on_error(exc)


class _LinkReader(can.Listener):
    """Received frames in order, and the first receive error, for one awaiting task.

    Not ``can.AsyncBufferedReader``: its ``asyncio.Queue`` under ``asyncio.timeout`` costs
    four loop lookups (each a ``getpid()`` on Python 3.11) per frame awaited, and the
    client awaits about a hundred frames a second (see drivers/wakeup.py). The notifier
    calls this on the loop's thread (from its receive thread via ``call_soon_threadsafe``
    on the virtual bus), so the deque needs no lock.
    """

    def __init__(self) -> None:
        self.messages: deque[can.Message] = deque()
        self.error: Exception | None = None
        self.arrived = Wakeup()

    def on_message_received(self, msg: can.Message) -> None:
        self.messages.append(msg)
        self.arrived.notify()

    def on_error(self, exc: Exception) -> None:
        if self.error is None:
            self.error = exc
        self.arrived.notify()  # the owner's check() sees it now, not after its timeout

    def stop(self) -> None:
        pass


def is_drop(exc: Exception) -> bool:
    """A send error that costs this frame only (no buffer space), not the link."""
    if not isinstance(exc, can.CanOperationError):
        return False
    return exc.error_code is None or exc.error_code in _DROP_ERRNOS


@dataclass
class LinkCounts:
    sent: int = 0
    dropped: int = 0
    received: int = 0


class BusLink:
    """An open bus, its notifier and reader; created inside the running event loop."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        try:
            bus.fileno()
            self.threaded = False
        except NotImplementedError:
            self.threaded = True
        self.reader = _LinkReader()
        self.notifier = _ReportingNotifier(
            bus, [self.reader], timeout=NOTIFIER_POLL_S, loop=asyncio.get_running_loop()
        )
        self.counts = LinkCounts()
        self.last_send_error: Exception | None = None

    def check(self) -> None:
        """Raise LinkLost if the receive side has failed."""
        if self.reader.error is not None:
            raise LinkLost(f"receive failed: {self.reader.error}") from self.reader.error

    def poll(self) -> can.Message | None:
        """The next received message if one is waiting, without awaiting."""
        messages = self.reader.messages
        if not messages:
            return None
        self.counts.received += 1
        return messages.popleft()

    async def next_message(self, timeout_s: float) -> can.Message | None:
        """The next received message, or None after ``timeout_s`` (or a receive error)."""
        message = self.poll()
        if message is not None or timeout_s <= 0 or self.reader.error is not None:
            return message
        await self.reader.arrived.wait(timeout_s)
        return self.poll()

    def send(self, arbitration_id: int, data: bytes, *, is_error_frame: bool = False) -> bool:
        """Send one frame now: True if sent, False if dropped for want of buffer space.

        Never blocks (python-can's socketcan send polls with a zero timeout); raises
        LinkLost for any error that is not a full buffer.
        """
        message = can.Message(
            arbitration_id=arbitration_id,
            data=data,
            is_extended_id=False,
            is_error_frame=is_error_frame,
        )
        try:
            self.bus.send(message)
        except (can.CanError, OSError) as exc:
            self.last_send_error = exc
            if is_drop(exc):
                self.counts.dropped += 1
                return False
            raise LinkLost(f"send failed: {exc}") from exc
        self.counts.sent += 1
        return True

    def close(self) -> None:
        """Stop receiving and close the bus now; safe to call more than once."""
        self.notifier.stop(timeout=0.0)
        self.bus.shutdown()

    async def aclose(self) -> None:
        """Close, first letting python-can's receive thread (virtual bus) finish its poll
        in a worker thread, so the event loop never waits for it."""
        try:
            if self.threaded:
                await asyncio.to_thread(self.notifier.stop, 4 * NOTIFIER_POLL_S)
        finally:
            self.close()


class Episode:
    """A condition logged once when it starts and once when it ends, never per frame."""

    def __init__(self, log: Any, event: str) -> None:
        self.log = log
        self.event = event
        self.active = False
        self.events = 0
        self.started_s = 0.0

    def occur(self, now_s: float, **fields: Any) -> bool:
        """Record one occurrence; logs (and returns True) only for the first of an episode."""
        self.events += 1
        if self.active:
            return False
        self.active = True
        self.events = 1
        self.started_s = now_s
        self.log.warning(self.event, **fields)
        return True

    def clear(self, now_s: float, **fields: Any) -> None:
        if self.active:
            self.active = False
            self.log.info(
                f"{self.event}_ended",
                events=self.events,
                duration_s=round(now_s - self.started_s, 3),
                **fields,
            )


def next_deadline(deadline_s: float, period_s: float, now_s: float) -> float:
    """The next periodic deadline after ``deadline_s``; missed periods are skipped rather
    than sent in a burst (a burst of stale commands helps nobody)."""
    deadline_s += period_s
    if deadline_s <= now_s:
        deadline_s = now_s + period_s
    return deadline_s
