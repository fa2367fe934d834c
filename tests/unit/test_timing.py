"""The control loop's clockwork: the sample window's percentiles, the timerfd, the ticker."""

from __future__ import annotations

import asyncio
import select
import sys
import time

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.timerfd import open_timerfd
from appliance.timing import ControlSlot, FixedRateTicker, SampleWindow
from tests.unit.test_early_wake import FakeClock

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="timerfd is Linux's")

samples = st.lists(
    st.floats(min_value=-1e3, max_value=1e3, allow_nan=False), min_size=1, max_size=300
)
quantiles = st.lists(st.floats(min_value=0.0, max_value=100.0), min_size=1, max_size=4)


@given(values=samples, capacity=st.integers(min_value=1, max_value=400), qs=quantiles)
def test_percentiles_are_numpys_over_the_last_capacity_samples(
    values: list[float], capacity: int, qs: list[float]
) -> None:
    window = SampleWindow(capacity)
    for value in values:
        window.append(value)
    kept = values[-capacity:]
    assert len(window) == len(kept)
    expected = np.percentile(np.asarray(kept), qs)
    assert window.percentiles(qs) == pytest.approx(list(expected), rel=1e-12, abs=1e-9)
    assert window.max() == max(kept)


def test_an_empty_window_reports_nan_and_reset_empties_it() -> None:
    window = SampleWindow(4)
    assert all(np.isnan(window.percentiles([50, 99])))
    window.append(1.0)
    window.reset()
    assert len(window) == 0 and np.isnan(window.max())
    with pytest.raises(ValueError, match="capacity"):
        SampleWindow(0)


@linux_only
def test_a_timerfd_is_readable_from_its_deadline_and_cleared_by_a_read() -> None:
    timerfd = open_timerfd()
    assert timerfd is not None
    try:
        timerfd.arm(time.monotonic() + 3600.0)
        assert select.select([timerfd], [], [], 0.05)[0] == []  # an hour away: quiet
        assert timerfd.clear() == 0
        timerfd.arm(time.monotonic() + 0.01)
        assert select.select([timerfd], [], [], 5.0)[0] == [timerfd]
        assert timerfd.clear() == 1
        assert select.select([timerfd], [], [], 0.0)[0] == []  # the read cleared it
        timerfd.arm(0.0)  # long past (and not the zero that would disarm it): at once
        assert select.select([timerfd], [], [], 5.0)[0] == [timerfd]
    finally:
        timerfd.close()
    assert timerfd.closed


@linux_only
async def test_the_ticker_wakes_from_the_timerfd_on_the_monotonic_clock() -> None:
    ticker = FixedRateTicker(0.01)
    assert ticker.precise
    for _ in range(5):
        await ticker.tick()
    # The loop's backstop timer comes 2 ms later and, when both are due, runs after the
    # timerfd's reader: every tick that waited was woken by the timerfd.
    assert ticker.timerfd_wakes >= 1
    assert ticker.stats.cycles == 5
    ticker.close()
    assert not ticker.precise
    started_s = time.monotonic()
    await ticker.tick()  # the loop's timer alone still keeps the schedule
    await ticker.tick()
    assert time.monotonic() - started_s >= 0.009
    assert ticker.stats.cycles == 7


async def test_a_ticker_on_a_fake_clock_keeps_the_loops_timer() -> None:
    fake_s = [0.0]
    ticker = FixedRateTicker(0.01, clock=lambda: fake_s[0])
    assert not ticker.precise
    assert await ticker.tick() == 0.0


@linux_only
def test_a_ticker_moves_its_timerfd_to_each_new_loop() -> None:
    ticker = FixedRateTicker(0.005)

    async def two_ticks() -> None:
        await ticker.tick()
        await ticker.tick()

    asyncio.run(two_ticks())
    first = ticker.timerfd_wakes
    ticker.reset()  # what ControlLoop.run does at each (re)start
    asyncio.run(two_ticks())
    assert first >= 1 and ticker.timerfd_wakes >= 1
    ticker.close()


async def test_work_far_from_a_deadline_goes_at_once_and_near_one_waits_for_the_cycle() -> None:
    clock = FakeClock()
    slot = ControlSlot(budget_s=0.002, clock=clock)
    await slot.clear()  # no control loop attached: nothing to keep clear of
    ticker = FixedRateTicker(0.02, clock=clock)
    slot.attach(ticker)
    await slot.clear()  # the loop has not ticked yet: no deadline
    assert await ticker.tick() == 0.0  # the first cycle; the next is due at 0.02 s
    clock.now_s = 0.010
    await slot.clear()  # 10 ms to go: clear
    assert slot.deferred == 0
    clock.now_s = 0.019  # 1 ms to go: inside the 2 ms budget
    work = asyncio.ensure_future(slot.clear())
    await asyncio.sleep(0)
    assert not work.done()
    clock.now_s = 0.020
    ticking = asyncio.ensure_future(ticker.tick())
    assert await ticking == 0.020  # the cycle due ran...
    await asyncio.sleep(0)
    assert not work.done()  # ...but the work waits until the loop is done with it
    next_tick = asyncio.ensure_future(ticker.tick())  # the loop comes back: cycle done
    await asyncio.wait_for(work, 1.0)
    assert slot.deferred == 1
    next_tick.cancel()


async def test_a_stopped_control_loop_holds_work_one_period_at_most() -> None:
    clock = FakeClock()
    slot = ControlSlot(budget_s=0.002, clock=clock)
    ticker = FixedRateTicker(0.05, clock=clock)
    slot.attach(ticker)
    await ticker.tick()
    clock.now_s = 0.06  # the cycle due at 0.05 s never runs: the loop is gone
    started_s = time.monotonic()
    await asyncio.wait_for(slot.clear(), 5.0)  # released by the bound, not by a cycle
    assert time.monotonic() - started_s >= 0.04
    assert slot.deferred == 1
    clock.now_s = 0.2  # a period and more past the deadline: nobody is ticking, no wait
    await slot.clear()
    assert slot.deferred == 1  # counted only when it waits
