"""Fixed-rate scheduling with measured jitter and overruns.

A control loop that sleeps ``period`` after each step drifts by the step's duration; this
one schedules against absolute deadlines (``start + n * period``) and, when it falls
behind, skips the missed ticks instead of bursting to catch up, counting each as an
overrun. Jitter (actual minus scheduled wake-up) is kept in a bounded window so its
percentiles can be reported without the memory growing over a day's run.

Two things keep the wake-up itself on time. The ticker sleeps on a timerfd armed at the
deadline (appliance/timerfd.py), not on asyncio's millisecond timer. And deferrable work
that would otherwise run into the deadline waits for the cycle (:class:`ControlSlot`).
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from appliance.timerfd import open_timerfd

# How far behind a timerfd deadline the loop's own timer wakes the ticker anyway.
BACKSTOP_S = 0.002


class SampleWindow:
    """The last ``capacity`` samples in a preallocated ring, with cheap percentiles.

    Why not a deque and ``np.percentile``: the heartbeat takes percentiles of two
    5,000-sample windows every second on the event loop, and that cost 0.78 ms a beat
    (the deque's copy into an array, then ``np.percentile``'s own overhead, 0.12 ms of its
    0.15). Here a sample is one store into the ring and a percentile one
    ``np.partition`` of the filled part (0.03 ms), interpolated as ``np.percentile``'s
    default ("linear") method does, which the tests check it against.
    """

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1 (got {capacity})")
        self._data = np.empty(capacity, dtype=np.float64)
        self._next = 0
        self._count = 0

    def reset(self) -> None:
        self._next = 0
        self._count = 0

    def __len__(self) -> int:
        return self._count

    def append(self, value: float) -> None:
        self._data[self._next] = value
        self._next = (self._next + 1) % len(self._data)
        self._count = min(self._count + 1, len(self._data))

    def values(self) -> np.ndarray:
        """The samples kept (oldest first is not promised: percentiles need no order)."""
        return self._data[: self._count]

    def percentiles(self, qs: Sequence[float]) -> list[float]:
        """``np.percentile(values, qs)`` (linear interpolation); NaN for each if empty."""
        n = self._count
        if n == 0:
            return [math.nan for _ in qs]
        positions = [min(max(q, 0.0), 100.0) / 100.0 * (n - 1) for q in qs]
        below = [math.floor(p) for p in positions]
        above = [min(b + 1, n - 1) for b in below]
        ranked = np.partition(self._data[:n], sorted(set(below + above)))
        out = []
        for position, lo, hi in zip(positions, below, above, strict=True):
            low, high = float(ranked[lo]), float(ranked[hi])
            out.append(low + (high - low) * (position - lo))
        return out

    def max(self) -> float:
        return float(self._data[: self._count].max()) if self._count else math.nan


@dataclass(frozen=True)
class JitterReport:
    cycles: int
    overruns: int
    jitter_p50_ms: float
    jitter_p99_ms: float
    jitter_max_ms: float


class RateStats:
    """Pure bookkeeping of a periodic loop; feed it scheduled and actual times."""

    def __init__(self, window: int = 5000) -> None:
        self._jitter_s = SampleWindow(window)
        self.cycles = 0
        self.overruns = 0

    def reset(self) -> None:
        self._jitter_s.reset()
        self.cycles = 0
        self.overruns = 0

    def update(self, scheduled_s: float, actual_s: float, missed_ticks: int = 0) -> None:
        self.cycles += 1
        self.overruns += missed_ticks
        self._jitter_s.append(actual_s - scheduled_s)

    def report(self) -> JitterReport:
        if not len(self._jitter_s):
            return JitterReport(self.cycles, self.overruns, math.nan, math.nan, math.nan)
        p50_s, p99_s = self._jitter_s.percentiles([50, 99])
        return JitterReport(
            self.cycles, self.overruns, p50_s * 1e3, p99_s * 1e3, self._jitter_s.max() * 1e3
        )


class FixedRateTicker:
    """Await ``tick()`` once per period; it returns the actual (monotonic) wake-up time."""

    def __init__(self, period_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not period_s > 0:
            raise ValueError(f"period_s must be positive (got {period_s})")
        self.period_s = period_s
        self._clock = clock
        self.stats = RateStats()
        self._next_s: float | None = None
        self._early: asyncio.Future[bool] | None = None
        self.early_wakes = 0
        # How late the last wake-up was against its schedule (0 for an early wake-up).
        self.last_late_s = 0.0
        # The deadline kept to the microsecond (appliance/timerfd.py), when the clock is
        # the kernel's monotonic one; a fake clock's deadlines mean nothing to the kernel.
        self._timerfd = open_timerfd() if clock is time.monotonic else None
        self._timerfd_loop: asyncio.AbstractEventLoop | None = None
        # The loop's own timer still runs, BACKSTOP_S behind the deadline: a timerfd
        # that never fired would then cost precision, not the control loop.
        self.timerfd_wakes = 0
        # Work deferred until a cycle has run (ControlSlot), by that cycle's deadline.
        self._after_cycle: list[tuple[float, asyncio.Future[None]]] = []

    @property
    def next_deadline_s(self) -> float | None:
        """When the next scheduled cycle is due (None before the first tick)."""
        return self._next_s

    def after_cycle(self, deadline_s: float, future: asyncio.Future[None]) -> None:
        """Resolve ``future`` once the cycle due at ``deadline_s`` has run: at the first
        ``tick()`` (a loop calls it when its cycle is done) that waits for a later one."""
        self._after_cycle.append((deadline_s, future))

    def _release_after_cycle(self) -> None:
        if not self._after_cycle or self._next_s is None:
            return
        keep = []
        for deadline_s, future in self._after_cycle:
            if deadline_s < self._next_s:
                if not future.done():
                    future.set_result(None)
            elif not future.done():
                keep.append((deadline_s, future))
        self._after_cycle = keep

    @property
    def precise(self) -> bool:
        """Whether wake-ups come from a timerfd (else from the loop's millisecond timer)."""
        return self._timerfd is not None

    def reset(self) -> None:
        self._next_s = None
        self._early = None
        self.early_wakes = 0
        self.last_late_s = 0.0
        self.timerfd_wakes = 0
        self.stats.reset()
        self._unwatch()
        waiting, self._after_cycle = self._after_cycle, []
        for _, future in waiting:  # a restarted loop has no cycle to wait for
            if not future.done():
                future.set_result(None)

    def close(self) -> None:
        """Release the timerfd (the ticker keeps working, on the loop's timer)."""
        self._unwatch()
        if self._timerfd is not None:
            self._timerfd.close()
            self._timerfd = None

    def _watch(self, loop: asyncio.AbstractEventLoop) -> bool:
        timerfd = self._timerfd
        if timerfd is None:
            return False
        if self._timerfd_loop is not loop:
            self._unwatch()
            try:
                loop.add_reader(timerfd.fileno(), self._on_timerfd)
            except (NotImplementedError, RuntimeError, OSError, ValueError):
                return False  # a loop without readers (Windows' proactor) or closed
            self._timerfd_loop = loop
        return True

    def _unwatch(self) -> None:
        loop, self._timerfd_loop = self._timerfd_loop, None
        if loop is not None and self._timerfd is not None and not loop.is_closed():
            loop.remove_reader(self._timerfd.fileno())

    def _on_timerfd(self) -> None:
        if self._timerfd is None or not self._timerfd.clear():
            return
        early = self._early
        if early is not None and not early.done():
            self.timerfd_wakes += 1
            early.set_result(False)

    def wake_early(self) -> None:
        """Make the pending ``tick()`` return now, off schedule (an operator action).

        The schedule is not moved and the early wake-up is not counted as jitter: the next
        ``tick()`` waits for the same scheduled deadline as before.
        """
        early = self._early
        if early is not None and not early.done():
            early.set_result(True)

    async def tick(self) -> float:
        self._release_after_cycle()
        now_s = self._clock()
        if self._next_s is None:
            self._next_s = now_s
        delay_s = self._next_s - now_s
        if delay_s > 0:
            loop = asyncio.get_running_loop()
            early: asyncio.Future[bool] = loop.create_future()
            self._early = early
            if self._watch(loop):
                assert self._timerfd is not None
                self._timerfd.arm(self._next_s)
                timer = loop.call_later(delay_s + BACKSTOP_S, _resolve, early)
            else:
                timer = loop.call_later(delay_s, _resolve, early)
            try:
                woken_early = await early
            finally:
                timer.cancel()
                self._early = None
            if woken_early:  # an extra cycle: the schedule and the statistics are kept
                self.early_wakes += 1
                self.last_late_s = 0.0
                return self._clock()
        else:
            await asyncio.sleep(0)  # stay cancellable and fair even when late
        actual_s = self._clock()
        scheduled_s = self._next_s
        missed = max(int((actual_s - scheduled_s) // self.period_s), 0)
        self.last_late_s = actual_s - scheduled_s
        self.stats.update(scheduled_s, actual_s, missed)
        self._next_s = scheduled_s + (missed + 1) * self.period_s
        return actual_s


def _resolve(future: asyncio.Future[bool]) -> None:
    if not future.done():
        future.set_result(False)


def _release(future: asyncio.Future[None]) -> None:
    if not future.done():
        future.set_result(None)


class ControlSlot:
    """Keeps deferrable bulk work out of the last moments before a control deadline.

    Why: every service shares one event loop, and a callback running when the control
    cycle comes due delays it by whatever it has left. The simulated scanners and the
    control loop run on the same clock, so a scan that lands just before the deadline
    lands there every period: a 90 s soak had 247 of 4,500 cycles more than 2 ms late
    behind the scanners' decoding alone (benchmarks/late_cycles.py names them). Work
    that can wait a few milliseconds (decoding a scan, later its features) awaits
    ``clear()`` first: at once when the next deadline is more than ``budget_s`` away,
    else after that cycle has run. So the control cycle owns the moments before its
    deadline, the way a time-triggered schedule reserves its slot.

    The wait is bounded: a control loop that is late, stopped or hung (the supervisor's
    business) holds the work at most one period past the deadline, and once a deadline is
    a period past, nothing waits for it at all.
    """

    def __init__(self, budget_s: float, clock: Callable[[], float] = time.monotonic) -> None:
        if not budget_s >= 0:
            raise ValueError(f"budget_s must not be negative (got {budget_s})")
        self.budget_s = budget_s
        self._clock = clock
        self._ticker: FixedRateTicker | None = None
        self.deferred = 0

    def attach(self, ticker: FixedRateTicker) -> None:
        """The control loop's ticker (until then, nothing is deferred)."""
        self._ticker = ticker

    async def clear(self) -> None:
        ticker = self._ticker
        if ticker is None:
            return
        deadline_s = ticker.next_deadline_s
        if deadline_s is None:
            return
        left_s = deadline_s - self._clock()
        if left_s > self.budget_s or left_s < -ticker.period_s:
            return  # clear of the deadline; or a loop a period behind is not ticking now
        self.deferred += 1
        loop = asyncio.get_running_loop()
        after: asyncio.Future[None] = loop.create_future()
        ticker.after_cycle(deadline_s, after)
        timer = loop.call_later(max(left_s, 0.0) + ticker.period_s, _release, after)
        try:
            await after
        finally:
            timer.cancel()
