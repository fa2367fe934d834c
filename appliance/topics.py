"""Every topic of the daemon by name, so status views can list input ages.

The topics themselves (``drivers.topics``) belong to the drivers that publish them; the
runtime adopts each one here when it wires the vehicle.
"""

from __future__ import annotations

from typing import Any

from drivers.topics import Topic


class TopicRegistry:
    """Every topic of the daemon by name, so status views can list input ages."""

    def __init__(self) -> None:
        self._topics: dict[str, Topic[Any]] = {}

    def get(self, name: str) -> Topic[Any]:
        topic = self._topics.get(name)
        if topic is None:
            topic = self._topics[name] = Topic(name)
        return topic

    def register(self, name: str, topic: Topic[Any]) -> None:
        """Adopt a topic a driver owns, so status views list its age."""
        if name in self._topics and self._topics[name] is not topic:
            raise ValueError(f"topic {name!r} is already registered")
        self._topics[name] = topic

    def items(self) -> list[tuple[str, Topic[Any]]]:
        return list(self._topics.items())

    def ages_s(self, now_s: float) -> dict[str, float]:
        return {name: topic.age_s(now_s) for name, topic in self._topics.items()}
