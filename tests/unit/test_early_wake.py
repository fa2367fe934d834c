"""Operator actions run an extra control cycle at once, without moving the schedule."""

from __future__ import annotations

import asyncio
import time

from appliance.control_loop import OperatorWatch
from appliance.timing import FixedRateTicker
from drivers.actuators.messages import (
    BoardStatus,
    BrakeTelemetry,
    Buttons,
    FaultCode,
    PanelTelemetry,
)
from drivers.topics import Topic


class FakeClock:
    """The ticker's clock, set by the test: what a tick returns does not depend on how
    fast a loaded machine runs the event loop (only the order of its timers matters)."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        return self.now_s


async def test_an_early_wake_is_an_extra_cycle_and_keeps_the_schedule() -> None:
    clock = FakeClock()
    ticker = FixedRateTicker(0.1, clock=clock)
    first_s = await ticker.tick()
    assert first_s == 0.0  # the first tick is due at once; the next at 0.1 s
    clock.now_s = 0.01
    asyncio.get_running_loop().call_soon(ticker.wake_early)
    early_s = await ticker.tick()
    assert early_s == 0.01  # returned at the wake, well before the 0.1 s tick
    assert ticker.early_wakes == 1
    assert ticker.stats.cycles == 1  # not a scheduled cycle: no jitter sample
    clock.now_s = 0.1  # the original deadline is due
    scheduled_s = await ticker.tick()
    assert scheduled_s == 0.1
    assert ticker.stats.cycles == 2
    # The original deadline, not early + period (0.11 s): the tick due at 0.1 s was on time.
    report = ticker.stats.report()
    assert report.jitter_p50_ms == report.jitter_max_ms == 0.0
    assert report.overruns == 0


async def test_a_wake_with_no_tick_pending_does_nothing() -> None:
    ticker = FixedRateTicker(0.05)
    ticker.wake_early()  # nobody waiting: no effect on the next tick
    start_s = time.monotonic()
    await ticker.tick()
    await ticker.tick()
    assert time.monotonic() - start_s >= 0.045
    assert ticker.early_wakes == 0


def _panel(counts: tuple[int, int, int, int, int], down: Buttons = Buttons.NONE) -> PanelTelemetry:
    return PanelTelemetry(BoardStatus.NONE, FaultCode.NONE, 0, down, counts)


def _brake(actuator_pct: float, pedal_pct: float | None) -> BrakeTelemetry:
    return BrakeTelemetry(BoardStatus.NONE, FaultCode.NONE, 0, actuator_pct, pedal_pct)


def test_panel_changes_wake_the_loop_and_repeats_do_not() -> None:
    wakes: list[int] = []
    watch = OperatorWatch(lambda: wakes.append(1), pedal_margin_pct=8.0)
    topic: Topic[PanelTelemetry] = Topic("board.panel")
    topic.subscribe(watch.on_panel)
    topic.publish(_panel((3, 0, 0, 0, 0)), 0.0)  # the first frame is only a baseline
    topic.publish(_panel((3, 0, 0, 0, 0)), 0.01)
    assert wakes == []
    topic.publish(_panel((3, 0, 0, 1, 0)), 0.02)  # manual override pressed
    topic.publish(_panel((3, 0, 0, 1, 0), Buttons.ESTOP), 0.03)  # the mushroom
    topic.publish(_panel((3, 0, 0, 1, 0), Buttons.ESTOP), 0.04)
    assert len(wakes) == 2


def test_a_pedal_wakes_the_loop_when_it_is_pressed_not_while_it_rests() -> None:
    wakes: list[int] = []
    watch = OperatorWatch(lambda: wakes.append(1), pedal_margin_pct=8.0)
    topic: Topic[BrakeTelemetry] = Topic("board.brake")
    topic.subscribe(watch.on_pedal("brake"))
    topic.publish(_brake(20.0, 25.0), 0.0)  # within the margin of our own actuator
    topic.publish(_brake(0.0, None), 0.01)  # no pedal sensor
    assert wakes == []
    topic.publish(_brake(0.0, 30.0), 0.02)  # the operator's foot
    topic.publish(_brake(0.0, 35.0), 0.03)  # still pressed: no new wake
    topic.publish(_brake(0.0, 0.0), 0.04)
    topic.publish(_brake(0.0, 30.0), 0.05)  # pressed again
    assert len(wakes) == 2
