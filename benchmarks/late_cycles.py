"""Who made a control cycle late: the callbacks, collections and gaps between its deadline
and its wake-up.

Why: a jitter percentile says *that* the loop woke late, the loop monitor's longest
callback says who held the loop longest in a second; neither says what delayed the cycles
that make the tail. This keeps the last few thousand callbacks of the daemon's loop (start,
end, callback) and the garbage collector's pauses, and for every cycle that woke later
than a threshold it splits the lateness into what overlapped it:

- each callback that ran inside the window (the control task's own step excluded),
- each collection (by generation; it runs inside some callback, so it is subtracted there),
- with a ``SchedProbe``, the time the loop's thread waited on the kernel's run queue
  (runnable, no CPU given: ``run_delay`` of its schedstat, to the nanosecond), taken out of
  the rest below; and whether the hypervisor stole CPU time from this machine since the
  cycle before (``steal`` of /proc/stat, over every CPU, in 10 ms ticks);
- the rest: time the loop ran no callback at all, so the process was waiting in the
  selector past its deadline, for the GIL (another thread of the process held it), or for
  a CPU the hypervisor gave to another machine (which the guest cannot see as waiting).

The cause of a late cycle is the biggest of these parts. Benchmarks only: it wraps the
loop monitor's ``record`` and costs a clock read and a tuple per callback, and with a
probe two preads of procfs per cycle.
"""

from __future__ import annotations

import gc
import os
import statistics
import time
from collections import Counter, defaultdict, deque
from collections.abc import Callable
from typing import Any

from appliance.loop_monitor import LoopMonitor, callback_name

GAP = "no callback running (selector, GIL or CPU wait)"
RUN_QUEUE = "runnable, waiting for a CPU (run queue)"


class SchedProbe:
    """The calling thread's cumulative run-queue wait and the machine's cumulative steal,
    both in seconds. Open it in the thread to watch (the event loop's)."""

    def __init__(self) -> None:
        self._schedstat = os.open("/proc/thread-self/schedstat", os.O_RDONLY)
        self._stat = os.open("/proc/stat", os.O_RDONLY)
        self._tick_s = 1.0 / os.sysconf("SC_CLK_TCK")

    def read(self) -> tuple[float, float]:
        run_delay_ns = int(os.pread(self._schedstat, 128, 0).split()[1])
        return run_delay_ns * 1e-9, self.steal_s() or 0.0

    def steal_s(self) -> float | None:
        """The machine's steal since boot, over every CPU (None where the kernel has none)."""
        cpu = os.pread(self._stat, 256, 0).split(b"\n", 1)[0].split()
        return int(cpu[8]) * self._tick_s if cpu[:1] == [b"cpu"] and len(cpu) > 8 else None

    def close(self) -> None:
        os.close(self._schedstat)
        os.close(self._stat)


class _Named:
    """A handle's callback kept for naming later (naming costs more than the keeping)."""

    __slots__ = ("_callback",)

    def __init__(self, callback: Any) -> None:
        self._callback = callback


class LateCycles:
    def __init__(
        self,
        monitor: LoopMonitor,
        threshold_s: float,
        clock: Callable[[], float] = time.perf_counter,
        keep: int = 4096,
        own_task: str = "task control",
        probe: Callable[[], tuple[float, float]] | None = None,
    ) -> None:
        self.threshold_s = threshold_s
        self._probe = probe
        self._probed: tuple[float, float] | None = None
        self.stolen = 0  # late cycles with host steal since the cycle before
        self._clock = clock
        self._own = own_task
        self._callbacks: deque[tuple[float, float, Any]] = deque(maxlen=keep)
        self._gc: deque[tuple[float, float, int]] = deque(maxlen=256)
        self._gc_started: tuple[float, int] | None = None
        self.causes: Counter[str] = Counter()
        self.parts_ms: defaultdict[str, list[float]] = defaultdict(list)
        self.late = 0
        self._monitor = monitor
        self._record = monitor.record
        monitor.record = self._recording  # type: ignore[method-assign]
        gc.callbacks.append(self._on_gc)

    def close(self) -> None:
        self._monitor.record = self._record  # type: ignore[method-assign]
        if self._on_gc in gc.callbacks:
            gc.callbacks.remove(self._on_gc)

    def reset(self) -> None:
        self.causes.clear()
        self.parts_ms.clear()
        self.late = 0
        self.stolen = 0
        self._probed = None

    def _recording(self, duration_s: float, handle: Any) -> None:
        end_s = self._clock()
        self._callbacks.append((end_s - duration_s, end_s, handle._callback))
        self._record(duration_s, handle)

    def _on_gc(self, phase: str, info: dict[str, Any]) -> None:
        now_s = self._clock()
        if phase == "start":
            self._gc_started = (now_s, int(info.get("generation", -1)))
        elif self._gc_started is not None:
            started_s, generation = self._gc_started
            self._gc.append((started_s, now_s, generation))
            self._gc_started = None

    def update(self, scheduled_s: float, actual_s: float) -> None:
        """One cycle's deadline and wake-up (the clock must be the monitor's); called for
        every cycle, so that a probe's counters are read at each wake-up."""
        waited_s = stolen_s = 0.0
        if self._probe is not None:
            probed, previous = self._probe(), self._probed
            self._probed = probed
            if previous is not None:
                waited_s, stolen_s = probed[0] - previous[0], probed[1] - previous[1]
        if actual_s - scheduled_s < self.threshold_s:
            return
        self.late += 1
        if stolen_s > 0:
            self.stolen += 1
        parts: defaultdict[str, float] = defaultdict(float)
        busy_s = 0.0
        # Newest first: callbacks are kept in the order they ended, so the first one that
        # ended before the deadline ends the search (a full pass was 18 % of a core).
        for start_s, end_s, callback in reversed(self._callbacks):
            if end_s <= scheduled_s:
                break
            overlap_s = min(end_s, actual_s) - max(start_s, scheduled_s)
            if overlap_s <= 0:
                continue
            name = callback_name(_Named(callback))  # type: ignore[arg-type]
            if name == self._own:
                continue
            parts[name] += overlap_s
            busy_s += overlap_s
        collected_s = 0.0
        for start_s, end_s, generation in self._gc:
            overlap_s = min(end_s, actual_s) - max(start_s, scheduled_s)
            if overlap_s > 0:
                parts[f"gc generation {generation}"] += overlap_s
                collected_s += overlap_s
        if collected_s and parts:  # a collection runs inside a callback: not counted twice
            holder = max(
                (n for n in parts if not n.startswith("gc ")), key=parts.__getitem__, default=None
            )
            if holder is not None:
                parts[holder] = max(parts[holder] - collected_s, 0.0)
        idle_s = max(actual_s - scheduled_s - busy_s, 0.0)
        # Run-queue wait since the last wake-up, at most the idle part of the lateness:
        # waiting before the deadline (a preempted callback) did not make this cycle late.
        queued_s = min(max(waited_s, 0.0), idle_s)
        if queued_s > 0:
            parts[RUN_QUEUE] += queued_s
        parts[GAP] += idle_s - queued_s
        cause = max(parts, key=parts.__getitem__)
        self.causes[cause] += 1
        for name, part_s in parts.items():
            if part_s > 0:
                self.parts_ms[name].append(part_s * 1e3)

    def lines(self, top: int = 6) -> list[str]:
        if not self.late:
            return [f"    late cycles (> {self.threshold_s * 1e3:g} ms): none"]
        out = [
            f"    late cycles (> {self.threshold_s * 1e3:g} ms): {self.late}; cause (the"
            " biggest part of the lateness): count, and that part's median / max ms"
        ]
        for name, count in self.causes.most_common(top):
            parts = self.parts_ms[name]
            out.append(
                f"      {count:5d}  {name}: {statistics.median(parts):.2f} / {max(parts):.2f}"
            )
        others = sum(self.causes.values()) - sum(c for _, c in self.causes.most_common(top))
        if others:
            out.append(f"      {others:5d}  other causes")
        if self._probe is not None:
            out.append(
                f"      {self.stolen} of the {self.late} with host steal since the cycle before"
            )
        return out
