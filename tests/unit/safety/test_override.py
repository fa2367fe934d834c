"""Operator override rules: steering (dwell, hysteresis, stops, unseen wheel) and pedals."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from appliance.config import parts
from appliance.config.models import Limits, SafetyTimeouts
from safety.arbitration import OperatorInput
from safety.override import (
    OperatorOverride,
    PedalOverrideDetector,
    PedalOverrideParams,
    SteeringOverrideDetector,
)

DEG = math.pi / 180.0
# threshold 4 deg, release 2 deg, dwell 0.1 s, 8 N m, stop margin 1.5 deg, stops at 30 deg
PARAMS = parts.steering_override_params(SafetyTimeouts(), Limits())
TORQUE_NM = 10.0
NON_FINITE = [math.nan, math.inf, -math.inf]


def overriding_detector() -> SteeringOverrideDetector:
    """A detector that found an override at t = 0.1 s: the tests go on from there."""
    detector = SteeringOverrideDetector(PARAMS)
    detector.update(0.0, 10 * DEG, TORQUE_NM, 0.0)
    assert detector.update(0.0, 10 * DEG, TORQUE_NM, 0.1)
    return detector


class TestSteeringOverride:
    def test_conversion_to_radians_happens_at_the_edge(self) -> None:
        assert PARAMS.threshold_rad == pytest.approx(4 * DEG)
        assert PARAMS.release_rad == pytest.approx(2 * DEG)
        assert PARAMS.stop_margin_rad == pytest.approx(1.5 * DEG)
        assert PARAMS.max_steer_angle_rad == pytest.approx(30 * DEG)
        assert (PARAMS.dwell_s, PARAMS.min_torque_nm) == (0.1, 8.0)

    @pytest.mark.parametrize(
        "changes",
        [
            {"release_rad": 4 * DEG},
            {"release_rad": 0.0},
            {"dwell_s": -0.1},
            {"min_torque_nm": -1.0},
            {"stop_margin_rad": -0.1},
            {"max_steer_angle_rad": 0.0},
            {"threshold_rad": math.nan},
            {"dwell_s": math.inf},
        ],
    )
    def test_invalid_params_are_refused_at_construction(self, changes: dict[str, float]) -> None:
        with pytest.raises(ValueError, match="must"):
            replace(PARAMS, **changes)

    def test_small_deviation_is_not_an_override(self) -> None:
        detector = SteeringOverrideDetector(PARAMS)
        for t in range(20):
            assert not detector.update(0.1, 0.1 + 3 * DEG, TORQUE_NM, t * 0.02)

    def test_deviation_exactly_at_the_threshold_is_not_an_override(self) -> None:
        detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0))
        assert not detector.update(0.0, PARAMS.threshold_rad, TORQUE_NM, 0.0)
        assert detector.update(0.0, PARAMS.threshold_rad + 1e-9, TORQUE_NM, 0.02)

    def test_override_after_the_dwell_and_not_before(self) -> None:
        detector = SteeringOverrideDetector(PARAMS)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.0)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.0999)
        assert detector.update(0.0, 5 * DEG, TORQUE_NM, 0.1)

    def test_zero_dwell_overrides_in_the_same_update(self) -> None:
        detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0))
        assert detector.update(0.0, -5 * DEG, TORQUE_NM, 0.0)

    def test_interrupted_deviation_restarts_the_dwell(self) -> None:
        detector = SteeringOverrideDetector(PARAMS)
        detector.update(0.0, 5 * DEG, TORQUE_NM, 0.0)
        detector.update(0.0, 1 * DEG, TORQUE_NM, 0.06)  # back on track for one cycle
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.08)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.17)
        assert detector.update(0.0, 5 * DEG, TORQUE_NM, 0.181)

    def test_torque_at_the_minimum_counts_below_it_does_not_either_sign(self) -> None:
        for sign in (1.0, -1.0):
            detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0))
            assert not detector.update(0.0, 5 * DEG, sign * 7.99, 0.0)
            assert detector.update(0.0, 5 * DEG, sign * 8.0, 0.02)

    def test_weak_torque_interrupts_the_dwell(self) -> None:
        detector = SteeringOverrideDetector(PARAMS)
        detector.update(0.0, 5 * DEG, TORQUE_NM, 0.0)
        detector.update(0.0, 5 * DEG, 1.0, 0.05)  # the wheel lags, nobody holds it
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.1)

    def test_hysteresis_band_keeps_the_override(self) -> None:
        detector = overriding_detector()
        assert detector.update(0.0, 3 * DEG, 0.0, 0.12)  # below threshold, torque gone
        assert detector.update(0.0, PARAMS.release_rad, 0.0, 0.14)  # exactly at release
        assert not detector.update(0.0, PARAMS.release_rad - 1e-9, 0.0, 0.16)

    def test_after_the_release_a_new_override_needs_a_new_dwell(self) -> None:
        detector = overriding_detector()
        assert not detector.update(0.0, 0.0, 0.0, 0.12)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.14)
        assert detector.update(0.0, 5 * DEG, TORQUE_NM, 0.25)

    @pytest.mark.parametrize("side", [1.0, -1.0])
    def test_pushing_against_a_stop_is_not_an_override(self, side: float) -> None:
        detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0))
        # The wheels stand at the lock (29 deg), the request lies further out (35 deg).
        for t in range(10):
            assert not detector.update(side * 35 * DEG, side * 29 * DEG, TORQUE_NM, t * 0.02)
        # Exactly at the inner edge of the margin band is at the stop too.
        edge_rad = PARAMS.max_steer_angle_rad - PARAMS.stop_margin_rad
        assert not detector.update(side * (edge_rad + 5 * DEG), side * edge_rad, TORQUE_NM, 1.0)
        # A reading past the configured maximum is at (or past) the lock as well.
        assert not detector.update(side * 40 * DEG, side * 31 * DEG, TORQUE_NM, 1.02)

    @pytest.mark.parametrize("side", [1.0, -1.0])
    def test_a_wide_margin_excepts_a_clamped_command_at_the_stop(self, side: float) -> None:
        # The margin reaches past the threshold: the wheels stop at 25 deg short of the
        # 30 deg maximum the limiter allows, and the servo pushes them there.
        detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0, stop_margin_rad=6 * DEG))
        assert not detector.update(side * 30 * DEG, side * 25 * DEG, TORQUE_NM, 0.0)
        assert detector.update(side * 20 * DEG, side * 25 * DEG, TORQUE_NM, 0.02)

    @pytest.mark.parametrize("side", [1.0, -1.0])
    def test_just_inside_the_margin_band_the_deviation_counts(self, side: float) -> None:
        detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0))
        inside_rad = PARAMS.max_steer_angle_rad - PARAMS.stop_margin_rad - 1e-6
        assert detector.update(side * (inside_rad + 5 * DEG), side * inside_rad, TORQUE_NM, 0.0)

    @pytest.mark.parametrize("side", [1.0, -1.0])
    def test_deviation_away_from_the_stop_near_the_stop_counts(self, side: float) -> None:
        # The operator holds the wheels at the lock while the command steers back inwards.
        detector = SteeringOverrideDetector(PARAMS)
        assert not detector.update(side * 20 * DEG, side * 29.5 * DEG, TORQUE_NM, 0.0)
        assert detector.update(side * 20 * DEG, side * 29.5 * DEG, TORQUE_NM, 0.1)

    @pytest.mark.parametrize("side", [1.0, -1.0])
    def test_the_other_stop_is_not_this_stop(self, side: float) -> None:
        # Measured near one stop, commanded beyond it on the other side: a real deviation.
        detector = SteeringOverrideDetector(replace(PARAMS, dwell_s=0.0))
        assert detector.update(-side * 35 * DEG, side * 29 * DEG, TORQUE_NM, 0.0)

    def test_the_stop_exemption_does_not_end_an_override(self) -> None:
        detector = overriding_detector()
        assert detector.update(35 * DEG, 29 * DEG, TORQUE_NM, 0.12)

    def test_released_steering_is_never_an_override_and_resets(self) -> None:
        detector = overriding_detector()
        assert not detector.update(None, 10 * DEG, TORQUE_NM, 0.12)
        assert (detector.overriding, detector.unknown) == (False, False)
        detector.update(0.0, 5 * DEG, TORQUE_NM, 0.14)
        detector.update(None, 5 * DEG, TORQUE_NM, 0.16)  # dwell interrupted by the release
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.18)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 0.27)
        assert detector.update(0.0, 5 * DEG, TORQUE_NM, 0.28)

    @pytest.mark.parametrize("commanded", [0.0, None])
    def test_missing_measured_angle_is_unknown_not_an_override(
        self, commanded: float | None
    ) -> None:
        detector = overriding_detector()
        assert not detector.update(commanded, None, TORQUE_NM, 0.12)
        assert detector.unknown
        assert not detector.update(0.0, 10 * DEG, TORQUE_NM, 0.14)  # seen again: a new dwell
        assert not detector.unknown

    @pytest.mark.parametrize("bad", NON_FINITE)
    @pytest.mark.parametrize("field", ["commanded", "measured", "torque", "now"])
    def test_non_finite_input_is_unknown_not_an_override(self, bad: float, field: str) -> None:
        detector = overriding_detector()
        result = detector.update(
            bad if field == "commanded" else 0.0,
            bad if field == "measured" else 10 * DEG,
            bad if field == "torque" else TORQUE_NM,
            bad if field == "now" else 0.12,
        )
        assert (result, detector.unknown, detector.overriding) == (False, True, False)

    @pytest.mark.parametrize("bad", NON_FINITE)
    def test_non_finite_measured_while_released_is_unknown(self, bad: float) -> None:
        detector = SteeringOverrideDetector(PARAMS)
        assert not detector.update(None, bad, 0.0, 0.0)
        assert detector.unknown

    def test_time_going_backwards_restarts_the_dwell(self) -> None:
        detector = SteeringOverrideDetector(PARAMS)
        detector.update(0.0, 5 * DEG, TORQUE_NM, 10.0)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 5.0)
        assert not detector.update(0.0, 5 * DEG, TORQUE_NM, 5.05)
        assert detector.update(0.0, 5 * DEG, TORQUE_NM, 5.101)

    def test_reset_forgets_override_dwell_and_unknown(self) -> None:
        detector = overriding_detector()
        detector.reset()
        assert (detector.overriding, detector.unknown, detector.deviating_since_s) == (
            False,
            False,
            None,
        )
        assert not detector.update(0.0, 3 * DEG, TORQUE_NM, 0.12)  # hysteresis forgotten


PEDAL = parts.pedal_override_params(SafetyTimeouts())  # margin 8 %


class TestPedalOverride:
    def test_margin_comes_from_the_config(self) -> None:
        assert PEDAL.margin_pct == 8.0

    @pytest.mark.parametrize("margin", [0.0, -1.0, math.nan, math.inf])
    def test_invalid_margin_is_refused(self, margin: float) -> None:
        with pytest.raises(ValueError, match="margin_pct"):
            PedalOverrideParams(margin)

    def test_foot_beyond_the_margin_overrides_at_once(self) -> None:
        detector = PedalOverrideDetector(PEDAL)
        assert detector.update(18.01, 10.0)

    def test_exactly_at_the_margin_is_not_an_override(self) -> None:
        assert not PedalOverrideDetector(PEDAL).update(18.0, 10.0)

    def test_pedal_following_the_actuator_is_not_an_override(self) -> None:
        detector = PedalOverrideDetector(PEDAL)
        assert not detector.update(40.0, 40.0)
        assert not detector.update(0.0, 40.0)  # actuator ahead of the pedal reading

    def test_override_ends_with_the_foot(self) -> None:
        detector = PedalOverrideDetector(PEDAL)
        assert detector.update(50.0, 0.0)
        assert not detector.update(5.0, 0.0)

    def test_no_pedal_sensor_is_not_an_override(self) -> None:
        assert not PedalOverrideDetector(PEDAL).update(None, 10.0)

    @pytest.mark.parametrize("bad", NON_FINITE)
    def test_non_finite_pedal_assumes_the_operator(self, bad: float) -> None:
        assert PedalOverrideDetector(PEDAL).update(bad, 10.0)

    @pytest.mark.parametrize("bad", NON_FINITE)
    @pytest.mark.parametrize("pedal", [None, 10.0])
    def test_non_finite_actuator_assumes_the_operator(
        self, bad: float, pedal: float | None
    ) -> None:
        assert PedalOverrideDetector(PEDAL).update(pedal, bad)

    def test_reset(self) -> None:
        detector = PedalOverrideDetector(PEDAL)
        detector.update(math.nan, 0.0)
        detector.reset()
        assert not detector.overriding


def operator_cycle(
    operator: OperatorOverride,
    *,
    measured_steer_rad: float | None = 0.0,
    servo_torque_nm: float = 0.0,
    brake_pedal_pct: float | None = 0.0,
    throttle_pedal_pct: float | None = None,
    now_s: float = 0.0,
) -> OperatorInput:
    """Steering commanded straight ahead, both actuators at rest."""
    return operator.update(
        commanded_steer_rad=0.0,
        measured_steer_rad=measured_steer_rad,
        servo_torque_nm=servo_torque_nm,
        brake_pedal_pct=brake_pedal_pct,
        brake_actuator_pct=0.0,
        throttle_pedal_pct=throttle_pedal_pct,
        throttle_actuator_pct=0.0,
        now_s=now_s,
    )


class TestOperatorOverride:
    def test_quiet_cycle_is_no_override(self) -> None:
        operator = parts.operator_override(SafetyTimeouts(), Limits())
        assert operator_cycle(operator) == OperatorInput()
        assert not operator.steering_unknown

    def test_each_detector_reports_its_own_field(self) -> None:
        operator = OperatorOverride(replace(PARAMS, dwell_s=0.0), PEDAL)
        assert operator_cycle(operator, measured_steer_rad=10 * DEG, servo_torque_nm=TORQUE_NM) == (
            OperatorInput(steering_override=True)
        )
        assert operator_cycle(operator, brake_pedal_pct=30.0) == OperatorInput(brake_pedal=True)
        assert operator_cycle(operator, throttle_pedal_pct=30.0) == OperatorInput(
            throttle_pedal=True
        )

    def test_reset_resets_every_detector(self) -> None:
        operator = OperatorOverride(replace(PARAMS, dwell_s=0.0), PEDAL)
        operator_cycle(
            operator,
            measured_steer_rad=10 * DEG,
            servo_torque_nm=TORQUE_NM,
            brake_pedal_pct=30.0,
            throttle_pedal_pct=30.0,
        )
        operator.reset()
        detectors = (operator.steering, operator.brake, operator.throttle)
        assert not any(d.overriding for d in detectors)

    def test_unseen_wheel_is_forwarded(self) -> None:
        operator = OperatorOverride(PARAMS, PEDAL)
        assert not operator_cycle(operator, measured_steer_rad=None).overriding
        assert operator.steering_unknown
