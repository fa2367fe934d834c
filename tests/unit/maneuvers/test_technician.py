"""The simulated technician's schedules do what the commands' instructions ask."""

from __future__ import annotations

import itertools
import math

import pytest

from appliance.maneuvers.technician import (
    Pose,
    palm_tree_schedule,
    pot_map_schedule,
    straight_legs_schedule,
)

LOCK_RAD = 9.42


def rests(poses: list[Pose], step_s: float = 0.05) -> list[tuple[float, float]]:
    """(wheel angle, seconds held) for every pose held longer than one step of a turn."""
    return [
        (pose.wheel_rad, after.t_s - pose.t_s)
        for pose, after in itertools.pairwise(poses)
        if pose.wheel_rad is not None and after.t_s - pose.t_s > 1.5 * step_s
    ]


@pytest.mark.parametrize(("pause_s", "rate"), [(2.0, 1.5), (1.0, 2.5), (0.5, 3.0)])
def test_the_pot_map_sweep_rests_at_every_half_turn_and_ends_resting_at_full_right(
    pause_s: float, rate: float
) -> None:
    poses = pot_map_schedule(LOCK_RAD, pause_s=pause_s, rate_rad_per_s=rate)
    held = rests(poses)
    stops = [wheel for wheel, _ in held]
    assert stops[0] == -LOCK_RAD and LOCK_RAD in stops and stops[-1] == 0.0
    assert all(s_ >= pause_s - 1e-9 for _, s_ in held)
    # The last rest at full right lasts what the instructions ask (2 s), whatever the pause.
    last_right = max(i for i, (wheel, _) in enumerate(held) if wheel == -LOCK_RAD)
    assert last_right > 0 and held[last_right][1] >= 2.0 - 1e-9
    # Never faster than asked, and hands off at the end.
    for before, after in itertools.pairwise(poses):
        if before.wheel_rad is not None and after.wheel_rad is not None:
            pace = abs(after.wheel_rad - before.wheel_rad) / (after.t_s - before.t_s)
            assert pace <= rate + 1e-6
    assert poses[-1].wheel_rad is None


def test_the_straight_legs_drive_then_brake_and_let_go() -> None:
    poses = straight_legs_schedule(3, leg_s=10.0, turn_s=4.0, throttle_pct=50.0)
    assert poses[-1] == Pose(poses[-1].t_s, None, 0.0, 0.0)
    assert poses[-2].brake_pct > 0.0 and poses[-2].throttle_pct == 0.0
    driving = poses[:-2]
    assert all(p.throttle_pct == 50.0 for p in driving)
    assert poses[-2].t_s == pytest.approx(3 * 10.0 + 2 * 4.0)


def test_the_palm_tree_turns_the_wheel_only_standing_and_backs_up_every_arc() -> None:
    poses = palm_tree_schedule(LOCK_RAD, arc_s=7.0, brake_s=2.0)
    held = sorted({p.wheel_rad for p in poses if p.throttle_pct > 0.0 and p.wheel_rad is not None})
    assert held == pytest.approx(sorted(LOCK_RAD - k * math.pi for k in range(7)), abs=0.2)
    assert max(held) == LOCK_RAD and min(held) == -LOCK_RAD
    # The throttle is only pressed at a held wheel angle, and each arc is backed up.
    for before, after in itertools.pairwise(poses):
        if before.wheel_rad != after.wheel_rad:
            assert before.throttle_pct == 0.0 and after.throttle_pct == 0.0
    forward = [p for p in poses if p.throttle_pct > 0.0 and not p.reverse]
    backward = [p for p in poses if p.throttle_pct > 0.0 and p.reverse]
    assert len(forward) == len(backward) == 2 * 7  # launch and cruise, per arc
    assert poses[-1].wheel_rad is None and not poses[-1].reverse
    ahead_only = palm_tree_schedule(LOCK_RAD, back_up=False)
    assert not any(p.reverse for p in ahead_only)
    # Broken off at the centre: full left to straight ahead, then hands off.
    left_half = palm_tree_schedule(LOCK_RAD, to_rad=0.0)
    held = sorted({p.wheel_rad for p in left_half if p.throttle_pct > 0.0})
    assert held == pytest.approx(sorted(LOCK_RAD - k * math.pi for k in range(4)), abs=0.2)
    assert left_half[-1].wheel_rad is None
