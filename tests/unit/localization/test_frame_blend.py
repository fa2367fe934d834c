"""The continually varying local frame (Fig. 11): dead reckoning, and the ramped transform.

Truth is written out here: a vehicle driven in ENU, its dead-reckoned copy in a local
frame that differs from ENU by a known rigid transform (plus, where said, drift), and
fixes made from the truth. What is checked is the transform the tracker would apply.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.localization.dead_reckoning import DeadReckoning
from appliance.localization.frame_blend import (
    FixVerdict,
    FrameBlendParams,
    LocalGlobalTransform,
)
from drivers.geometry import Pose2D

DT_S = 0.02  # the control cycle
FIX_EVERY = 5  # 10 Hz fixes
SPEED_MPS = 4.47  # 10 mph
START = Pose2D(500.0, -300.0, 0.3)  # ENU, far from the origin on purpose


def _rot(yaw: float) -> np.ndarray:
    return np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])


def _map(t: Pose2D, xy: tuple[float, float]) -> np.ndarray:
    """T applied to a global point, written out with a rotation matrix."""
    return np.asarray(_rot(t.yaw_rad) @ np.array(xy) + np.array([t.x_m, t.y_m]))


def _unmap(t: Pose2D, xy: tuple[float, float] | np.ndarray) -> np.ndarray:
    return np.asarray(_rot(t.yaw_rad).T @ (np.asarray(xy) - np.array([t.x_m, t.y_m])))


@dataclass(frozen=True)
class Step:
    time_s: float
    truth: Pose2D  # ENU
    local: Pose2D  # dead-reckoned
    fix: Pose2D | None  # what the receiver said, if it spoke this cycle


def _drive(
    seconds: float,
    *,
    sigma_m: float = 0.0,
    turn_rps: float = 0.0,
    gyro_bias_rps: float = 0.0,
    jump_at_s: float | None = None,
    jump_m: tuple[float, float] = (0.0, 0.0),
    seed: int = 0,
) -> Iterator[Step]:
    """The truth (trapezoidal yaw, the same rule as the dead reckoning) and its copies."""
    rng = np.random.default_rng(seed)
    dr = DeadReckoning()
    x, y, yaw, previous_rate = START.x_m, START.y_m, START.yaw_rad, 0.0
    for k in range(round(seconds / DT_S)):
        now = k * DT_S
        rate = turn_rps * math.sin(now / 6.0)
        if k:
            delta = 0.5 * (rate + previous_rate) * DT_S
            yaw += delta
            chord = SPEED_MPS * DT_S * (math.sin(delta / 2) / (delta / 2) if delta else 1.0)
            x += chord * math.cos(yaw - delta / 2)
            y += chord * math.sin(yaw - delta / 2)
        previous_rate = rate
        local = dr.update(SPEED_MPS, now, yaw_rate_rps=rate + gyro_bias_rps)
        fix = None
        if k % FIX_EVERY == 0:
            fx, fy = x + rng.normal(0, sigma_m), y + rng.normal(0, sigma_m)
            if jump_at_s is not None and now >= jump_at_s:
                fx, fy = fx + jump_m[0], fy + jump_m[1]
            fix = Pose2D(fx, fy, yaw)
        yield Step(now, Pose2D(x, y, yaw), local, fix)


def _true_transform(truth: Pose2D, local: Pose2D) -> Pose2D:
    """local ← global from one exact pair, written out (not through the code under test)."""
    yaw = local.yaw_rad - truth.yaw_rad
    t = np.array([local.x_m, local.y_m]) - _rot(yaw) @ np.array([truth.x_m, truth.y_m])
    return Pose2D(float(t[0]), float(t[1]), yaw)


# -- dead reckoning ------------------------------------------------------------------------


def test_dead_reckoning_straight_line_is_exact() -> None:
    dr = DeadReckoning()
    for k in range(101):
        pose = dr.update(2.0, 0.1 * k, heading_rad=0.5)
    assert pose.x_m == pytest.approx(2.0 * 10.0 * math.cos(0.5), abs=1e-9)
    assert pose.y_m == pytest.approx(2.0 * 10.0 * math.sin(0.5), abs=1e-9)
    assert pose.yaw_rad == pytest.approx(0.5)


@pytest.mark.parametrize("by_heading", [False, True])
def test_dead_reckoning_follows_a_circle_exactly(by_heading: bool) -> None:
    speed, dt, steps = 3.0, 0.05, 300
    rate = math.pi / (steps * dt)  # half a turn in 300 steps: radius 14.3 m
    dr = DeadReckoning()
    for k in range(steps + 1):
        t = k * dt
        if by_heading:
            dr.update(speed, t, heading_rad=rate * t)
        else:
            dr.update(speed, t, yaw_rate_rps=rate)
    radius = speed / rate
    assert dr.pose.x_m == pytest.approx(0.0, abs=1e-9)
    assert dr.pose.y_m == pytest.approx(2 * radius, abs=1e-9)  # the far side of the circle
    assert abs(dr.pose.yaw_rad) == pytest.approx(math.pi, abs=1e-9)


@given(
    st.lists(
        st.tuples(st.floats(-5.0, 10.0), st.floats(-1.0, 1.0), st.floats(0.001, 0.2)),
        min_size=2,
        max_size=40,
    )
)
def test_dead_reckoning_moves_no_more_than_it_drove(
    inputs: list[tuple[float, float, float]],
) -> None:
    dr = DeadReckoning()
    now, previous_speed = 0.0, inputs[0][0]
    last = dr.update(inputs[0][0], now, yaw_rate_rps=inputs[0][1])
    for speed, rate, dt in inputs[1:]:
        now += dt
        pose = dr.update(speed, now, yaw_rate_rps=rate)
        bound = 0.5 * (abs(speed) + abs(previous_speed)) * dt + 1e-12
        assert math.hypot(pose.x_m - last.x_m, pose.y_m - last.y_m) <= bound
        last, previous_speed = pose, speed


def test_pose_at_interpolates_the_history() -> None:
    dr = DeadReckoning()
    for k in range(200):
        dr.update(1.0, 0.01 * k, heading_rad=0.0)
    assert dr.pose_at(1.234) == pytest.approx(Pose2D(1.234, 0.0, 0.0), abs=1e-9)
    assert dr.pose_at(1.99) == pytest.approx(Pose2D(1.99, 0.0, 0.0), abs=1e-9)
    assert dr.pose_at(2.5) is None  # the future
    assert dr.pose_at(-1.0) is None  # older than the history kept (2 s)


def test_dead_reckoning_refuses_bad_input() -> None:
    dr = DeadReckoning()
    with pytest.raises(ValueError, match="exactly one"):
        dr.update(1.0, 0.0)
    with pytest.raises(ValueError, match="exactly one"):
        dr.update(1.0, 0.0, heading_rad=0.0, yaw_rate_rps=0.0)
    with pytest.raises(ValueError, match="finite"):
        dr.update(math.nan, 0.0, heading_rad=0.0)
    dr.update(1.0, 1.0, heading_rad=0.0)
    with pytest.raises(ValueError, match="backwards"):
        dr.update(1.0, 0.5, heading_rad=0.0)


# -- the transform -------------------------------------------------------------------------


def test_nothing_is_known_before_the_first_fix() -> None:
    blend = LocalGlobalTransform()
    assert not blend.ready
    with pytest.raises(RuntimeError, match="no fix yet"):
        blend.current(0.0)


def test_perfect_fixes_hold_the_transform_and_map_the_route_exactly() -> None:
    blend = LocalGlobalTransform()
    route = np.array(
        [[START.x_m + d * math.cos(0.3), START.y_m + d * math.sin(0.3)] for d in range(0, 300, 7)]
    )
    expected = None
    for step in _drive(60.0):
        if step.fix is not None:
            assert blend.update_fix(step.fix, 0.02, step.local, step.time_s) is FixVerdict.ACCEPTED
        if expected is None:
            expected = _true_transform(step.truth, step.local)
        got = blend.current(step.time_s)
        assert got == pytest.approx(expected, abs=1e-9)
    assert expected is not None
    want = np.array([_map(expected, (float(x), float(y))) for x, y in route])
    assert np.allclose(blend.to_local(route, 60.0), want, atol=1e-9)
    assert blend.outliers == 0


def _check_rate_bounds(
    blend: LocalGlobalTransform, before: Pose2D, after: Pose2D, pivot: Pose2D
) -> None:
    """The global point under the vehicle moves ≤ v dt; any point r away ≤ v dt + ω dt r."""
    p = blend.params
    g = _unmap(before, (pivot.x_m, pivot.y_m))
    moved = np.linalg.norm(_map(after, tuple(g)) - _map(before, tuple(g)))
    assert moved <= p.max_translation_rate_mps * DT_S + 1e-9
    turned = abs(math.remainder(after.yaw_rad - before.yaw_rad, math.tau))
    assert turned <= p.max_rotation_rate_rps * DT_S + 1e-12
    for offset in ((30.0, 0.0), (0.0, -30.0)):
        far = g + np.array(offset)
        moved = np.linalg.norm(_map(after, tuple(far)) - _map(before, tuple(far)))
        assert moved <= (p.max_translation_rate_mps + p.max_rotation_rate_rps * 30.0) * DT_S + 1e-9


@pytest.mark.parametrize("size_m", [0.3, 1.0])
def test_a_jump_that_lasts_is_believed_after_the_wait_and_spread_at_a_bounded_rate(
    size_m: float,
) -> None:
    """Held for adopt_after_s (30 s), then followed within the ramp's time: 0.3 m by the
    2 s fade, 1.0 m by the 0.2 m/s bound (5 s)."""
    jump, jump_at = (size_m * math.cos(1.0), size_m * math.sin(1.0)), 40.0
    blend = LocalGlobalTransform()
    p = blend.params
    # the regime starts at the first of the fixes that agree on it
    adopted = jump_at + p.adopt_after_s
    earliest = adopted + (size_m - 1e-3) / p.max_translation_rate_mps
    deadline = adopted + size_m / p.max_translation_rate_mps + p.estimate_period_s + 0.5
    before, pivot, reached_s, verdicts = None, None, None, []
    for step in _drive(100.0, jump_at_s=jump_at, jump_m=jump):
        if step.fix is not None:
            verdicts.append(blend.update_fix(step.fix, 0.05, step.local, step.time_s))
            pivot = step.local
        after = blend.current(step.time_s)
        if before is not None and pivot is not None:
            _check_rate_bounds(blend, before, after, pivot)
        before = after
        # where the jumped fixes say the vehicle is, in the local frame, vs where it is
        jumped = _map(after, (step.truth.x_m + jump[0], step.truth.y_m + jump[1]))
        error = np.linalg.norm(jumped - [step.local.x_m, step.local.y_m])
        if step.time_s < adopted:
            assert error == pytest.approx(size_m, abs=1e-6)  # held: not followed yet
        elif reached_s is None and error < 1e-3:
            reached_s = step.time_s
    assert reached_s is not None and reached_s <= deadline
    if size_m / p.blend_s > p.max_translation_rate_mps:  # the ramp, not the fade, is slower
        assert reached_s >= earliest
    assert verdicts.count(FixVerdict.JUMP_FOLLOWED) == 1
    assert blend.jumps_followed == 1
    assert blend.outliers == p.jump_persist_fixes


def test_a_fix_that_flips_back_and_forth_is_never_followed() -> None:
    """The Husky's LGPR/GPS threshold switching: 0.3 m away for 15 s, back for 15 s, with
    5 cm noise and each flip in its own direction. The path stays where the first
    regime put it: measured at the vehicle, RMS 3.0 cm and 6.6 cm at worst (noise alone:
    1.1 and 2.9 cm); following the flips would be 0.3 m half of the time."""
    blend = LocalGlobalTransform()
    errors = []
    for step in _drive(200.0, sigma_m=0.05, seed=11):
        if step.fix is not None:
            period = int(step.time_s // 15.0)
            fix = step.fix
            if period % 2 == 1:
                angle = 2.0 * math.pi * ((period * 0.618) % 1.0)
                fix = Pose2D(
                    fix.x_m + 0.3 * math.cos(angle), fix.y_m + 0.3 * math.sin(angle), fix.yaw_rad
                )
            blend.update_fix(fix, 0.05, step.local, step.time_s)
        here = _map(blend.current(step.time_s), (step.truth.x_m, step.truth.y_m))
        if step.time_s > 10.0:
            errors.append(float(np.linalg.norm(here - [step.local.x_m, step.local.y_m])))
    rms = float(np.sqrt(np.mean(np.square(errors))))
    print(f"flipping fix: RMS {rms * 100:.1f} cm, max {max(errors) * 100:.1f} cm")
    assert rms < 0.04
    assert max(errors) < 0.1
    assert blend.jumps_followed == 0
    assert blend.jumps_held > 0


def test_a_jump_landing_near_an_old_regime_is_measured_again() -> None:
    """Two 0.3 m jumps 35° apart, each 20 s long with 20 s between: the second lands
    within the gate of the first's remembered vector (0.18 m apart) and is taken into that
    regime. Its vector is measured again, not kept: kept, it would put the trusted offset
    0.18 m off once the window holds only the second jump's fixes."""
    blend = LocalGlobalTransform()
    jumps = {1: 0.0, 3: math.radians(35.0)}
    errors = []
    for step in _drive(100.0, sigma_m=0.05, seed=5):
        if step.fix is not None:
            period = int(step.time_s // 20.0)
            fix = step.fix
            if period in jumps:
                angle = jumps[period]
                fix = Pose2D(
                    fix.x_m + 0.3 * math.cos(angle), fix.y_m + 0.3 * math.sin(angle), fix.yaw_rad
                )
            blend.update_fix(fix, 0.05, step.local, step.time_s)
        here = _map(blend.current(step.time_s), (step.truth.x_m, step.truth.y_m))
        if step.time_s > 60.0:  # during and after the second jump
            errors.append(float(np.linalg.norm(here - [step.local.x_m, step.local.y_m])))
    rms = float(np.sqrt(np.mean(np.square(errors))))
    print(f"second jump near the first: RMS {rms * 100:.1f} cm, max {max(errors) * 100:.1f} cm")
    assert blend.jumps_followed == 0 and blend.jumps_held > 0
    assert rms < 0.04
    assert max(errors) < 0.1


def test_white_fix_noise_barely_moves_the_path() -> None:
    """σ = 5 cm at 10 Hz: measured RMS 1.1 cm, max 2.9 cm at the vehicle (20 s window)."""
    blend = LocalGlobalTransform()
    errors, speeds, previous = [], [], None
    for step in _drive(200.0, sigma_m=0.05, seed=7):
        if step.fix is not None:
            blend.update_fix(step.fix, 0.05, step.local, step.time_s)
        applied = blend.current(step.time_s)
        here = _map(applied, (step.truth.x_m, step.truth.y_m))
        if step.time_s > 30.0:  # the window has filled
            errors.append(np.linalg.norm(here - [step.local.x_m, step.local.y_m]))
            assert previous is not None
            there = _map(previous, (step.truth.x_m, step.truth.y_m))
            speeds.append(np.linalg.norm(here - there) / DT_S)
        previous = applied
    rms = math.sqrt(float(np.mean(np.square(errors))))
    assert rms < 0.02
    assert max(errors) < 0.04
    assert max(speeds) < 0.05  # the path drifts by cm/s, never the 0.2 m/s of a jump ramp


def test_a_gyro_bias_is_tracked() -> None:
    bias = math.radians(0.02)  # 72°/h: a poor gyro; 6° of drift over the run
    blend = LocalGlobalTransform()
    errors, yaw_errors, first = [], [], None
    for step in _drive(300.0, sigma_m=0.05, turn_rps=0.15, gyro_bias_rps=bias, seed=3):
        if step.fix is not None:
            blend.update_fix(step.fix, 0.05, step.local, step.time_s)
        applied = blend.current(step.time_s)
        first = first or applied
        if step.time_s > 30.0:
            here = _map(applied, (step.truth.x_m, step.truth.y_m))
            errors.append(np.linalg.norm(here - [step.local.x_m, step.local.y_m]))
            true_yaw = step.local.yaw_rad - step.truth.yaw_rad
            yaw_errors.append(abs(math.remainder(applied.yaw_rad - true_yaw, math.tau)))
    assert math.sqrt(float(np.mean(np.square(errors)))) < 0.025
    assert max(errors) < 0.06
    assert max(yaw_errors) < math.radians(0.1)
    # and the drift was real: the first transform, kept, would be metres off by now
    assert first is not None
    stale = _map(first, (step.truth.x_m, step.truth.y_m))
    assert np.linalg.norm(stale - [step.local.x_m, step.local.y_m]) > 1.0


def test_lone_and_scattered_outliers_are_not_followed() -> None:
    blend = LocalGlobalTransform()
    expected, throws = None, {10.0: (2.0, 0.0), 12.0: (0.0, 2.0), 12.1: (-2.0, 0.0), 12.2: (0, -2)}
    for step in _drive(20.0):
        if step.fix is not None:
            fix = step.fix
            throw = throws.get(round(step.time_s, 2))
            if throw is not None:
                fix = Pose2D(fix.x_m + throw[0], fix.y_m + throw[1], fix.yaw_rad)
            verdict = blend.update_fix(fix, 0.05, step.local, step.time_s)
            assert verdict is (FixVerdict.OUTLIER if throw else FixVerdict.ACCEPTED)
        expected = expected or _true_transform(step.truth, step.local)
        assert blend.current(step.time_s) == pytest.approx(expected, abs=1e-9)
    assert blend.outliers == 4 and blend.jumps_followed == 0


def test_fixes_are_weighted_by_inverse_variance() -> None:
    blend = LocalGlobalTransform()
    here, offset = Pose2D(10.0, 20.0, 0.0), 0.1
    weights = {0.02: 1 / 0.02**2, 0.2: 1 / 0.2**2}
    for k in range(100):  # standing still: alternate a good fix and a poor one 0.1 m east
        sigma = 0.02 if k % 2 == 0 else 0.2
        fix = Pose2D(here.x_m + (0.0 if sigma == 0.02 else offset), here.y_m, 0.0)
        blend.update_fix(fix, sigma, Pose2D(0.0, 0.0, 0.0), 0.1 * k)
    weighted_east = offset * weights[0.2] / (weights[0.02] + weights[0.2])  # ≈ 1 mm, not 5 cm
    estimate = blend.estimate(9.9 + blend.params.blend_s)
    assert -estimate.x_m - here.x_m == pytest.approx(weighted_east, abs=2e-4)


def test_old_fixes_are_ignored_and_bad_fixes_refused() -> None:
    blend = LocalGlobalTransform()
    blend.update_fix(Pose2D(0, 0, 0), 0.05, Pose2D(0, 0, 0), 1.0)
    assert blend.update_fix(Pose2D(5, 5, 0), 0.05, Pose2D(0, 0, 0), 0.5) is FixVerdict.OUT_OF_ORDER
    with pytest.raises(ValueError, match="finite"):
        blend.update_fix(Pose2D(math.nan, 0, 0), 0.05, Pose2D(0, 0, 0), 2.0)
    with pytest.raises(ValueError, match="σ"):
        blend.update_fix(Pose2D(0, 0, 0), -1.0, Pose2D(0, 0, 0), 2.0)
    with pytest.raises(ValueError, match="shape"):
        blend.to_local(np.zeros((3, 3)), 2.0)
    with pytest.raises(ValueError, match="window_s"):
        FrameBlendParams(window_s=0.0)


@given(
    st.tuples(st.floats(-5e3, 5e3), st.floats(-5e3, 5e3), st.floats(-math.pi, math.pi)),
    st.tuples(st.floats(-5e3, 5e3), st.floats(-5e3, 5e3), st.floats(-math.pi, math.pi)),
    st.lists(st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)), min_size=1, max_size=20),
)
def test_to_local_and_to_global_are_inverses(
    fix: tuple[float, float, float],
    local: tuple[float, float, float],
    points: list[tuple[float, float]],
) -> None:
    blend = LocalGlobalTransform()
    blend.update_fix(Pose2D(*fix), 0.05, Pose2D(*local), 0.0)
    p = np.array(points)
    assert np.allclose(blend.to_local(blend.to_global(p, 0.0), 0.0), p, atol=1e-6)
    assert np.allclose(blend.to_global(blend.to_local(p, 0.0), 0.0), p, atol=1e-6)
    # and the fix maps onto the local pose it came with
    assert np.allclose(blend.to_local(np.array([fix[:2]]), 0.0), [local[:2]], atol=1e-6)


def test_a_heading_jump_turns_the_path_about_the_vehicle_at_a_bounded_rate() -> None:
    """Standing still, the INS heading steps by 10°: the path turns about the vehicle,
    at most 1°/s, and the vehicle's own point does not move."""
    blend = LocalGlobalTransform()
    p = blend.params
    here, local, step_rad = Pose2D(100.0, 50.0, 0.2), Pose2D(3.0, 4.0, 0.0), math.radians(10.0)
    before, reached_s = None, None
    for k in range(1500):
        now = k * DT_S
        heading = here.yaw_rad + (step_rad if now >= 5.0 else 0.0)
        if k % FIX_EVERY == 0:
            blend.update_fix(Pose2D(here.x_m, here.y_m, heading), 0.05, local, now)
        after = blend.current(now)
        if before is not None:
            _check_rate_bounds(blend, before, after, local)
        before = after
        assert np.allclose(_map(after, (here.x_m, here.y_m)), [local.x_m, local.y_m], atol=1e-9)
        want_yaw = local.yaw_rad - heading
        if now >= 5.0 and reached_s is None and abs(after.yaw_rad - want_yaw) < 1e-6:
            reached_s = now
    assert reached_s is not None
    assert 5.0 + step_rad / p.max_rotation_rate_rps - 0.05 <= reached_s
    assert reached_s <= 5.0 + step_rad / p.max_rotation_rate_rps + p.estimate_period_s
    # a heading jump is followed at once (the estimate's yaw is the newest fixes'): the
    # switching the regimes guard against moves positions, not the INS's heading
    assert blend.jumps_followed == 0
