"""The link's receive side: every waiting frame per wake-up, in order, and errors wake it."""

from __future__ import annotations

import asyncio
import os

import can

from drivers.pc104.link import MAX_FRAMES_PER_WAKE, BusLink


class QueuedBus(can.BusABC):
    """A bus whose frames are all waiting already (a loop that fell behind the bus)."""

    def __init__(self, count: int) -> None:
        super().__init__(channel="queued")
        self.waiting = [can.Message(arbitration_id=0x100, data=[i % 256]) for i in range(count)]
        self.fail: Exception | None = None
        # A descriptor that never becomes readable: the notifier takes its event-loop
        # path (as with socketcan) and the test calls the readiness callback itself.
        self._read_fd, self._write_fd = os.pipe()

    def fileno(self) -> int:
        return self._read_fd

    def shutdown(self) -> None:
        super().shutdown()
        for fd in (self._read_fd, self._write_fd):
            os.close(fd)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.fail is not None:
            raise self.fail
        return (self.waiting.pop(0) if self.waiting else None), False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        pass


async def test_one_wake_reads_every_waiting_frame_up_to_the_bound() -> None:
    bus = QueuedBus(MAX_FRAMES_PER_WAKE + 10)
    link = BusLink(bus)
    try:
        link.notifier._on_message_available(bus)
        got = [link.poll() for _ in range(MAX_FRAMES_PER_WAKE)]
        assert [m.data[0] for m in got if m is not None] == list(range(MAX_FRAMES_PER_WAKE))
        assert link.poll() is None  # the rest waits for the next turn of the loop
        link.notifier._on_message_available(bus)
        rest = await link.next_message(0.0)
        assert rest is not None and rest.data[0] == MAX_FRAMES_PER_WAKE
        assert link.counts.received == MAX_FRAMES_PER_WAKE + 1
    finally:
        link.close()


async def test_waiting_for_a_frame_times_out_and_wakes_on_one() -> None:
    bus = QueuedBus(0)
    link = BusLink(bus)
    try:
        assert await link.next_message(0.01) is None
        loop = asyncio.get_running_loop()
        bus.waiting.append(can.Message(arbitration_id=0x101, data=[7]))
        loop.call_later(0.01, link.notifier._on_message_available, bus)
        started = loop.time()
        message = await link.next_message(10.0)
        assert message is not None and message.arbitration_id == 0x101
        assert loop.time() - started < 5.0
    finally:
        link.close()


async def test_a_receive_error_wakes_the_waiter_and_is_kept() -> None:
    bus = QueuedBus(0)
    link = BusLink(bus)
    try:
        bus.fail = can.CanOperationError("receive failed", error_code=19)
        loop = asyncio.get_running_loop()
        loop.call_later(0.01, link.notifier._on_message_available, bus)
        started = loop.time()
        assert await link.next_message(10.0) is None
        assert loop.time() - started < 5.0
        assert link.reader.error is bus.fail
    finally:
        link.close()
