"""The servo's rate limit, deadband, backlash and torque limit, and the pot mapping (pure)."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.actuators.messages import POT_FULL_SCALE_COUNTS, SteeringMode
from drivers.actuators.steering_model import (
    PotMapping,
    ServoParams,
    ServoState,
    ServoTarget,
    available_torque_nm,
    load_torque_nm,
    pot_counts,
    step_servo,
)

PARAMS = ServoParams()
DT_S = 0.01


def run(state: ServoState, target: ServoTarget, seconds: float, **kw: float) -> ServoState:
    params = ServoParams(**kw) if kw else PARAMS
    for _ in range(round(seconds / DT_S)):
        state = step_servo(state, target, DT_S, params)
    return state


def position(setpoint_rad: float) -> ServoTarget:
    return ServoTarget(SteeringMode.POSITION, setpoint_rad)


@given(st.floats(-9.0, 9.0), st.floats(0.001, 0.1))
def test_rate_limit_holds_for_any_step(setpoint_rad: float, dt_s: float) -> None:
    after = step_servo(ServoState(), position(setpoint_rad), dt_s, PARAMS)
    assert abs(after.motor_rad) <= PARAMS.max_rate_rad_per_s * dt_s + 1e-12


def test_large_step_slews_at_the_rate_limit() -> None:
    after = run(ServoState(), position(9.0), 0.5)
    assert after.motor_rad == pytest.approx(PARAMS.max_rate_rad_per_s * 0.5, rel=1e-9)


def test_deadband_ignores_small_errors() -> None:
    state = ServoState(motor_rad=1.0, wheel_rad=1.0 - PARAMS.backlash_rad / 2)
    assert run(state, position(1.0 + 0.9 * PARAMS.deadband_rad), 0.5) == state
    moved = run(state, position(1.0 + 2 * PARAMS.deadband_rad), 0.5)
    assert moved.motor_rad > state.motor_rad


def test_position_settles_within_the_deadband() -> None:
    after = run(ServoState(), position(2.0), 2.0)
    assert abs(after.motor_rad - 2.0) <= PARAMS.deadband_rad
    assert after.wheel_rad == pytest.approx(after.motor_rad - PARAMS.backlash_rad / 2)


def test_backlash_reversal_moves_the_servo_before_the_wheel() -> None:
    forward = run(ServoState(), position(2.0), 2.0)
    wheel_before = forward.wheel_rad
    # A reversal smaller than the play: the servo turns, the wheel does not.
    small = run(forward, position(forward.motor_rad - 0.8 * PARAMS.backlash_rad), 1.0)
    assert small.motor_rad < forward.motor_rad
    assert small.wheel_rad == wheel_before
    # Past the play the wheel follows, lagging by half the play on the other side.
    large = run(small, position(1.0), 2.0)
    assert large.wheel_rad == pytest.approx(large.motor_rad + PARAMS.backlash_rad / 2)
    assert large.wheel_rad < wheel_before


def test_torque_limit_stalls_against_a_heavy_wheel() -> None:
    weak = {"torque_limit_nm": PARAMS.friction_nm * 0.9}
    after = run(ServoState(), position(3.0), 1.0, **weak)
    assert after.wheel_rad == 0.0
    assert after.motor_rad == pytest.approx(PARAMS.backlash_rad / 2)
    assert after.torque_nm == pytest.approx(PARAMS.friction_nm * 0.9)


def test_self_centring_load_limits_how_far_a_weak_servo_turns() -> None:
    # Enough torque for the friction, not for the centring at large angles.
    limit_nm = PARAMS.friction_nm + PARAMS.centering_nm_per_rad * 2.0
    after = run(ServoState(), position(6.0), 3.0, torque_limit_nm=limit_nm)
    assert after.wheel_rad == pytest.approx(2.0, abs=0.07)
    # The load is evaluated at the start of each step: at most one step of overshoot.
    one_step_nm = PARAMS.centering_nm_per_rad * PARAMS.max_rate_rad_per_s * DT_S
    assert load_torque_nm(after.wheel_rad, PARAMS) <= limit_nm + one_step_nm


def test_torque_loss_means_the_wheel_does_not_move() -> None:
    state = ServoState()
    for _ in range(100):
        state = step_servo(state, position(3.0), DT_S, PARAMS, torque_scale=0.0)
    assert state.wheel_rad == 0.0


def test_asymmetric_torque() -> None:
    params = ServoParams(torque_asymmetry=0.2)
    assert available_torque_nm(+1, params, 1.0) == pytest.approx(12.0)
    assert available_torque_nm(-1, params, 1.0) == pytest.approx(18.0)


def test_release_moves_nothing() -> None:
    state = ServoState(motor_rad=1.0, wheel_rad=0.98, torque_nm=5.0)
    after = run(state, ServoTarget(SteeringMode.RELEASE, 5.0), 0.5)
    assert (after.motor_rad, after.wheel_rad, after.torque_nm) == (1.0, 0.98, 0.0)


def test_torque_mode_turns_only_above_the_load() -> None:
    below = run(ServoState(), ServoTarget(SteeringMode.TORQUE, 0.0, 3.0), 0.5)
    assert below.wheel_rad == 0.0
    above = run(ServoState(), ServoTarget(SteeringMode.TORQUE, 0.0, 10.0), 0.5)
    assert above.wheel_rad > 0.5
    clipped = run(ServoState(), ServoTarget(SteeringMode.TORQUE, 0.0, -30.0), 0.2)
    assert clipped.torque_nm >= -PARAMS.torque_limit_nm


def test_the_wheel_stops_at_the_steering_lock() -> None:
    after = run(ServoState(), position(15.0), 4.0)
    assert after.wheel_rad == pytest.approx(PARAMS.wheel_limit_rad)


def test_pot_mapping_is_offset_nonlinear_and_monotonic() -> None:
    mapping = PotMapping()
    assert pot_counts(0.0, mapping) == round(mapping.centre_counts) != 2048
    left, right = pot_counts(5.0, mapping), pot_counts(-5.0, mapping)
    # The cubic term makes the mapping compress at large angles, symmetric about the centre.
    assert left - mapping.centre_counts == pytest.approx(mapping.centre_counts - right, abs=1)
    assert left - mapping.centre_counts < 5.0 * mapping.gain_counts_per_rad
    angles = [x / 10 for x in range(-94, 95)]
    counts = [mapping.ideal_counts(a) for a in angles]
    assert counts == sorted(counts)
    assert min(counts) > 0 and max(counts) < POT_FULL_SCALE_COUNTS


def test_pot_noise_and_clipping() -> None:
    mapping = PotMapping()
    assert pot_counts(1.0, mapping, noise_counts=1.6) - pot_counts(1.0, mapping) in (1, 2)
    linear = PotMapping(cubic_counts_per_rad3=0.0)
    assert pot_counts(100.0, linear) == POT_FULL_SCALE_COUNTS
    assert pot_counts(-100.0, linear) == 0
