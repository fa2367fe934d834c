"""Consistency rules: steering tracking, the link error budget and counter deltas."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from appliance.config import parts
from appliance.config.models import SafetyTimeouts
from safety.consistency import (
    CounterDeltas,
    ErrorBudget,
    SteeringTrackingMonitor,
)

DEG = math.pi / 180.0
TRACKING = parts.steering_tracking_params(SafetyTimeouts())  # 3 deg for 0.5 s
NON_FINITE = [math.nan, math.inf, -math.inf]


def off_track_since_zero() -> SteeringTrackingMonitor:
    """A monitor that has seen the steering 5 deg off its command since t = 0."""
    monitor = SteeringTrackingMonitor(TRACKING)
    assert not monitor.update(0.0, 5 * DEG, False, 0.0)
    return monitor


class TestSteeringTracking:
    def test_conversion_to_radians_happens_at_the_edge(self) -> None:
        assert TRACKING.tolerance_rad == pytest.approx(3 * DEG)
        assert TRACKING.fault_after_s == 0.5

    @pytest.mark.parametrize(
        "changes",
        [{"tolerance_rad": 0.0}, {"fault_after_s": 0.0}, {"tolerance_rad": math.nan}],
    )
    def test_invalid_params_are_refused(self, changes: dict[str, float]) -> None:
        with pytest.raises(ValueError, match="must be positive"):
            replace(TRACKING, **changes)

    def test_tracking_steering_is_no_fault(self) -> None:
        monitor = SteeringTrackingMonitor(TRACKING)
        for t in range(100):
            assert not monitor.update(0.2, 0.2 + 2.9 * DEG, False, t * 0.02)

    def test_exactly_at_the_tolerance_is_on_track(self) -> None:
        monitor = SteeringTrackingMonitor(TRACKING)
        assert not monitor.update(0.0, TRACKING.tolerance_rad, False, 0.0)
        assert not monitor.update(0.0, TRACKING.tolerance_rad, False, 1.0)
        assert monitor.off_track_since_s is None

    def test_fault_after_the_delay_and_not_before(self) -> None:
        monitor = off_track_since_zero()
        assert not monitor.update(0.0, 5 * DEG, False, 0.4999)
        assert monitor.update(0.0, -5 * DEG, False, 0.5)
        assert monitor.update(0.0, 5 * DEG, False, 3.0)

    def test_the_condition_is_a_level_not_a_latch(self) -> None:
        monitor = off_track_since_zero()
        assert monitor.update(0.0, 5 * DEG, False, 0.5)
        assert not monitor.update(0.0, 0.0, False, 0.52)
        assert not monitor.update(0.0, 5 * DEG, False, 0.54)  # a new delay starts

    def test_back_on_track_restarts_the_delay(self) -> None:
        monitor = off_track_since_zero()
        monitor.update(0.0, 1 * DEG, False, 0.3)
        assert not monitor.update(0.0, 5 * DEG, False, 0.4)
        assert not monitor.update(0.0, 5 * DEG, False, 0.89)
        assert monitor.update(0.0, 5 * DEG, False, 0.9)

    @pytest.mark.parametrize("measured", [0.0, 5 * DEG, None, math.nan])
    def test_released_steering_is_never_a_fault_and_resets(self, measured: float | None) -> None:
        monitor = off_track_since_zero()
        assert not monitor.update(None, measured, False, 10.0)
        assert monitor.off_track_since_s is None

    @pytest.mark.parametrize("measured", [5 * DEG, None, math.nan])
    def test_override_is_never_a_fault_and_resets(self, measured: float | None) -> None:
        monitor = off_track_since_zero()
        assert not monitor.update(0.0, measured, True, 10.0)
        assert not monitor.update(0.0, 5 * DEG, False, 10.4)  # the delay starts again

    @pytest.mark.parametrize("measured", [None, *NON_FINITE])
    def test_unseen_steering_is_a_fault_after_the_delay(self, measured: float | None) -> None:
        monitor = SteeringTrackingMonitor(TRACKING)
        assert not monitor.update(0.0, measured, False, 0.0)
        assert not monitor.update(0.0, measured, False, 0.4999)
        assert monitor.update(0.0, measured, False, 0.5)

    def test_unseen_and_off_track_add_up(self) -> None:
        monitor = off_track_since_zero()
        monitor.update(0.0, None, False, 0.3)
        assert monitor.update(0.0, 5 * DEG, False, 0.5)

    @pytest.mark.parametrize("bad", NON_FINITE)
    @pytest.mark.parametrize("overriding", [False, True])
    def test_non_finite_command_is_a_fault_at_once(self, bad: float, overriding: bool) -> None:
        assert SteeringTrackingMonitor(TRACKING).update(bad, 0.0, overriding, 0.0)

    @pytest.mark.parametrize("bad", NON_FINITE)
    def test_non_finite_time_is_a_fault_at_once_and_keeps_the_timer(self, bad: float) -> None:
        monitor = off_track_since_zero()
        assert monitor.update(0.0, 0.0, False, bad)
        assert monitor.update(0.0, 5 * DEG, False, 0.5)

    def test_time_going_backwards_restarts_the_delay(self) -> None:
        monitor = SteeringTrackingMonitor(TRACKING)
        monitor.update(0.0, 5 * DEG, False, 10.0)
        assert not monitor.update(0.0, 5 * DEG, False, 5.0)
        assert monitor.update(0.0, 5 * DEG, False, 5.5)

    def test_reset(self) -> None:
        monitor = off_track_since_zero()
        monitor.reset()
        assert not monitor.update(0.0, 5 * DEG, False, 0.5)


class TestErrorBudget:
    def test_limit_comes_from_the_config(self) -> None:
        assert parts.error_budget(SafetyTimeouts()).limit == 10

    @pytest.mark.parametrize("limit", [0, -1, True, 2.5])
    def test_invalid_limit_is_refused(self, limit: int) -> None:
        with pytest.raises(ValueError, match="limit"):
            ErrorBudget(limit)

    def test_the_odd_error_is_tolerated(self) -> None:
        budget = ErrorBudget(3)
        for _ in range(100):
            assert not budget.update(1, 1)
        assert budget.level == 0

    def test_exhausted_at_the_limit_not_below(self) -> None:
        budget = ErrorBudget(3)
        assert not budget.update(2, 0)
        assert budget.update(1, 0)

    def test_level_is_capped_at_the_limit(self) -> None:
        budget = ErrorBudget(3)
        budget.update(50, 0)
        assert budget.level == 3
        assert budget.update(0, 2)
        assert not budget.update(0, 1)  # three good frames were enough, not fifty

    def test_stays_exhausted_until_back_at_zero(self) -> None:
        budget = ErrorBudget(4)
        budget.update(4, 0)
        assert budget.update(0, 3)
        assert budget.update(2, 0)  # rising again inside the band: still exhausted
        assert budget.update(0, 2)
        assert not budget.update(0, 1)
        assert not budget.update(3, 0)  # hysteresis over: below the limit is fine again

    def test_level_floors_at_zero(self) -> None:
        budget = ErrorBudget(3)
        budget.update(0, 100)
        assert budget.level == 0
        assert budget.update(3, 0)  # good frames banked earlier buy nothing

    def test_errors_count_before_the_good_frames_of_the_same_update(self) -> None:
        budget = ErrorBudget(3)
        budget.update(2, 0)
        assert budget.update(1, 5)  # could have reached the limit inside the batch
        assert budget.level == 0
        assert not budget.update(0, 0)  # the next update reports the recovery
        assert not budget.update(1, 0)

    @pytest.mark.parametrize(("errors", "good"), [(-1, 0), (0, -1), (math.nan, 0), (0, 1.5)])
    def test_invalid_counts_raise_and_change_nothing(self, errors: int, good: int) -> None:
        budget = ErrorBudget(3)
        budget.update(2, 0)
        with pytest.raises(ValueError, match="non-negative int"):
            budget.update(errors, good)
        assert (budget.level, budget.exhausted) == (2, False)

    def test_reset(self) -> None:
        budget = ErrorBudget(2)
        budget.update(2, 0)
        budget.reset()
        assert (budget.level, budget.exhausted) == (0, False)


class TestCounterDeltas:
    def test_first_update_is_the_baseline(self) -> None:
        deltas = CounterDeltas()
        assert deltas.update({"errors": 7, "frames": 1000}) == {"errors": 0, "frames": 0}
        assert not deltas.restarted

    def test_increases_since_the_last_update(self) -> None:
        deltas = CounterDeltas()
        deltas.update({"errors": 7, "frames": 1000})
        assert deltas.update({"errors": 9, "frames": 1050}) == {"errors": 2, "frames": 50}
        assert deltas.update({"errors": 9, "frames": 1050}) == {"errors": 0, "frames": 0}

    def test_a_total_going_down_is_a_restart_and_rebaselines_everything(self) -> None:
        deltas = CounterDeltas()
        deltas.update({"errors": 7, "frames": 1000})
        assert deltas.update({"errors": 8, "frames": 20}) == {"errors": 0, "frames": 0}
        assert deltas.restarted
        assert deltas.update({"errors": 9, "frames": 30}) == {"errors": 1, "frames": 10}
        assert not deltas.restarted  # the flag is for the restarting update only

    def test_a_new_name_starts_with_its_baseline(self) -> None:
        deltas = CounterDeltas()
        deltas.update({"errors": 7})
        assert deltas.update({"errors": 8, "frames": 500}) == {"errors": 1, "frames": 0}

    def test_a_missing_name_keeps_its_baseline(self) -> None:
        deltas = CounterDeltas()
        deltas.update({"errors": 7, "frames": 100})
        assert deltas.update({"frames": 110}) == {"frames": 10}
        assert deltas.update({"errors": 9, "frames": 120}) == {"errors": 2, "frames": 10}

    @pytest.mark.parametrize("bad", [-1, math.nan, 1.5, None])
    def test_invalid_totals_raise_and_change_nothing(self, bad: int) -> None:
        deltas = CounterDeltas()
        deltas.update({"errors": 7, "frames": 100})
        with pytest.raises(ValueError, match="non-negative int"):
            deltas.update({"errors": 8, "frames": bad})
        assert deltas.totals == {"errors": 7, "frames": 100}

    def test_reset_forgets_the_baselines(self) -> None:
        deltas = CounterDeltas()
        deltas.update({"errors": 7})
        deltas.reset()
        assert deltas.update({"errors": 3}) == {"errors": 0}
        assert not deltas.restarted
