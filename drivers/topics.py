"""Latest-value topics: how drivers hand measurements to the control loop.

A control loop wants the newest value of each input and how old it is, never a queue of
stale ones; so a topic keeps exactly one sample, stamped with the (monotonic) time it
was measured. Consumers that want every sample (a recorder, a feature extractor) await
``wait_next``, which never blocks the producer: a slow consumer skips samples and can see
how many by the sequence number.

They live at the bottom of the floor plan, beside the drivers that publish into them: a
driver that owns its output needs nothing from the runtime that reads it.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

T = TypeVar("T")


@dataclass(frozen=True)
class Sample(Generic[T]):
    value: T
    stamp_s: float  # monotonic time the value was measured (or received, if that is all we know)
    seq: int  # 1 for the first sample, +1 per publish

    def age_s(self, now_s: float) -> float:
        return now_s - self.stamp_s


class Topic(Generic[T]):
    def __init__(self, name: str) -> None:
        self.name = name
        self._latest: Sample[T] | None = None
        self._seq = 0
        self._changed: asyncio.Event | None = None
        self._listeners: list[Callable[[Sample[T]], None]] = []

    def subscribe(self, listener: Callable[[Sample[T]], None]) -> None:
        """Call ``listener`` with every sample as it is published (it must not block)."""
        self._listeners.append(listener)

    def reset(self) -> None:
        self._latest = None

    def publish(self, value: T, stamp_s: float) -> Sample[T]:
        self._seq += 1
        sample = Sample(value, stamp_s, self._seq)
        self._latest = sample
        if self._changed is not None:
            self._changed.set()
            self._changed = None
        for listener in self._listeners:
            listener(sample)
        return sample

    def latest(self) -> Sample[T] | None:
        return self._latest

    def age_s(self, now_s: float) -> float:
        """Age of the latest sample; infinite if there is none (deny by default)."""
        return math.inf if self._latest is None else self._latest.age_s(now_s)

    async def wait_next(self, after_seq: int = 0) -> Sample[T]:
        """The first sample with ``seq > after_seq``, waiting for it if necessary."""
        while self._latest is None or self._latest.seq <= after_seq:
            if self._changed is None:
                self._changed = asyncio.Event()
            await self._changed.wait()
        return self._latest
