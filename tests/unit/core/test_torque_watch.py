"""The servo-torque watch (Fig. 21): the load while steering against the tuning's
baseline, from a servo whose load model is written out here."""

from __future__ import annotations

import math

import numpy as np

from appliance.core.torque_watch import TorqueWatch
from calibration.servo_torque import TorqueStats, torque_stats

DT_S = 0.02


def drive(seconds: float, scale: float, phase: float = 0.0) -> list[tuple[float, float, float]]:
    """(t, wheel, torque): the wheel weaving as a route makes it, the servo pushing
    c0 + c_wheel |wheel| + c_rate |rate|, times ``scale`` (a servo needing more)."""
    rows = []
    for i in range(round(seconds / DT_S)):
        t = i * DT_S
        wheel = 3.0 * math.sin(0.7 * t + phase) + 1.0 * math.sin(2.3 * t)
        rate = 2.1 * math.cos(0.7 * t + phase) + 2.3 * math.cos(2.3 * t)
        torque = scale * (1.0 + 0.4 * abs(wheel) + 0.3 * abs(rate))
        rows.append((t, wheel, math.copysign(torque, rate)))
    return rows


def baseline_stats() -> TorqueStats:
    rows = np.array(drive(60.0, 1.0))
    rate = np.gradient(rows[:, 1], rows[:, 0])
    return torque_stats(rows[:, 1], rate, rows[:, 2])


def verdicts(scale: float) -> list[bool]:
    watch = TorqueWatch(baseline_stats(), window=1500, every=500)
    made = []
    for t, wheel, torque in drive(60.0, scale, phase=1.0):
        # The encoder has a zero of its own (0.7 rad off): only its rate is used.
        comparison = watch.update(1000.0 + t, True, wheel, wheel + 0.7, torque)
        if comparison is not None:
            made.append(comparison.retune)
    return made


def test_the_same_servo_driven_otherwise_is_as_tuned() -> None:
    made = verdicts(1.0)
    assert made and not any(made)


def test_a_servo_needing_a_third_more_torque_is_flagged() -> None:
    made = verdicts(1.3)
    assert made and all(made)


def test_released_steering_and_gaps_add_nothing() -> None:
    watch = TorqueWatch(baseline_stats(), every=10)
    for i in range(100):
        assert watch.update(i * DT_S, False, 1.0, 1.0, 2.0) is None
        assert watch.update(i * DT_S, True, None, 1.0, 2.0) is None
    assert watch.last is None and watch.status()["retune"] is None
    for i in range(20):  # idle: no torque, nothing to fit
        watch.update(10.0 + i * DT_S, True, 0.0, 0.0, 0.0)
    assert watch.last is None and "samples" in watch.status()["reason"]
