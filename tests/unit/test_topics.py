"""Latest-value topics."""

from __future__ import annotations

import asyncio
import math

from appliance.topics import TopicRegistry
from drivers.topics import Topic


def test_latest_value_and_age() -> None:
    topic: Topic[int] = Topic("x")
    assert topic.latest() is None
    assert topic.age_s(10.0) == math.inf
    topic.publish(1, stamp_s=1.0)
    sample = topic.publish(2, stamp_s=2.0)
    assert topic.latest() == sample
    assert sample.seq == 2
    assert topic.age_s(2.5) == 0.5


async def test_wait_next_sees_a_later_sample_and_slow_consumers_skip() -> None:
    topic: Topic[str] = Topic("scan")
    waiter = asyncio.create_task(topic.wait_next())
    await asyncio.sleep(0)
    topic.publish("a", 1.0)
    assert (await asyncio.wait_for(waiter, 1.0)).value == "a"
    topic.publish("b", 2.0)
    topic.publish("c", 3.0)
    nxt = await asyncio.wait_for(topic.wait_next(after_seq=1), 1.0)
    assert (nxt.value, nxt.seq) == ("c", 3)


def test_registry_lists_ages() -> None:
    reg = TopicRegistry()
    reg.get("a").publish(1, 1.0)
    reg.get("b")
    ages = reg.ages_s(2.0)
    assert ages["a"] == 1.0
    assert ages["b"] == math.inf
    assert reg.get("a") is reg.get("a")
