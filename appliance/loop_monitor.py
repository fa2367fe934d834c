"""The event loop's own lag: how long each callback held the loop, and who ran it.

Why: every service of the daemon shares one event loop, so one callback that runs for
30 ms delays the control cycle, every driver and the watchdog by 30 ms. The control loop's
jitter says *that* it woke late; this says *who* held the loop. Each callback the loop runs
(a task's step, a reader's wake-up, a timer) is timed; per reporting window the monitor
keeps the longest one and its name (the task's name for a task step, the function's
qualified name otherwise), how many ran longer than ``slow_s`` and how busy the loop was.

How: asyncio runs every callback through ``Handle._run``; the monitor wraps that method
once for the process and times only handles of the loops it was installed on, so other
loops (a test's, a thread's) pay one dictionary lookup. Two clock reads per callback (0.4 us
each on this project's VMs), against callbacks of tens of microseconds; a thread CPU-time
read costs 3.6 us there, so CPU is read once per window, for the whole process. Naming a
callback (the costly part) is done only for a new longest one.
"""

from __future__ import annotations

import asyncio
import functools
import time
from asyncio import events
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

DEFAULT_SLOW_S = 0.005  # a quarter of a 50 Hz period: worth naming in the log
# Above this per clock read the monitor would cost more than it tells: inside user-mode
# Linux (the HIL tests) a perf_counter() is a trapped system call, 32 us measured, against
# 0.4 us on the VMs and less with a vDSO on the vehicle's PC.
MAX_CLOCK_READ_S = 5e-6

_original_run = events.Handle._run
_monitors: dict[asyncio.AbstractEventLoop, LoopMonitor] = {}


def _timed_run(self: events.Handle) -> None:
    monitor = _monitors.get(self._loop)  # type: ignore[attr-defined]
    if monitor is None:
        _original_run(self)
        return
    clock = monitor.clock
    started = clock()
    try:
        _original_run(self)
    finally:
        monitor.record(clock() - started, self)


def callback_name(handle: events.Handle) -> str:
    """Who a callback belongs to: ``task <name>`` for a task's step, else the function."""
    callback: Any = handle._callback  # type: ignore[attr-defined]
    while isinstance(callback, functools.partial):
        callback = callback.func
    owner = getattr(callback, "__self__", None)
    if isinstance(owner, asyncio.Task):
        return f"task {owner.get_name()}"
    name = getattr(callback, "__qualname__", None) or type(callback).__qualname__
    module = getattr(callback, "__module__", None)
    return f"{module}.{name}" if module and module != "builtins" else str(name)


@dataclass(frozen=True)
class LoopLag:
    """One window of the loop's life (or the worst since start)."""

    window_s: float
    callbacks: int
    slow_callbacks: int
    busy_pct: float
    longest_ms: float
    longest_by: str
    # The process's CPU over the window. Far below busy_pct, the callbacks were not
    # running but waiting for a CPU the machine gave to other processes: the longest one
    # is then where the wait happened, not its cause.
    cpu_pct: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return {
            "window_s": round(self.window_s, 3),
            "callbacks": self.callbacks,
            "slow_callbacks": self.slow_callbacks,
            "busy_pct": round(self.busy_pct, 1),
            "longest_callback_ms": round(self.longest_ms, 3),
            "longest_callback_by": self.longest_by,
            "cpu_pct": round(self.cpu_pct, 1),
        }


class LoopMonitor:
    """Times one event loop's callbacks; ``take_window()`` reports and starts a new window."""

    def __init__(
        self,
        slow_s: float = DEFAULT_SLOW_S,
        clock: Callable[[], float] = time.perf_counter,
        cpu_clock: Callable[[], float] = time.process_time,
    ) -> None:
        self.slow_s = slow_s
        self.clock = clock
        self.cpu_clock = cpu_clock
        self._loop: asyncio.AbstractEventLoop | None = None
        self.worst_ms = 0.0
        self.worst_by = ""
        self.total_slow = 0
        self.disabled_reason = ""
        self.reset()

    def reset(self) -> None:
        """Start a new window (the worst-since-start figures are kept)."""
        self._window_started = self.clock()
        self._window_cpu_started = self.cpu_clock()
        self._callbacks = 0
        self._slow = 0
        self._busy_s = 0.0
        self._longest_s = 0.0
        self._longest_by = ""

    def clock_read_s(self, reads: int = 200) -> float:
        """What one read of the monitor's clock costs here."""
        clock = self.clock
        started = time.perf_counter()
        for _ in range(reads):
            clock()
        return (time.perf_counter() - started) / reads

    def install(self, loop: asyncio.AbstractEventLoop, *, check_cost: bool = True) -> bool:
        """Start timing ``loop``'s callbacks; False (and ``disabled_reason``) when a clock
        read costs so much here that timing every callback would slow the loop down."""
        if self._loop is not None:
            raise RuntimeError("this monitor is already installed on a loop")
        if check_cost:
            cost_s = self.clock_read_s()
            if cost_s > MAX_CLOCK_READ_S:
                self.disabled_reason = (
                    f"a clock read costs {cost_s * 1e6:.1f} us here "
                    f"(limit {MAX_CLOCK_READ_S * 1e6:.0f} us): callbacks are not timed"
                )
                return False
        if events.Handle._run is not _timed_run:
            events.Handle._run = _timed_run  # type: ignore[method-assign]
        _monitors[loop] = self
        self._loop = loop
        self.disabled_reason = ""
        self.reset()
        return True

    def uninstall(self) -> None:
        if self._loop is not None and _monitors.get(self._loop) is self:
            del _monitors[self._loop]
        self._loop = None

    def record(self, duration_s: float, handle: events.Handle) -> None:
        self._callbacks += 1
        self._busy_s += duration_s
        if duration_s >= self.slow_s:
            self._slow += 1
            self.total_slow += 1
        if duration_s > self._longest_s:
            self._longest_s = duration_s
            self._longest_by = callback_name(handle)
            if duration_s * 1e3 > self.worst_ms:
                self.worst_ms = duration_s * 1e3
                self.worst_by = self._longest_by

    def window(self) -> LoopLag:
        """The current window so far."""
        window_s = max(self.clock() - self._window_started, 1e-9)
        return LoopLag(
            window_s=window_s,
            callbacks=self._callbacks,
            slow_callbacks=self._slow,
            busy_pct=100.0 * self._busy_s / window_s,
            longest_ms=self._longest_s * 1e3,
            longest_by=self._longest_by,
            cpu_pct=100.0 * (self.cpu_clock() - self._window_cpu_started) / window_s,
        )

    def take_window(self) -> LoopLag:
        """The window just ended; the next one starts now."""
        lag = self.window()
        self.reset()
        return lag

    def worst(self) -> dict[str, Any]:
        """The longest callback since the monitor was installed, and the slow ones' count."""
        if self.disabled_reason:
            return {"disabled": self.disabled_reason}
        return {
            "longest_callback_ms": round(self.worst_ms, 3),
            "longest_callback_by": self.worst_by,
            "slow_callbacks": self.total_slow,
        }
