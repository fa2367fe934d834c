"""Heartbeat and restart budget: the pure rules the supervisor is built on."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from safety.watchdog import Heartbeat, RestartBudget, RestartPolicy


def test_heartbeat_is_dead_until_first_beat() -> None:
    hb = Heartbeat(0.1)
    assert not hb.is_alive(0.0)
    assert hb.age_s(5.0) == math.inf
    hb.beat(1.0)
    assert hb.is_alive(1.09)
    assert not hb.is_alive(1.1001)
    hb.reset()
    assert not hb.is_alive(1.0)


def test_heartbeat_rejects_non_positive_deadline() -> None:
    with pytest.raises(ValueError, match="positive"):
        Heartbeat(0.0)


def test_backoff_grows_geometrically_up_to_the_cap_then_gives_up() -> None:
    budget = RestartBudget(
        RestartPolicy(initial_backoff_s=0.1, backoff_factor=2.0, backoff_cap_s=0.5, max_restarts=5)
    )
    delays = [budget.on_failure(ran_for_s=0.01) for _ in range(6)]
    assert delays == [0.1, 0.2, 0.4, 0.5, 0.5, None]
    assert budget.total_restarts == 5


def test_long_healthy_run_restores_the_budget() -> None:
    policy = RestartPolicy(max_restarts=2, budget_reset_after_s=10.0)
    budget = RestartBudget(policy)
    assert budget.on_failure(1.0) is not None
    assert budget.on_failure(1.0) is not None
    assert budget.on_failure(1.0) is None
    fresh = RestartBudget(policy)
    fresh.on_failure(1.0)
    fresh.on_failure(1.0)
    assert fresh.on_failure(10.0) == policy.initial_backoff_s  # a new episode


@pytest.mark.parametrize(
    "kwargs",
    [
        {"initial_backoff_s": 0.0},
        {"initial_backoff_s": 2.0, "backoff_cap_s": 1.0},
        {"backoff_factor": 0.5},
        {"max_restarts": -1},
    ],
)
def test_restart_policy_rejects_nonsense(kwargs: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="need"):
        RestartPolicy(**kwargs)


@given(
    initial=st.floats(0.001, 5.0),
    factor=st.floats(1.0, 5.0),
    cap_extra=st.floats(0.0, 50.0),
    max_restarts=st.integers(0, 30),
    runs=st.lists(st.floats(0.0, 100.0), max_size=60),
)
def test_budget_properties(
    initial: float, factor: float, cap_extra: float, max_restarts: int, runs: list[float]
) -> None:
    policy = RestartPolicy(
        initial_backoff_s=initial,
        backoff_factor=factor,
        backoff_cap_s=initial + cap_extra,
        max_restarts=max_restarts,
        budget_reset_after_s=30.0,
    )
    budget = RestartBudget(policy)
    in_episode = 0
    for ran_for_s in runs:
        if ran_for_s >= 30.0:
            in_episode = 0
        delay = budget.on_failure(ran_for_s)
        if in_episode >= max_restarts:
            assert delay is None
        else:
            in_episode += 1
            assert delay is not None
            assert initial <= delay <= policy.backoff_cap_s
        assert budget.restarts_in_episode <= max_restarts
