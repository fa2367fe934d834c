"""Fault monitor: levels to raise/clear records, each fault logged once, mode events."""

from __future__ import annotations

import math

import pytest

from appliance.modes import (
    EngageConditions,
    FaultCleared,
    FaultRaised,
    ManualOverridePressed,
    Mode,
    ModeState,
    step,
)
from safety.faults import HISTORY_LENGTH, FaultChanges, FaultMonitor, FaultRecord

STALE = "stale:board.steering"
TRACKING = "steering_tracking"


class TestFaultMonitor:
    def test_nothing_active_is_no_change(self) -> None:
        changes = FaultMonitor().update({}, 0.0)
        assert changes == FaultChanges()
        assert not changes

    def test_a_fault_is_raised_once_while_it_stays(self) -> None:
        monitor = FaultMonitor()
        changes = monitor.update({STALE: "age 0.2 s"}, 1.0)
        assert changes.raised == (FaultRecord(STALE, "age 0.2 s", 1.0),)
        assert changes.cleared == ()
        for t in range(2, 50):
            assert not monitor.update({STALE: "age 0.2 s"}, float(t))

    def test_a_changing_detail_is_not_a_new_fault(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "age 0.2 s"}, 1.0)
        assert not monitor.update({STALE: "age 0.9 s"}, 2.0)
        assert monitor.active_faults[STALE] == FaultRecord(STALE, "age 0.2 s", 1.0)

    def test_cleared_once_when_it_disappears(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "old"}, 1.0)
        changes = monitor.update({}, 2.5)
        assert changes.cleared == (FaultRecord(STALE, "old", 1.0, 2.5),)
        assert changes.raised == ()
        assert not monitor.update({}, 3.0)
        assert STALE not in monitor.active_faults

    def test_a_fault_that_comes_back_is_raised_again(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        monitor.update({}, 2.0)
        assert monitor.update({STALE: "b"}, 3.0).raised == (FaultRecord(STALE, "b", 3.0),)

    def test_keys_are_independent(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        changes = monitor.update({TRACKING: "5 deg off"}, 2.0)
        assert [r.key for r in changes.raised] == [TRACKING]
        assert [r.key for r in changes.cleared] == [STALE]
        assert list(monitor.active_faults) == [TRACKING]

    def test_active_faults_keep_the_first_timestamp_and_are_read_only(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        monitor.update({STALE: "a", TRACKING: "b"}, 2.0)
        assert {k: r.raised_s for k, r in monitor.active_faults.items()} == {
            STALE: 1.0,
            TRACKING: 2.0,
        }
        with pytest.raises(TypeError):
            monitor.active_faults[STALE] = FaultRecord(STALE, "x", 0.0)  # type: ignore[index]

    def test_history_records_occurrences_with_their_clearing(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        monitor.update({STALE: "a", TRACKING: "b"}, 2.0)
        monitor.update({TRACKING: "b"}, 3.0)
        monitor.update({TRACKING: "b", STALE: "c"}, 4.0)
        assert monitor.history == (
            FaultRecord(STALE, "a", 1.0, 3.0),
            FaultRecord(TRACKING, "b", 2.0, None),
            FaultRecord(STALE, "c", 4.0, None),
        )

    def test_history_is_bounded(self) -> None:
        monitor = FaultMonitor()
        for t in range(3 * HISTORY_LENGTH):
            monitor.update({f"fault{t % 2}": "x"} if t % 4 < 2 else {}, float(t))
        assert len(monitor.history) == HISTORY_LENGTH
        assert monitor.history[-1].raised_s > monitor.history[0].raised_s

    def test_clearing_a_fault_older_than_the_history_still_clears_it(self) -> None:
        monitor = FaultMonitor()
        monitor.update({"old": "x"}, 0.0)
        for t in range(1, 2 * HISTORY_LENGTH):
            monitor.update({"old": "x", f"flap{t}": "y"}, float(t))
        changes = monitor.update({}, 1000.0)
        assert FaultRecord("old", "x", 0.0, 1000.0) in changes.cleared
        assert all(r.cleared_s is not None for r in monitor.history)

    @pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
    def test_non_finite_time_raises_and_changes_nothing(self, bad: float) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        with pytest.raises(ValueError, match="finite"):
            monitor.update({TRACKING: "b"}, bad)
        assert list(monitor.active_faults) == [STALE]
        assert len(monitor.history) == 1

    def test_reset_forgets_everything_so_active_faults_are_raised_again(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        monitor.reset()
        assert (dict(monitor.active_faults), monitor.history) == ({}, ())
        assert monitor.update({STALE: "a"}, 2.0).raised == (FaultRecord(STALE, "a", 2.0),)

    def test_mode_events_map_one_to_one_raises_first(self) -> None:
        monitor = FaultMonitor()
        monitor.update({STALE: "a"}, 1.0)
        assert monitor.update({TRACKING: "b"}, 2.0).mode_events() == (
            FaultRaised(reason=TRACKING),
            FaultCleared(reason=STALE),
        )

    def test_the_mode_machine_latches_until_cleared_and_the_operator_presses(self) -> None:
        conditions = EngageConditions(
            fault_active=False,
            stale_inputs=(),
            calibration_valid=True,
            operator_overriding=False,
            speed_above_limit=False,
            source_ready=True,
        )
        monitor = FaultMonitor()
        state = ModeState(mode=Mode.ENGAGED, self_check_passed=True)

        def run(active: dict[str, str], now_s: float) -> None:
            nonlocal state
            for event in monitor.update(active, now_s).mode_events():
                state, _ = step(state, event, conditions, now_s)

        run({TRACKING: "5 deg off for 0.5 s"}, 1.0)
        run({TRACKING: "6 deg off"}, 1.02)
        assert state.mode is Mode.ERROR
        assert [f.reason for f in state.faults] == [TRACKING]
        state, _ = step(state, ManualOverridePressed(), conditions, 1.1)
        assert state.mode is Mode.ERROR  # not cleared yet: the press is refused
        run({}, 2.0)
        assert state.mode is Mode.ERROR  # cleared, but latched until the operator presses
        state, _ = step(state, ManualOverridePressed(), conditions, 2.1)
        assert state.mode is Mode.READY
