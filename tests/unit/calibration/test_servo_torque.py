"""The Fig. 21 check: the steering servo's torque now against the baseline's."""

from __future__ import annotations

import math

import numpy as np
import pytest

from calibration.servo_torque import (
    IDLE,
    TorqueParams,
    TorqueRecorder,
    compare_torque,
    torque_stats,
)
from drivers.actuators.messages import SteeringMode
from drivers.actuators.steering_model import ServoParams, ServoState, ServoTarget, step_servo

HUSKY_SERVO = ServoParams()


def sweep(
    seed: int, torque_scale: float = 1.0, params: ServoParams = HUSKY_SERVO
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two minutes of the simulated servo following random sine sweeps up to 9 rad."""
    rng = np.random.default_rng(seed)
    state, wheels, rates, torques = ServoState(), [], [], []
    dt_s, t_s, end_s, start_s, amplitude, period = 0.02, 0.0, 0.0, 0.0, 0.0, 1.0
    while t_s < 120.0:
        if t_s >= end_s:
            amplitude, period = rng.uniform(2.0, 9.0), rng.uniform(3.0, 10.0)
            start_s, end_s = t_s, t_s + period
        target = amplitude * math.sin(2 * math.pi * (t_s - start_s) / period)
        before = state.wheel_rad
        command = ServoTarget(SteeringMode.POSITION, target)
        state = step_servo(state, command, dt_s, params, torque_scale)
        wheels.append(state.wheel_rad)
        rates.append((state.wheel_rad - before) / dt_s)
        torques.append(state.torque_nm)
        t_s += dt_s
    return np.array(wheels), np.array(rates), np.array(torques)


BASELINE = torque_stats(*sweep(1))


def test_the_same_servo_driven_differently_needs_no_retuning() -> None:
    for seed in (2, 3, 4):
        comparison = compare_torque(BASELINE, torque_stats(*sweep(seed)))
        assert not comparison.retune, comparison.reasons
        assert abs(comparison.relative_change) < 0.01


def test_the_fit_recovers_the_simulated_load() -> None:
    c0, c_wheel, c_rate = BASELINE.coeffs
    assert c0 == pytest.approx(HUSKY_SERVO.friction_nm, rel=0.01)
    assert c_wheel == pytest.approx(HUSKY_SERVO.centering_nm_per_rad, rel=0.01)
    assert abs(c_rate) < 0.01  # the simulated load does not grow with the rate
    assert BASELINE.stall_fraction < 0.01


def test_a_servo_run_short_of_torque_stalls_and_asks_for_retuning() -> None:
    comparison = compare_torque(BASELINE, torque_stats(*sweep(2, torque_scale=0.6)))
    assert comparison.retune
    assert comparison.stall_fraction_change > 0.3
    assert "runs short of torque" in comparison.reasons[-1]


def test_torque_to_spare_changes_nothing() -> None:
    comparison = compare_torque(BASELINE, torque_stats(*sweep(2, torque_scale=0.85)))
    assert not comparison.retune


@pytest.mark.parametrize(
    ("servo", "retune"),
    [
        (ServoParams(friction_nm=6.0), True),
        (ServoParams(centering_nm_per_rad=0.8), True),
        (ServoParams(friction_nm=4.5), False),
    ],
)
def test_a_heavier_load_asks_for_retuning_beyond_15_percent(
    servo: ServoParams, retune: bool
) -> None:
    comparison = compare_torque(BASELINE, torque_stats(*sweep(2, params=servo)))
    hard_wheel = BASELINE.hard_wheel_rad
    expected = (servo.friction_nm + servo.centering_nm_per_rad * hard_wheel) / (
        HUSKY_SERVO.friction_nm + HUSKY_SERVO.centering_nm_per_rad * hard_wheel
    )
    assert comparison.relative_change == pytest.approx(expected - 1.0, abs=0.01)
    assert comparison.retune == retune


def test_the_recorder_counts_what_the_fit_can_use_and_gives_the_same_stats() -> None:
    wheels, rates, torques = sweep(5)
    recorder = TorqueRecorder()
    recorder.update(0.0, 1.0, 1.0)
    recorder.reset()
    assert recorder.coverage() == (0, 0)
    for row in zip(wheels, rates, torques, strict=True):
        recorder.update(*(float(v) for v in row))
    stats = recorder.stats()
    assert stats == torque_stats(wheels, rates, torques)
    assert recorder.coverage() == (stats.moving, stats.stalls)
    assert stats.moving + stats.stalls + stats.rejected[IDLE] == rates.size
    with pytest.raises(ValueError, match="non-finite"):
        recorder.update(math.nan, 1.0, 1.0)


def test_garbage_raises_value_error() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        torque_stats(np.zeros(3), np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="non-finite"):
        torque_stats(np.zeros(2), np.array([0.0, math.inf]), np.zeros(2))
    with pytest.raises(ValueError, match="steer more"):
        torque_stats(np.zeros(100), np.zeros(100), np.ones(100))
    with pytest.raises(ValueError, match="max_change"):
        TorqueParams(max_change=0.0)
    with pytest.raises(ValueError, match="min_moving_samples"):
        TorqueParams(min_moving_samples=3)
