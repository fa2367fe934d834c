"""Watchdog primitives: heartbeats, restart budgets and backoff, with time as an argument.

These are the pieces the supervisor, the control loop and the systemd notifier agree on.
They hold no clock and no task: the caller passes ``now_s`` (monotonic seconds), so the
same rules run in the daemon, in faster-than-real-time tests and in replay.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


class Heartbeat:
    """Liveness of one producer: alive while its last beat is younger than the deadline.

    A heartbeat that has never beaten is not alive: a service has to prove it is working,
    not merely that it was started (deny by default).
    """

    def __init__(self, deadline_s: float) -> None:
        if not deadline_s > 0:
            raise ValueError(f"deadline_s must be positive (got {deadline_s})")
        self.deadline_s = deadline_s
        self.last_beat_s: float | None = None
        self.beats = 0

    def reset(self) -> None:
        self.last_beat_s = None
        self.beats = 0

    def beat(self, now_s: float) -> None:
        self.last_beat_s = now_s
        self.beats += 1

    def age_s(self, now_s: float) -> float:
        return math.inf if self.last_beat_s is None else now_s - self.last_beat_s

    def is_alive(self, now_s: float) -> bool:
        return self.age_s(now_s) <= self.deadline_s


@dataclass(frozen=True)
class RestartPolicy:
    """How often and how fast a failing service is restarted.

    ``max_restarts`` counts restarts inside one episode; an episode ends when the service
    has run ``budget_reset_after_s`` without failing, so a service that fails once a day
    is never given up on, while one that fails in a loop is.
    """

    initial_backoff_s: float = 0.1
    backoff_factor: float = 2.0
    backoff_cap_s: float = 5.0
    max_restarts: int = 5
    budget_reset_after_s: float = 30.0

    def __post_init__(self) -> None:
        if self.initial_backoff_s <= 0 or self.backoff_cap_s < self.initial_backoff_s:
            raise ValueError("need 0 < initial_backoff_s <= backoff_cap_s")
        if self.backoff_factor < 1 or self.max_restarts < 0 or self.budget_reset_after_s <= 0:
            raise ValueError(
                "need backoff_factor >= 1, max_restarts >= 0, budget_reset_after_s > 0"
            )


class RestartBudget:
    """Decides whether a failed service may restart, and after what delay."""

    def __init__(self, policy: RestartPolicy) -> None:
        self.policy = policy
        self.restarts_in_episode = 0
        self.total_restarts = 0

    def reset(self) -> None:
        self.restarts_in_episode = 0

    def on_failure(self, ran_for_s: float) -> float | None:
        """Record a failure of a run that lasted ``ran_for_s``.

        Returns the delay before the next start, or None when the budget is exhausted.
        """
        if ran_for_s >= self.policy.budget_reset_after_s:
            self.restarts_in_episode = 0
        if self.restarts_in_episode >= self.policy.max_restarts:
            return None
        delay_s = min(
            self.policy.initial_backoff_s * self.policy.backoff_factor**self.restarts_in_episode,
            self.policy.backoff_cap_s,
        )
        self.restarts_in_episode += 1
        self.total_restarts += 1
        return delay_s
