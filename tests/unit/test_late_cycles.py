"""benchmarks/late_cycles.py: the split of a late cycle into who made it late, checked
against lateness built by hand on a fake clock (callbacks, run-queue wait, steal)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import pytest

from appliance.loop_monitor import LoopMonitor
from benchmarks.late_cycles import GAP, RUN_QUEUE, LateCycles, SchedProbe


class Clock:
    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


@dataclass
class Handle:
    _callback: Any


def board_reader() -> None:
    """A callback of the loop, named by its function."""


NAME = f"{__name__}.board_reader"  # how the loop monitor names a plain function


class Probe:
    """Cumulative (run-queue wait, steal) seconds, as SchedProbe reads them."""

    def __init__(self) -> None:
        self.waited_s = 0.0
        self.stolen_s = 0.0

    def __call__(self) -> tuple[float, float]:
        return self.waited_s, self.stolen_s


def late_cycles(probe: Probe | None = None) -> tuple[LateCycles, LoopMonitor, Clock]:
    clock = Clock()
    monitor = LoopMonitor(clock=clock)
    return LateCycles(monitor, threshold_s=0.002, clock=clock, probe=probe), monitor, clock


def run_callback(monitor: LoopMonitor, clock: Clock, start_s: float, end_s: float) -> None:
    clock.now_s = end_s
    monitor.record(end_s - start_s, Handle(board_reader))  # type: ignore[arg-type]


def test_a_callback_across_the_deadline_is_the_cause_and_the_rest_is_the_gap() -> None:
    late, monitor, clock = late_cycles()
    run_callback(monitor, clock, 0.0095, 0.0135)  # 3.5 ms of it past the 10 ms deadline
    late.update(0.010, 0.0145)  # woke 4.5 ms late
    assert late.late == 1
    assert late.causes == {NAME: 1}
    assert late.parts_ms[NAME] == [pytest.approx(3.5)]
    assert late.parts_ms[GAP] == [pytest.approx(1.0)]


def test_a_cycle_on_time_is_not_counted() -> None:
    late, monitor, clock = late_cycles()
    run_callback(monitor, clock, 0.0095, 0.0105)
    late.update(0.010, 0.0119)  # 1.9 ms: under the 2 ms threshold
    assert late.late == 0 and not late.causes


def test_run_queue_wait_since_the_last_wake_up_comes_out_of_the_gap() -> None:
    probe = Probe()
    late, monitor, clock = late_cycles(probe)
    late.update(0.000, 0.0001)  # the first wake-up reads the counters
    run_callback(monitor, clock, 0.0099, 0.0110)  # 1 ms past the deadline
    probe.waited_s = 0.004  # 4 ms runnable without a CPU since the last wake-up
    late.update(0.010, 0.016)  # 6 ms late: 1 ms callback, 5 ms idle
    assert late.causes == {RUN_QUEUE: 1}
    assert late.parts_ms[RUN_QUEUE] == [pytest.approx(4.0)]
    assert late.parts_ms[GAP] == [pytest.approx(1.0)]
    assert late.stolen == 0


def test_run_queue_wait_is_never_more_than_the_idle_part() -> None:
    probe = Probe()
    late, _, _ = late_cycles(probe)
    late.update(0.000, 0.0001)
    probe.waited_s = 0.050  # mostly before the deadline: it did not make this cycle late
    late.update(0.010, 0.013)
    assert late.parts_ms[RUN_QUEUE] == [pytest.approx(3.0)]
    assert GAP not in late.parts_ms


def test_steal_since_the_cycle_before_is_counted_per_late_cycle() -> None:
    probe = Probe()
    late, _, _ = late_cycles(probe)
    late.update(0.000, 0.0001)
    probe.stolen_s = 0.010
    late.update(0.010, 0.0101)  # on time: steal elsewhere is not counted
    probe.stolen_s = 0.020
    late.update(0.020, 0.035)
    late.update(0.040, 0.050)  # late, and no steal since 0.035
    assert (late.late, late.stolen) == (2, 1)
    assert late.lines()[-1].strip() == "1 of the 2 with host steal since the cycle before"
    late.reset()
    assert (late.late, late.stolen) == (0, 0)


def test_the_probe_reads_counters_that_only_grow() -> None:
    probe = SchedProbe()
    try:
        first = probe.read()
        sum(range(200_000))
        second = probe.read()
        assert all(v >= 0 for v in first)
        assert second[0] >= first[0] and second[1] >= first[1]
    finally:
        probe.close()
