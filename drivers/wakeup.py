"""A flag that callbacks set and one task awaits with a deadline, at the cost of one timer.

Why not ``async with asyncio.timeout(t): await event.wait()``: on Python 3.11 that costs
four ``get_running_loop()`` calls (each a ``getpid()`` system call), two clock reads and
the Timeout's cancel/uncancel bookkeeping, and the drivers' serve loops waited this way
about 350 times a second (four actuator boards at 50 Hz, the PC104 per frame; counted
with tools/count_calls.py): some 1,400 getpid() a second. On a PC that is cheap; inside
user-mode Linux, where the HIL tests run and every system call is trapped (about 30 us
measured), it is some 40 ms of every second of the guest's one CPU, on top of the
clock reads.
A :class:`Wakeup` keeps the loop it was made on, so a wait is one future and one
``call_later``: no lookups, one clock read (``call_later``'s own).

Only for use on the loop's own thread (callbacks of ``add_reader``, python-can's notifier
with a loop, other tasks); it is not thread-safe.
"""

from __future__ import annotations

import asyncio


def _expire(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


class Wakeup:
    """``set()`` wakes the waiter now; ``wait(timeout_s)`` returns whether it was set."""

    def __init__(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """``loop``: the loop of every wait; None binds the running one at the first."""
        self._loop = loop  # bound at the first wait when not given
        self._is_set = False
        self._waiter: asyncio.Future[None] | None = None

    def is_set(self) -> bool:
        return self._is_set

    def set(self) -> None:
        self._is_set = True
        self.notify()

    def clear(self) -> None:
        self._is_set = False

    def notify(self) -> None:
        """Wake the waiter without setting the flag (news for it, not a state)."""
        waiter = self._waiter
        if waiter is not None and not waiter.done():
            waiter.set_result(None)

    async def wait(self, timeout_s: float) -> bool:
        """Until set, notified, or ``timeout_s`` passed (at once if <= 0); True if set.

        One waiter at a time: a second concurrent wait is a programming error.
        """
        if self._is_set:
            return True
        if timeout_s <= 0.0:
            return False
        if self._waiter is not None:
            raise RuntimeError("Wakeup already has a waiter")
        loop = self._loop
        if loop is None or loop.is_closed():  # first wait, or an object outliving its loop
            loop = self._loop = asyncio.get_running_loop()
        waiter: asyncio.Future[None] = loop.create_future()
        timer = loop.call_later(timeout_s, _expire, waiter)
        self._waiter = waiter
        try:
            await waiter
        finally:
            timer.cancel()
            self._waiter = None
        return self._is_set
