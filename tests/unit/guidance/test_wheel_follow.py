"""The wheel follower: its wish never turns faster than the rate, reaches what is wanted,
starts from the wheels, and the speed waits for the wheels (0 far off, 1 on them)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.guidance.wheel_follow import WheelFollower, WheelFollowParams

RATE = math.radians(8.0)
angles = st.floats(-1.2, 1.2)


@given(st.lists(st.tuples(angles, angles), min_size=1, max_size=60), angles)
def test_the_wish_turns_at_the_rate_at_most_and_the_share_is_a_share(
    steps: list[tuple[float, float]], start: float
) -> None:
    follower = WheelFollower(WheelFollowParams(RATE))
    wish, share = follower.update(steps[0][0], start, 0.0)
    assert abs(wish - start) <= 1e-12 and 0.0 <= share <= 1.0
    for k, (wanted, measured) in enumerate(steps[1:], start=1):
        before = wish
        wish, share = follower.update(wanted, measured, 0.02 * k)
        assert abs(wish - before) <= RATE * 0.02 + 1e-12
        assert 0.0 <= share <= 1.0
        if abs(wanted - measured) >= math.radians(6.0):
            assert share == 0.0


def test_it_reaches_what_is_wanted_and_drives_once_the_wheels_are_there() -> None:
    follower = WheelFollower(WheelFollowParams(RATE))
    wish, share = follower.update(0.5, 0.0, 0.0)
    assert wish == 0.0 and share == 0.0  # standing: the wheels are 29 degrees off
    t = 0.0
    while wish < 0.5:
        t += 0.02
        wish, _ = follower.update(0.5, wish, t)
    assert t == pytest.approx(0.5 / RATE, abs=0.03)
    assert follower.update(0.5, 0.5, t + 0.02) == (0.5, 1.0)
    assert follower.update(0.5, None, t + 0.04)[1] == 0.0  # wheels not seen: stand
    follower.reset()
    assert follower.update(0.3, -0.1, 10.0)[0] == -0.1  # again from the wheels
