"""SlowCycleLog: which late or slow cycles reach the log, checked on hand-made timings."""

from __future__ import annotations

from structlog.testing import capture_logs

from appliance.control_loop import STALL_PERIODS, SlowCycleLog
from appliance.timing import FixedRateTicker
from tests.unit.test_early_wake import FakeClock

PERIOD_MS = 40.0


def logged(calls: list[tuple[float, float, float]]) -> list[dict[str, object]]:
    """(now_s, late_ms, step_ms) per cycle -> the log lines."""
    slow = SlowCycleLog(min_interval_s=1.0)
    with capture_logs() as lines:
        for now_s, late_ms, step_ms in calls:
            slow.update(now_s, late_ms, step_ms, PERIOD_MS)
    return [line for line in lines if line["event"] == "control_cycle_slow"]


def test_cycles_on_time_and_quick_are_not_logged() -> None:
    assert logged([(t * 0.04, 39.9, 39.9) for t in range(100)]) == []


def test_a_late_wake_up_and_a_long_step_are_logged_with_their_figures() -> None:
    lines = logged([(1.0, 45.0, 2.0), (3.0, 0.5, 41.0)])
    assert [(ln["late_ms"], ln["step_ms"], ln["period_ms"]) for ln in lines] == [
        (45.0, 2.0, 40.0),
        (0.5, 41.0, 40.0),
    ]


def test_mild_ones_within_a_second_are_counted_and_told_with_the_next_line() -> None:
    lines = logged([(1.0, 50.0, 1.0), (1.2, 50.0, 1.0), (1.5, 60.0, 1.0), (2.1, 70.0, 1.0)])
    assert [ln["late_ms"] for ln in lines] == [50.0, 70.0]
    assert [ln["earlier_unlogged"] for ln in lines] == [0, 2]


def test_a_stall_is_logged_even_right_after_another_line() -> None:
    stall_ms = STALL_PERIODS * PERIOD_MS
    lines = logged([(1.0, 50.0, 1.0), (1.01, stall_ms, 1.0), (1.02, 1.0, stall_ms + 1)])
    assert [(ln["late_ms"], ln["step_ms"]) for ln in lines] == [
        (50.0, 1.0),
        (stall_ms, 1.0),
        (1.0, stall_ms + 1),
    ]


def test_reset_forgets_the_last_line() -> None:
    slow = SlowCycleLog(min_interval_s=1.0)
    with capture_logs() as lines:
        slow.update(1.0, 50.0, 1.0, PERIOD_MS)
        slow.reset()
        slow.update(1.1, 50.0, 1.0, PERIOD_MS)
    assert len(lines) == 2


async def test_the_ticker_tells_how_late_its_last_wake_up_was() -> None:
    clock = FakeClock()
    ticker = FixedRateTicker(0.1, clock=clock)
    await ticker.tick()  # due at once: on time
    assert ticker.last_late_s == 0.0
    clock.now_s = 0.35  # the process stopped past two deadlines (0.1 and 0.2) and most of 0.3
    await ticker.tick()
    assert abs(ticker.last_late_s - 0.25) < 1e-12  # against the 0.1 s deadline it was due at
    assert ticker.stats.overruns == 2
