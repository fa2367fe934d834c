"""SafeBrake and SpeedRamp: the safe state and the speed set-point as functions of time.

Expectations come from the config's meaning: the fault brake is the share of full
braking that gives ``safe_stop_decel_mps2``, reached at ``safe_stop_brake_ramp_pct_per_s``;
the e-stop is ``brake_max_pct`` at once; the set-point rises at ``max_accel_mps2`` and a
controlled stop ends within ``hold_to_move_stop_distance_m``.
"""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config, parts
from appliance.config.models import Engagement, Limits
from safety.safe_state import (
    STOP_DISTANCE_MARGIN,
    SafeBrake,
    SafeKind,
    SpeedRamp,
    SpeedRampParams,
)

CONFIG = load_config("sim")
SAFETY = CONFIG.safety
LIMITS = CONFIG.limits
ENGAGEMENT = CONFIG.engagement
FAULT_PCT = 100.0 * SAFETY.safe_stop_decel_mps2 / SAFETY.full_brake_decel_mps2
RAMP = SAFETY.safe_stop_brake_ramp_pct_per_s
ACCEL = ENGAGEMENT.max_accel_mps2
MAX_SPEED = min(ENGAGEMENT.max_set_speed_mps, LIMITS.max_speed_mps)
DT_S = 0.01
NON_FINITE = [math.nan, math.inf, -math.inf]
FIRST_CYCLE_S = 0.02  # the ramp starts one nominal cycle in, so the first cycle brakes


def brake() -> SafeBrake:
    return SafeBrake(parts.safe_brake_params(SAFETY, LIMITS))


def ramp() -> SpeedRamp:
    return SpeedRamp(parts.speed_ramp_params(ENGAGEMENT, LIMITS))


def times(start_s: float = 0.0, dt_s: float = DT_S, count: int = 200) -> list[float]:
    return [start_s + i * dt_s for i in range(count)]


# ---- SafeBrake ------------------------------------------------------------------------------
def test_params_map_the_safe_stop_deceleration_to_a_brake_level() -> None:
    params = parts.safe_brake_params(SAFETY, LIMITS)
    assert params.fault_brake_pct == pytest.approx(FAULT_PCT)
    assert params.estop_brake_pct == LIMITS.brake_max_pct
    assert params.ramp_pct_per_s == RAMP


@pytest.mark.parametrize(
    ("decel_mps2", "brake_min_pct", "brake_max_pct", "expected_pct"),
    [
        (1.5, 0.0, 100.0, 30.0),
        (5.0, 0.0, 60.0, 60.0),  # never beyond the configured maximum
        (0.5, 20.0, 100.0, 20.0),  # never below the configured minimum
        (0.01, 0.0, 100.0, 1.0),  # never a "safe" state without brake
    ],
)
def test_fault_level_respects_the_brake_range(
    decel_mps2: float, brake_min_pct: float, brake_max_pct: float, expected_pct: float
) -> None:
    safety = SAFETY.model_copy(update={"safe_stop_decel_mps2": decel_mps2})
    limits = LIMITS.model_copy(
        update={"brake_min_pct": brake_min_pct, "brake_max_pct": brake_max_pct}
    )
    assert parts.safe_brake_params(safety, limits).fault_brake_pct == expected_pct


def test_no_safe_state_releases_the_brake() -> None:
    b = brake()
    assert [b.update(SafeKind.NONE, t) for t in times(count=5)] == [0.0] * 5
    b.update(SafeKind.FAULT, 1.0)
    assert b.update(SafeKind.NONE, 1.01) == 0.0


@pytest.mark.parametrize("released_before", [False, True])
def test_fault_brakes_in_the_first_cycle_then_ramps_to_its_level(released_before: bool) -> None:
    b = brake()
    if released_before:
        b.update(SafeKind.NONE, -DT_S)
    levels = [b.update(SafeKind.FAULT, t) for t in times()]
    assert 0.0 < levels[0] <= RAMP * (FIRST_CYCLE_S + DT_S) + 1e-9  # a real brake, not a step
    for before, after in itertools.pairwise(levels):
        assert 0.0 <= after - before <= RAMP * DT_S + 1e-9
    assert levels[-1] == pytest.approx(FAULT_PCT)
    assert max(levels) == pytest.approx(FAULT_PCT)


def test_a_late_cycle_does_not_jump_the_ramp() -> None:
    b = brake()
    first = b.update(SafeKind.FAULT, 0.0)
    late = b.update(SafeKind.FAULT, 5.0)  # a 5 s gap counts as at most max_step_dt_s
    assert late - first <= RAMP * b.params.max_step_dt_s + 1e-9
    assert b.update(SafeKind.FAULT, 4.0) == late  # time going backwards adds nothing


def test_estop_is_full_brake_at_once_even_during_a_ramp() -> None:
    b = brake()
    assert b.update(SafeKind.ESTOP, 0.0) == LIMITS.brake_max_pct
    b.reset()
    b.update(SafeKind.FAULT, 0.0)
    assert b.update(SafeKind.ESTOP, DT_S) == LIMITS.brake_max_pct


def test_reset_forgets_the_ramp() -> None:
    b = brake()
    for t in times():
        b.update(SafeKind.FAULT, t)
    b.reset()
    assert b.update(SafeKind.FAULT, 10.0) < FAULT_PCT


@pytest.mark.parametrize("bad_s", NON_FINITE)
def test_a_broken_clock_in_a_safe_state_brakes_fully(bad_s: float) -> None:
    b = brake()
    b.update(SafeKind.FAULT, 0.0)
    assert b.update(SafeKind.FAULT, bad_s) == LIMITS.brake_max_pct
    level = b.update(SafeKind.FAULT, DT_S)  # the clock is back: a finite, safe level
    assert math.isfinite(level) and level > 0.0


# ---- SpeedRamp ------------------------------------------------------------------------------
def test_setpoint_rises_at_the_acceleration_limit_and_stops_at_the_cap() -> None:
    r = ramp()
    setpoints = [r.update(100.0, t) for t in times(count=1000)]
    assert setpoints[0] == 0.0  # the first update has no dt: no change
    for before, after in itertools.pairwise(setpoints):
        assert 0.0 <= after - before <= ACCEL * DT_S + 1e-9
    assert setpoints[-1] == MAX_SPEED
    assert sum(1 for s in setpoints if s < MAX_SPEED) >= MAX_SPEED / (ACCEL * DT_S) - 1


def test_setpoint_falls_at_once_and_never_goes_negative() -> None:
    r = ramp()
    r.reset(2.0)
    assert r.update(0.5, 0.0) == 0.5
    assert r.update(-3.0, DT_S) == 0.0


def test_a_late_cycle_does_not_jump_the_setpoint() -> None:
    r = ramp()
    r.update(MAX_SPEED, 0.0)
    assert r.update(MAX_SPEED, 5.0) <= ACCEL * r.params.max_step_dt_s + 1e-9


@pytest.mark.parametrize("bad", NON_FINITE)
def test_a_non_finite_target_is_zero(bad: float) -> None:
    r = ramp()
    r.reset(1.5)
    assert r.update(bad, 0.0) == 0.0
    r.reset(bad)
    assert r.setpoint_mps == 0.0


@pytest.mark.parametrize("bad_s", [math.inf, -math.inf])
def test_an_infinite_time_cannot_open_the_ramp(bad_s: float) -> None:
    r = ramp()
    r.update(MAX_SPEED, 0.0)
    setpoints = [r.update(MAX_SPEED, t) for t in (bad_s, DT_S, 2 * DT_S)]
    assert all(s <= ACCEL * 3 * r.params.max_step_dt_s for s in setpoints)


def test_a_nan_time_cannot_open_the_ramp() -> None:
    r = ramp()
    r.update(MAX_SPEED, 0.0)
    setpoints = [r.update(MAX_SPEED, t) for t in (math.nan, DT_S, 2 * DT_S)]
    assert all(s <= ACCEL * 3 * r.params.max_step_dt_s for s in setpoints)


def test_controlled_stop_keeps_the_deceleration_fixed_at_the_release() -> None:
    r = ramp()
    r.reset(2.0)
    r.update(2.0, 0.0)
    setpoints = [r.update(2.0, t, controlled_stop=True) for t in times(DT_S, count=500)]
    decel = 2.0**2 / (2.0 * ENGAGEMENT.hold_to_move_stop_distance_m * STOP_DISTANCE_MARGIN)
    steps = [before - after for before, after in itertools.pairwise([2.0, *setpoints]) if after]
    assert steps == pytest.approx([decel * DT_S] * len(steps))
    assert setpoints[-1] == 0.0
    distance_m = sum(s * DT_S for s in setpoints)
    assert distance_m <= ENGAGEMENT.hold_to_move_stop_distance_m * STOP_DISTANCE_MARGIN
    assert r.update(2.0, 6.0) > 0.0  # held again: the ramp rises from 0


# The follower model below divides by the start speed (its lag is tau = x / v0), which
# overflows as v0 approaches 0: start speeds are drawn from a micrometre per second up.
MIN_START_SPEED_MPS = 1e-6


@st.composite
def ramp_cases(draw: st.DrawFn) -> tuple[SpeedRampParams, float]:
    """Any Engagement and Limits the config accepts (set speed within the speed limit) with a
    set speed of at least ``MIN_START_SPEED_MPS``, and a start speed between 1 % and all of
    the set speed and never below ``MIN_START_SPEED_MPS``: by construction, not by filter."""
    engagement = Engagement(
        max_set_speed_mps=draw(st.floats(MIN_START_SPEED_MPS, 20.0)),
        max_accel_mps2=draw(st.floats(0.0, 5.0, exclude_min=True)),
        hold_to_move_stop_distance_m=draw(st.floats(0.05, 20.0)),
    )
    params = parts.speed_ramp_params(
        engagement, Limits(max_speed_mps=20.0, max_engage_speed_mps=4.5)
    )
    lowest_share = max(0.01, MIN_START_SPEED_MPS / params.max_speed_mps)
    return params, params.max_speed_mps * draw(st.floats(lowest_share, 1.0))


@settings(max_examples=200, deadline=None)
@given(case=ramp_cases(), lag_share=st.floats(0.0, 1.0), dt_s=st.floats(0.01, 0.1))
def test_a_lagged_follower_stops_within_the_stop_distance(
    case: tuple[SpeedRampParams, float], lag_share: float, dt_s: float
) -> None:
    """A first-order follower (the PC104's speed loop) whose lag fits the margin the ramp
    leaves, tau * v <= (1 - margin) * distance, stops within the configured distance."""
    params, v0 = case
    tau_s = lag_share * (1.0 - STOP_DISTANCE_MARGIN) * params.stop_distance_m / v0
    r = SpeedRamp(params)
    r.reset(v0)
    now_s = 0.0
    r.update(v0, now_s)
    follower = v0
    distance_m = 0.0
    setpoint = v0
    while setpoint > 0.0:
        now_s += dt_s
        setpoint = r.update(v0, now_s, controlled_stop=True)
        assert setpoint >= 0.0
        # exact first-order response to the held set-point over one cycle
        decay = math.exp(-dt_s / tau_s) if tau_s > 0.0 else 0.0
        distance_m += setpoint * dt_s + (follower - setpoint) * tau_s * (1.0 - decay)
        follower = setpoint + (follower - setpoint) * decay
    distance_m += follower * tau_s  # what the follower still rolls once the set-point is 0
    assert distance_m <= params.stop_distance_m + 1e-9
