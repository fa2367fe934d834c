"""Generic property suite over the operator and consistency rules, for every valid config.

In the spirit of opendbc's ``safety/tests/common.py``: the per-rule files test chosen
cases; here every rule runs over random input sequences with thresholds drawn from
everything ``SafetyTimeouts`` and ``Limits`` accept, and the invariants no rule may break
are checked each cycle. The bookkeeping in each test is written from the rule's
definition, not from its implementation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import parts
from appliance.config.models import Limits, SafetyTimeouts
from safety.consistency import (
    CounterDeltas,
    ErrorBudget,
    SteeringTrackingMonitor,
    SteeringTrackingParams,
)
from safety.faults import HISTORY_LENGTH, FaultMonitor
from safety.override import (
    OperatorOverride,
    PedalOverrideDetector,
    SteeringOverrideDetector,
    SteeringOverrideParams,
)

NON_FINITE_VALUES = (math.nan, math.inf, -math.inf)
non_finite = st.sampled_from(NON_FINITE_VALUES)


def positive(high: float) -> st.SearchStrategy[float]:
    return st.floats(0.0, high, exclude_min=True)


@st.composite
def release_and_threshold_deg(draw: st.DrawFn) -> tuple[float, float]:
    """``0 < release < threshold <= 30`` by construction: the threshold is drawn above."""
    release = draw(st.floats(0.0, 30.0, exclude_min=True, exclude_max=True))
    return release, draw(st.floats(release, 30.0, exclude_min=True))


# Degrees at or above this stay normal floats in radians, never 0.
SMALLEST_CONVERTIBLE_DEG = 1e-300
# Two angles this far apart (relative) stay in order through math.radians' rounding.
RADIANS_ORDER_GAP = 1.0 + 1e-14


@st.composite
def convertible_release_and_threshold_deg(draw: st.DrawFn) -> tuple[float, float]:
    """A release and threshold that stay positive and ordered in radians, by construction."""
    release = draw(st.floats(SMALLEST_CONVERTIBLE_DEG, 30.0 / RADIANS_ORDER_GAP))
    return release, draw(st.floats(min(release * RADIANS_ORDER_GAP, 30.0), 30.0))


@st.composite
def valid_safety(draw: st.DrawFn, *, convertible: bool = False) -> SafetyTimeouts:
    """Any SafetyTimeouts the config would accept: the rules must hold for all of them.

    Drawn so that the config's validators hold by design (release below threshold).
    ``convertible`` also keeps every angle the rules convert positive and ordered in
    radians, so the rules accept the config at start-up; without it the draw covers the
    config's whole range, down to angles whose radians collapse (see
    :func:`radians_collapse`).
    """
    pair = convertible_release_and_threshold_deg() if convertible else release_and_threshold_deg()
    release, threshold = draw(pair)
    tolerance = st.floats(SMALLEST_CONVERTIBLE_DEG, 30.0) if convertible else positive(30.0)
    return SafetyTimeouts(
        steer_override_threshold_deg=threshold,
        steer_override_release_deg=release,
        steer_override_dwell_s=draw(st.floats(0.0, 2.0)),
        steer_override_min_torque_nm=draw(st.floats(0.0, 30.0)),
        steer_stop_margin_deg=draw(st.floats(0.0, 10.0)),
        steer_tracking_tolerance_deg=draw(tolerance),
        steer_tracking_fault_after_s=draw(positive(5.0)),
        pedal_override_margin_pct=draw(positive(50.0)),
        pc104_error_budget_limit=draw(st.integers(1, 1000)),
    )


valid_limits = st.builds(Limits, max_steer_angle_deg=positive(60.0))
convertible_limits = st.builds(
    Limits, max_steer_angle_deg=st.floats(SMALLEST_CONVERTIBLE_DEG, 60.0)
)


def radians_collapse(safety: SafetyTimeouts, limits: Limits) -> bool:
    """A positive angle that is 0 in radians, or a release no longer below the threshold.

    The config accepts angles down to the smallest float (5e-324 deg); converted to
    radians such an angle underflows to 0, or two neighbouring values become one.
    """
    release_rad = math.radians(safety.steer_override_release_deg)
    positive_rad = (
        release_rad,
        math.radians(safety.steer_tracking_tolerance_deg),
        math.radians(limits.max_steer_angle_deg),
    )
    threshold_rad = math.radians(safety.steer_override_threshold_deg)
    return min(positive_rad) == 0.0 or release_rad >= threshold_rad


def steering_params(
    safety: SafetyTimeouts, limits: Limits
) -> tuple[SteeringOverrideParams, SteeringTrackingParams]:
    """The rules' parameters (a config whose radians collapse raises ValueError)."""
    return (
        parts.steering_override_params(safety, limits),
        parts.steering_tracking_params(safety),
    )


@dataclass(frozen=True)
class Cycle:
    commanded_rad: float | None
    measured_rad: float | None
    torque_nm: float
    now_s: float

    @property
    def seen(self) -> bool:
        """Steering commanded and measured, and every number finite."""
        numbers = (self.commanded_rad, self.measured_rad, self.torque_nm, self.now_s)
        return all(x is not None and math.isfinite(x) for x in numbers)

    @property
    def deviation_rad(self) -> float:
        assert self.commanded_rad is not None
        assert self.measured_rad is not None
        return abs(self.measured_rad - self.commanded_rad)


@st.composite
def steering_runs(draw: st.DrawFn, max_steer_angle_rad: float) -> list[Cycle]:
    """Segments of repeated inputs (so dwell and delay times can elapse), time rising.

    Angles cover the whole range, the stops and their margin bands; now and then an
    input is missing or not finite (rarely enough that long valid runs remain common).
    """

    def now_and_then(
        usual: st.SearchStrategy[float], rare: st.SearchStrategy[float | None], one_in: int = 8
    ) -> float | None:
        return draw(rare) if draw(st.integers(1, one_in)) == 1 else draw(usual)

    near_stop = st.builds(
        lambda side, offset: side * (max_steer_angle_rad + offset),
        st.sampled_from([1.0, -1.0]),
        st.floats(-0.25, 0.25),
    )
    finite_angle = st.one_of(st.floats(-1.2, 1.2), near_stop)
    unusable = st.none() | non_finite
    cycles: list[Cycle] = []
    now_s = draw(st.floats(-1e3, 1e3))
    for _ in range(draw(st.integers(1, 12))):
        commanded = now_and_then(finite_angle, unusable, one_in=4)
        measured = now_and_then(finite_angle, unusable)
        torque_nm = now_and_then(st.floats(-40.0, 40.0), non_finite)
        assert torque_nm is not None
        for _ in range(draw(st.integers(1, 8))):
            now_s += draw(st.one_of(st.just(0.0), st.floats(0.0, 0.4)))
            clock = draw(non_finite) if draw(st.integers(1, 16)) == 1 else now_s
            cycles.append(Cycle(commanded, measured, torque_nm, clock))
    return cycles


@st.composite
def steering_cases(
    draw: st.DrawFn,
) -> tuple[SteeringOverrideParams, SteeringTrackingParams, list[Cycle]]:
    safety, limits = draw(valid_safety(convertible=True)), draw(convertible_limits)
    override, tracking = steering_params(safety, limits)
    return override, tracking, draw(steering_runs(override.max_steer_angle_rad))


SteeringCase = tuple[SteeringOverrideParams, SteeringTrackingParams, list[Cycle]]


def towards_a_stop(p: SteeringOverrideParams, c: Cycle) -> bool:
    """Measured within the margin of a stop, the command further out towards it."""
    if not c.seen:
        return False
    assert c.commanded_rad is not None
    assert c.measured_rad is not None
    for side in (1.0, -1.0):
        measured_out, commanded_out = side * c.measured_rad, side * c.commanded_rad
        near = measured_out > 0.0 and measured_out >= p.max_steer_angle_rad - p.stop_margin_rad
        if near and commanded_out > measured_out:
            return True
    return False


class TestSteeringProperties:
    @settings(max_examples=200, deadline=None)
    @given(valid_safety(), valid_limits)
    def test_every_valid_config_converts_unless_its_radians_collapse(
        self, safety: SafetyTimeouts, limits: Limits
    ) -> None:
        if radians_collapse(safety, limits):
            with pytest.raises(ValueError, match="must be positive"):
                steering_params(safety, limits)
        else:
            steering_params(safety, limits)

    def test_a_vanishing_angle_is_refused_at_start_up(self) -> None:
        safety = SafetyTimeouts(steer_override_release_deg=5e-324)
        assert radians_collapse(safety, Limits())
        with pytest.raises(ValueError, match="release_rad must be positive"):
            parts.steering_override_params(safety, Limits())

    @settings(max_examples=150, deadline=None)
    @given(steering_cases())
    def test_released_steering_is_never_an_override_nor_a_tracking_fault(
        self, case: SteeringCase
    ) -> None:
        override_params, tracking_params, cycles = case
        detector = SteeringOverrideDetector(override_params)
        monitor = SteeringTrackingMonitor(tracking_params)
        for c in cycles:
            overriding = detector.update(c.commanded_rad, c.measured_rad, c.torque_nm, c.now_s)
            fault = monitor.update(c.commanded_rad, c.measured_rad, overriding, c.now_s)
            if c.commanded_rad is None:
                assert not overriding
                assert not fault

    @settings(max_examples=150, deadline=None)
    @given(steering_cases())
    def test_override_only_after_the_dwell_and_kept_above_release(self, case: SteeringCase) -> None:
        p, _, cycles = case
        detector = SteeringOverrideDetector(p)
        pushing_since_s: float | None = None  # hands-on deviation, stops not excepted
        previous = False
        for c in cycles:
            overriding = detector.update(c.commanded_rad, c.measured_rad, c.torque_nm, c.now_s)
            pushing = (
                c.seen and c.deviation_rad > p.threshold_rad and abs(c.torque_nm) >= p.min_torque_nm
            )
            if not pushing:
                pushing_since_s = None
            elif pushing_since_s is None:
                pushing_since_s = c.now_s
            if overriding:
                assert c.seen  # never an override it cannot see
                assert not detector.unknown
            if overriding and not previous:
                assert not towards_a_stop(p, c)
                assert pushing_since_s is not None
                assert c.now_s - pushing_since_s >= p.dwell_s
            if previous and c.seen:
                assert overriding is (c.deviation_rad >= p.release_rad)
            previous = overriding

    @settings(max_examples=150, deadline=None)
    @given(steering_cases(), st.data())
    def test_tracking_fault_exactly_after_the_delay(
        self, case: SteeringCase, data: st.DataObject
    ) -> None:
        _, p, cycles = case
        monitor = SteeringTrackingMonitor(p)
        off_track_since_s: float | None = None
        for c in cycles:
            overriding = data.draw(st.booleans())
            fault = monitor.update(c.commanded_rad, c.measured_rad, overriding, c.now_s)
            if c.commanded_rad is None:
                off_track_since_s = None
                assert not fault
                continue
            if not (math.isfinite(c.commanded_rad) and math.isfinite(c.now_s)):
                assert fault  # broken producer or clock: at once, timer untouched
                continue
            unseen = c.measured_rad is None or not math.isfinite(c.measured_rad)
            if overriding or not (unseen or c.deviation_rad > p.tolerance_rad):
                off_track_since_s = None
                assert not fault
                continue
            if off_track_since_s is None:
                off_track_since_s = c.now_s
            assert fault is (c.now_s - off_track_since_s >= p.fault_after_s)

    @settings(max_examples=150, deadline=None)
    @given(steering_cases())
    def test_a_non_finite_steering_input_is_never_all_fine(self, case: SteeringCase) -> None:
        override_params, tracking_params, cycles = case
        detector = SteeringOverrideDetector(override_params)
        monitor = SteeringTrackingMonitor(tracking_params)
        for c in cycles:
            overriding = detector.update(c.commanded_rad, c.measured_rad, c.torque_nm, c.now_s)
            fault = monitor.update(c.commanded_rad, c.measured_rad, overriding, c.now_s)
            numbers = (c.commanded_rad, c.measured_rad, c.torque_nm, c.now_s)
            if any(x is not None and not math.isfinite(x) for x in numbers):
                assert detector.unknown
                assert not overriding
            if c.commanded_rad is not None and not (
                math.isfinite(c.commanded_rad) and math.isfinite(c.now_s)
            ):
                assert fault
            if c.measured_rad is None:
                assert detector.unknown


pedal_value = st.one_of(st.floats(-10.0, 110.0), st.floats(-10.0, 110.0), non_finite)


def not_all_fine_with_one_bad_input(
    operator: OperatorOverride, monitor: SteeringTrackingMonitor, data: st.DataObject
) -> bool:
    """One cycle of operator detection and tracking with one input not finite."""
    names = ("commanded", "measured", "torque", "brake", "brake_act", "throttle", "now")
    broken, bad = data.draw(st.sampled_from(names)), data.draw(non_finite)

    def given_or_bad(name: str, usual: st.SearchStrategy[float]) -> float:
        return bad if name == broken else data.draw(usual)

    commanded = (
        given_or_bad("commanded", st.floats(-1.0, 1.0))
        if (broken == "commanded" or data.draw(st.booleans()))
        else None
    )
    measured = given_or_bad("measured", st.floats(-1.0, 1.0))
    now_s = given_or_bad("now", st.floats(0.0, 100.0))
    operator_input = operator.update(
        commanded_steer_rad=commanded,
        measured_steer_rad=measured,
        servo_torque_nm=given_or_bad("torque", st.floats(-40.0, 40.0)),
        brake_pedal_pct=given_or_bad("brake", st.floats(0.0, 100.0)),
        brake_actuator_pct=given_or_bad("brake_act", st.floats(0.0, 100.0)),
        throttle_pedal_pct=given_or_bad("throttle", st.floats(0.0, 100.0)),
        throttle_actuator_pct=data.draw(st.floats(0.0, 100.0)),
        now_s=now_s,
    )
    fault = monitor.update(commanded, measured, operator_input.overriding, now_s)
    return operator_input.overriding or operator.steering_unknown or fault


class TestPedalProperties:
    @settings(max_examples=150, deadline=None)
    @given(
        valid_safety(),
        st.lists(st.tuples(st.none() | pedal_value, pedal_value), min_size=1, max_size=20),
    )
    def test_pedal_override_is_the_foot_beyond_the_margin_or_a_non_finite_input(
        self, safety: SafetyTimeouts, cycles: list[tuple[float | None, float]]
    ) -> None:
        params = parts.pedal_override_params(safety)
        detector = PedalOverrideDetector(params)
        for pedal_pct, actuator_pct in cycles:
            overriding = detector.update(pedal_pct, actuator_pct)
            broken = not math.isfinite(actuator_pct) or (
                pedal_pct is not None and not math.isfinite(pedal_pct)
            )
            if broken:
                assert overriding  # deny by default: assume the operator
            elif pedal_pct is None:
                assert not overriding
            else:
                assert overriding is (pedal_pct > actuator_pct + params.margin_pct)

    @settings(max_examples=100, deadline=None)
    @given(valid_safety(convertible=True), convertible_limits, st.data())
    def test_a_non_finite_operator_input_is_never_all_fine(
        self, safety: SafetyTimeouts, limits: Limits, data: st.DataObject
    ) -> None:
        steering, tracking = steering_params(safety, limits)
        operator = OperatorOverride(steering, parts.pedal_override_params(safety))
        monitor = SteeringTrackingMonitor(tracking)
        for _ in range(data.draw(st.integers(1, 10))):
            assert not_all_fine_with_one_bad_input(operator, monitor, data)


@st.composite
def budget_runs(draw: st.DrawFn) -> tuple[ErrorBudget, list[tuple[int, int]]]:
    limit = draw(valid_safety()).pc104_error_budget_limit
    scale = st.integers(0, max(1, limit // 3))
    bursts = st.tuples(st.one_of(st.just(0), scale, st.integers(0, 2 * limit)), scale)
    return ErrorBudget(limit), draw(st.lists(bursts, min_size=1, max_size=40))


class TestErrorBudgetProperties:
    @settings(max_examples=200, deadline=None)
    @given(budget_runs())
    def test_exhausted_implies_limit_errors_since_the_budget_was_last_at_zero(
        self, run: tuple[ErrorBudget, list[tuple[int, int]]]
    ) -> None:
        budget, updates = run
        errors_since_zero = 0
        previous = False
        for errors, good in updates:
            errors_since_zero += errors
            exhausted = budget.update(errors, good)
            assert 0 <= budget.level <= budget.limit
            if exhausted:
                assert errors_since_zero >= budget.limit
            if previous and not exhausted:
                assert budget.level == 0  # hysteresis: exhausted until back at zero
            if budget.level == 0:
                errors_since_zero = 0
            previous = exhausted

    @settings(max_examples=100, deadline=None)
    @given(
        st.integers(1, 1000),
        st.one_of(st.integers(max_value=-1), non_finite, st.floats(0.5, 1e6)),
        st.booleans(),
    )
    def test_counts_that_are_not_counts_raise(self, limit: int, bad: float, first: bool) -> None:
        budget, deltas = ErrorBudget(limit), CounterDeltas()
        errors, good = (bad, 0) if first else (0, bad)
        with pytest.raises(ValueError, match="non-negative int"):
            budget.update(errors, good)  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="non-negative int"):
            deltas.update({"errors": bad})  # type: ignore[dict-item]


class TestCounterDeltasProperties:
    @settings(max_examples=150, deadline=None)
    @given(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 10**6)), max_size=30))
    def test_deltas_are_never_negative_and_sum_to_the_growth(
        self, totals: list[tuple[int, int]]
    ) -> None:
        deltas = CounterDeltas()
        baseline: tuple[int, int] | None = None  # where the current run of the driver began
        last: tuple[int, int] | None = None
        summed = [0, 0]
        for errors, frames in totals:
            step = deltas.update({"errors": errors, "frames": frames})
            assert all(d >= 0 for d in step.values())
            went_down = last is not None and (errors < last[0] or frames < last[1])
            assert deltas.restarted is went_down
            if baseline is None or went_down:
                assert step == {"errors": 0, "frames": 0}
                summed = [0, 0]
                baseline = (errors, frames)
            else:
                summed = [summed[0] + step["errors"], summed[1] + step["frames"]]
                assert summed == [errors - baseline[0], frames - baseline[1]]
            last = (errors, frames)


KEYS = ("stale:board.steering", "stale:scan.left", "steering_tracking", "pc104_link_errors")


class TestFaultMonitorProperties:
    @settings(max_examples=150, deadline=None)
    @given(
        st.lists(
            st.dictionaries(st.sampled_from(KEYS), st.sampled_from(["a", "b", "c"])),
            max_size=60,
        )
    )
    def test_raised_and_cleared_alternate_per_key_once_each(
        self, cycles: list[dict[str, str]]
    ) -> None:
        monitor = FaultMonitor()
        events: dict[str, list[str]] = {key: [] for key in KEYS}
        previous: set[str] = set()
        for t, active in enumerate(cycles):
            changes = monitor.update(active, float(t))
            raised = [r.key for r in changes.raised]
            cleared = [r.key for r in changes.cleared]
            assert sorted(raised) == sorted(set(active) - previous)
            assert sorted(cleared) == sorted(previous - set(active))
            for key in raised:
                events[key].append("raised")
            for key in cleared:
                events[key].append("cleared")
            assert all(r.raised_s == t and r.cleared_s is None for r in changes.raised)
            assert all(r.cleared_s == t and r.raised_s < t for r in changes.cleared)
            assert set(monitor.active_faults) == set(active)
            assert len(monitor.history) <= HISTORY_LENGTH
            assert len(changes.mode_events()) == len(raised) + len(cleared)
            previous = set(active)
        for sequence in events.values():
            assert sequence == ["raised", "cleared"] * (len(sequence) // 2) + (
                ["raised"] if len(sequence) % 2 else []
            )

    @settings(max_examples=50, deadline=None)
    @given(st.dictionaries(st.sampled_from(KEYS), st.just("x")), non_finite)
    def test_a_non_finite_clock_is_refused(self, active: dict[str, str], bad: float) -> None:
        with pytest.raises(ValueError, match="finite"):
            FaultMonitor().update(active, bad)
