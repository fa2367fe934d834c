"""drivers.wakeup: set, notify and timeout, against asyncio's own clock."""

from __future__ import annotations

import asyncio

import pytest

from drivers.wakeup import Wakeup


async def test_times_out_without_set() -> None:
    wakeup = Wakeup()
    loop = asyncio.get_running_loop()
    started = loop.time()
    assert await wakeup.wait(0.02) is False
    assert loop.time() - started >= 0.02


async def test_set_wakes_the_waiter_at_once_and_stays_set() -> None:
    wakeup = Wakeup()
    loop = asyncio.get_running_loop()
    loop.call_later(0.01, wakeup.set)
    started = loop.time()
    assert await wakeup.wait(10.0) is True
    assert loop.time() - started < 5.0
    assert await wakeup.wait(10.0) is True  # a set flag returns without waiting
    wakeup.clear()
    assert await wakeup.wait(0.0) is False


async def test_notify_wakes_without_setting() -> None:
    wakeup = Wakeup()
    loop = asyncio.get_running_loop()
    loop.call_later(0.01, wakeup.notify)
    started = loop.time()
    assert await wakeup.wait(10.0) is False
    assert loop.time() - started < 5.0
    wakeup.notify()  # nobody waiting: lost, as news should be
    assert await wakeup.wait(0.01) is False


async def test_cancelled_wait_leaves_no_waiter_or_timer() -> None:
    wakeup = Wakeup()
    task = asyncio.create_task(wakeup.wait(10.0))
    await asyncio.sleep(0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    loop = asyncio.get_running_loop()
    assert not [h for h in loop._scheduled if not h.cancelled()]  # type: ignore[attr-defined]
    assert await wakeup.wait(0.001) is False  # a new wait is allowed


async def test_one_waiter_at_a_time() -> None:
    wakeup = Wakeup()
    first = asyncio.create_task(wakeup.wait(10.0))
    await asyncio.sleep(0)
    with pytest.raises(RuntimeError):
        await wakeup.wait(1.0)
    wakeup.set()
    assert await first is True


def test_usable_from_one_asyncio_run_to_the_next() -> None:
    wakeup = Wakeup()
    assert asyncio.run(wakeup.wait(0.001)) is False
    assert asyncio.run(wakeup.wait(0.001)) is False  # rebinds to the new loop
