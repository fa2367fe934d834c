"""ReceiveMonitor: counters, CRC failures, periods and staleness, with time as an argument."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.pc104.monitor import MonitorParams, ReceiveMonitor, RxVerdict

PERIOD_S = 0.02
MAX_AGE_S = 0.1
A, R, S, U = RxVerdict.ACCEPTED, RxVerdict.RESYNCING, RxVerdict.STUCK, RxVerdict.UNTRUSTED


def make(**overrides: float) -> ReceiveMonitor:
    params = {"period_s": PERIOD_S, "max_age_s": MAX_AGE_S, **overrides}
    return ReceiveMonitor(MonitorParams(**params))  # type: ignore[arg-type]


def feed(monitor: ReceiveMonitor, counters: list[int], start_s: float = 0.0) -> list[RxVerdict]:
    return [monitor.update(start_s + i * PERIOD_S, c) for i, c in enumerate(counters)]


def synced(first_counter: int = 0) -> ReceiveMonitor:
    monitor = make()
    assert feed(monitor, [(first_counter + i) % 16 for i in range(3)]) == [R, R, A]
    return monitor


def test_a_new_stream_is_used_from_its_third_frame_in_sequence() -> None:
    monitor = make()
    assert feed(monitor, [5, 6, 7, 8]) == [R, R, A, A]
    assert monitor.counts.accepted == 2
    assert monitor.counts.counter_errors == 0
    assert monitor.counts.resyncs == 0  # the first sync is not a resync


def test_counter_wraps_from_15_to_0() -> None:
    monitor = synced(13)
    assert feed(monitor, [0, 1], start_s=1.0) == [A, A]
    assert monitor.counts.counter_errors == 0


def test_a_stuck_counter_is_rejected_and_counted() -> None:
    monitor = synced(0)
    assert monitor.update(0.06, 2) == S
    assert monitor.update(0.08, 2) == S
    assert monitor.counts.stuck == 2
    assert monitor.stale(0.04 + MAX_AGE_S + 1e-6)  # stuck frames do not keep it fresh


def test_skipped_frames_are_counted_but_the_frame_is_used() -> None:
    monitor = synced(0)  # last counter 2
    assert monitor.update(0.1, 5) == A  # 3 and 4 lost
    assert (monitor.counts.skips, monitor.counts.lost_frames) == (1, 2)


def test_a_jump_forces_a_resync_and_a_restarted_peer_is_accepted_again() -> None:
    monitor = synced(6)  # last counter 8
    assert feed(monitor, [0, 1, 2, 3], start_s=1.0) == [R, R, A, A]  # peer rebooted
    assert monitor.counts.jumps == 1
    assert monitor.counts.resyncs == 1
    assert monitor.synced


def test_a_break_during_resync_starts_the_resync_again() -> None:
    monitor = synced(0)
    assert feed(monitor, [9, 10, 4, 5, 6], start_s=1.0) == [R, R, R, R, A]
    assert monitor.counts.jumps == 2


def test_a_backwards_step_is_a_jump() -> None:
    monitor = synced(4)  # last counter 6
    assert monitor.update(1.0, 5) == R
    assert monitor.counts.jumps == 1


def test_a_few_crc_failures_cost_nothing_but_a_count() -> None:
    monitor = synced(0)
    for _ in range(4):
        monitor.record_invalid(0.05)
    assert monitor.counts.invalid == 4
    assert monitor.update(0.06, 3) == A
    assert monitor.error_budget == 3


def test_an_exhausted_error_budget_is_earned_back_with_good_frames() -> None:
    monitor = synced(0)
    for _ in range(5):
        monitor.record_invalid(0.05)
    assert not monitor.trusted
    assert feed(monitor, [3, 4, 5, 6, 7, 8], start_s=0.06) == [U, U, U, U, A, A]
    assert monitor.counts.untrusted == 4


def test_errors_outnumbering_good_frames_make_the_stream_untrusted() -> None:
    monitor = synced(0)
    verdicts = []
    counter, t = 3, 0.1
    for _ in range(10):
        monitor.record_invalid(t)
        monitor.record_invalid(t)
        verdicts.append(monitor.update(t, counter))
        counter, t = (counter + 1) % 16, t + PERIOD_S
    assert verdicts[-1] is U
    assert monitor.counts.untrusted > 0


def test_frames_later_than_one_and_a_half_periods_are_counted_late() -> None:
    monitor = make()
    monitor.update(0.0, 0)
    monitor.update(0.03, 1)  # exactly 1.5 periods: on time
    monitor.update(0.0301 + 0.03, 2)  # a little more than 1.5 periods
    assert monitor.counts.late == 1


def test_staleness_at_exactly_the_limit() -> None:
    monitor = synced(0)  # last accepted at t = 0.04
    last_s = 0.04
    assert monitor.last_accepted_s == pytest.approx(last_s)
    assert monitor.stale_deadline_s() == last_s + MAX_AGE_S
    assert not monitor.stale(last_s + MAX_AGE_S)  # exactly at the limit: still fresh
    assert monitor.stale(last_s + MAX_AGE_S + 1e-9)
    assert monitor.age_s(last_s + 0.05) == pytest.approx(0.05)


def test_a_stream_never_accepted_is_stale() -> None:
    monitor = make()
    assert monitor.stale(0.0)
    monitor.update(0.0, 0)
    assert monitor.stale(0.0)  # resyncing frames do not count


def test_reset_forgets_everything() -> None:
    monitor = synced(0)
    monitor.record_invalid(0.1)
    monitor.reset()
    assert monitor.counts.frames == 0 and monitor.error_budget == 0
    assert monitor.stale(0.0)
    assert feed(monitor, [7, 8, 9]) == [R, R, A]


def test_counter_outside_four_bits_is_a_caller_bug() -> None:
    with pytest.raises(ValueError, match="counter"):
        make().update(0.0, 16)


@pytest.mark.parametrize(
    "bad",
    [
        {"period_s": 0.0},
        {"max_age_s": -1.0},
        {"late_factor": 0.5},
        {"max_lost_frames": 14},
        {"resync_frames": 0},
    ],
)
def test_invalid_params_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match=r"need|room"):
        make(**bad)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(0, 15), max_size=60))
def test_any_counter_sequence_keeps_the_counts_consistent(counters: list[int]) -> None:
    monitor = make()
    verdicts = feed(monitor, counters)
    c = monitor.counts
    assert c.frames == len(counters)
    assert c.accepted == verdicts.count(A)
    assert c.stuck == verdicts.count(S)
    assert c.untrusted == verdicts.count(U)
    assert 0 <= monitor.error_budget <= monitor.params.error_budget_limit
    # In-sequence tails always end up accepted: a peer can always be resynced.
    tail = [(counters[-1] + i) % 16 for i in range(1, 12)] if counters else list(range(11))
    assert feed(monitor, tail, start_s=10.0)[-1] is A
