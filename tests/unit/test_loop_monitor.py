"""The event-loop monitor: the longest callback of a window and who ran it, on a fake clock."""

from __future__ import annotations

import asyncio
import functools

from appliance.cli.status_view import render_status
from appliance.loop_monitor import LoopMonitor


class FakeClock:
    def __init__(self) -> None:
        self.now_s = 100.0

    def __call__(self) -> float:
        return self.now_s

    def advance(self, seconds: float) -> None:
        self.now_s += seconds


async def test_the_longest_callback_is_named_by_its_task() -> None:
    clock, cpu = FakeClock(), FakeClock()
    monitor = LoopMonitor(slow_s=0.005, clock=clock, cpu_clock=cpu)
    monitor.install(asyncio.get_running_loop())
    try:

        async def hog() -> None:
            await asyncio.sleep(0)
            clock.advance(0.030)  # this step "ran" 30 ms, 4 ms of it on the CPU
            cpu.advance(0.004)

        async def quick() -> None:
            await asyncio.sleep(0)
            clock.advance(0.001)

        await asyncio.gather(
            asyncio.create_task(quick(), name="quick"), asyncio.create_task(hog(), name="hog")
        )
        lag = monitor.take_window()
    finally:
        monitor.uninstall()
    assert lag.longest_by == "task hog"
    assert abs(lag.longest_ms - 30.0) < 1e-6
    assert lag.slow_callbacks == 1
    assert lag.callbacks >= 4
    assert monitor.worst()["longest_callback_by"] == "task hog"
    # The window restarted: nothing in it yet.
    assert monitor.window().callbacks == 0 and monitor.window().longest_by == ""


async def test_plain_callbacks_are_named_by_function_partials_unwrapped() -> None:
    clock = FakeClock()
    monitor = LoopMonitor(clock=clock)
    loop = asyncio.get_running_loop()
    monitor.install(loop)
    done = loop.create_future()

    def on_timer(amount_s: float) -> None:
        clock.advance(amount_s)
        done.set_result(None)

    try:
        loop.call_soon(functools.partial(on_timer, 0.012))
        await done
        lag = monitor.take_window()
    finally:
        monitor.uninstall()
    assert lag.longest_by.endswith("on_timer")
    assert lag.longest_by.startswith(__name__)
    assert abs(lag.longest_ms - 12.0) < 1e-6


def test_other_loops_are_not_timed_and_uninstall_stops_timing() -> None:
    clock = FakeClock()
    monitor = LoopMonitor(clock=clock)
    mine = asyncio.new_event_loop()
    other = asyncio.new_event_loop()
    try:
        monitor.install(mine)
        other.run_until_complete(asyncio.sleep(0))
        assert monitor.window().callbacks == 0
        mine.run_until_complete(asyncio.sleep(0))
        assert monitor.window().callbacks > 0
        monitor.uninstall()
        monitor.reset()
        mine.run_until_complete(asyncio.sleep(0))
        assert monitor.window().callbacks == 0
    finally:
        monitor.uninstall()
        mine.close()
        other.close()


def test_busy_share_is_the_callbacks_time_over_the_window() -> None:
    clock, cpu = FakeClock(), FakeClock()
    monitor = LoopMonitor(clock=clock, cpu_clock=cpu)
    loop = asyncio.new_event_loop()
    try:
        monitor.install(loop)

        def work() -> None:
            clock.advance(0.25)  # a quarter of the window, a tenth of it on the CPU
            cpu.advance(0.1)

        loop.call_soon(work)
        loop.run_until_complete(asyncio.sleep(0))
        clock.advance(0.75)  # idle
        lag = monitor.take_window()
    finally:
        monitor.uninstall()
        loop.close()
    assert abs(lag.window_s - 1.0) < 1e-9
    assert abs(lag.busy_pct - 25.0) < 1e-6
    assert abs(lag.cpu_pct - 10.0) < 1e-6


def test_dbw_status_shows_who_held_the_loop() -> None:
    doc = {
        "mode": "ready",
        "event_loop": {
            "window_s": 1.0,
            "callbacks": 900,
            "slow_callbacks": 2,
            "busy_pct": 31.0,
            "longest_callback_ms": 7.25,
            "longest_callback_by": "task lms111_left",
            "cpu_pct": 12.0,
            "since_start": {
                "longest_callback_ms": 41.0,
                "longest_callback_by": "task status",
                "slow_callbacks": 9,
            },
        },
    }
    line = next(x for x in render_status(doc).splitlines() if x.startswith("event loop:"))
    assert "ms (task lms111_left)" in line
    assert "2 slow in the last 1.0 s" in line
    assert "31 % busy (12 % CPU)" in line
    assert "worst since start 41.0 ms (task status)" in line


def test_a_clock_too_costly_to_read_leaves_the_loop_untimed_and_says_why() -> None:
    monitor = LoopMonitor()
    monitor.clock_read_s = lambda reads=200: 32e-6  # type: ignore[method-assign]  # UML's
    loop = asyncio.new_event_loop()
    try:
        assert monitor.install(loop) is False
        loop.run_until_complete(asyncio.sleep(0))
        assert monitor.window().callbacks == 0
        assert "32.0 us" in monitor.disabled_reason
        doc = {"event_loop": {**monitor.window().as_dict(), "since_start": monitor.worst()}}
        line = next(x for x in render_status(doc).splitlines() if x.startswith("event loop"))
        assert line.startswith("event loop: not monitored: a clock read costs 32.0 us")
    finally:
        monitor.uninstall()
        loop.close()
