"""Fixed-rate scheduling with measured jitter and overruns.

A control loop that sleeps ``period`` after each step drifts by the step's duration; this
one schedules against absolute deadlines (``start + n * period``) and, when it falls
behind, skips the missed ticks instead of bursting to catch up, counting each as an
overrun. Jitter (actual minus scheduled wake-up) is kept in a bounded window so its
percentiles can be reported without the memory growing over a day's run.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

# np.percentile imports numpy.ma lazily on its first call: a 15-70 ms stall of the event
# loop, once, after the daemon is READY (enough to make the steering pot stale). Import it
# now, at start-up.
import numpy.ma


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
        self._jitter_s: deque[float] = deque(maxlen=window)
        self.cycles = 0
        self.overruns = 0

    def reset(self) -> None:
        self._jitter_s.clear()
        self.cycles = 0
        self.overruns = 0

    def update(self, scheduled_s: float, actual_s: float, missed_ticks: int = 0) -> None:
        self.cycles += 1
        self.overruns += missed_ticks
        self._jitter_s.append(actual_s - scheduled_s)

    def report(self) -> JitterReport:
        if not self._jitter_s:
            return JitterReport(self.cycles, self.overruns, math.nan, math.nan, math.nan)
        jitter_ms = np.asarray(self._jitter_s) * 1e3
        p50, p99 = np.percentile(jitter_ms, [50, 99])
        return JitterReport(
            self.cycles, self.overruns, float(p50), float(p99), float(jitter_ms.max())
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

    def reset(self) -> None:
        self._next_s = None
        self._early = None
        self.early_wakes = 0
        self.stats.reset()

    def wake_early(self) -> None:
        """Make the pending ``tick()`` return now, off schedule (an operator action).

        The schedule is not moved and the early wake-up is not counted as jitter: the next
        ``tick()`` waits for the same scheduled deadline as before.
        """
        early = self._early
        if early is not None and not early.done():
            early.set_result(True)

    async def tick(self) -> float:
        now_s = self._clock()
        if self._next_s is None:
            self._next_s = now_s
        delay_s = self._next_s - now_s
        if delay_s > 0:
            loop = asyncio.get_running_loop()
            early: asyncio.Future[bool] = loop.create_future()
            self._early = early
            timer = loop.call_later(delay_s, _resolve, early)
            try:
                woken_early = await early
            finally:
                timer.cancel()
                self._early = None
            if woken_early:  # an extra cycle: the schedule and the statistics are kept
                self.early_wakes += 1
                return self._clock()
        else:
            await asyncio.sleep(0)  # stay cancellable and fair even when late
        actual_s = self._clock()
        scheduled_s = self._next_s
        missed = max(int((actual_s - scheduled_s) // self.period_s), 0)
        self.stats.update(scheduled_s, actual_s, missed)
        self._next_s = scheduled_s + (missed + 1) * self.period_s
        return actual_s


def _resolve(future: asyncio.Future[bool]) -> None:
    if not future.done():
        future.set_result(False)
