"""The tablet's rules: pairing, authentication, replay, flooding, and the hold's timeout."""

from __future__ import annotations

import itertools
from collections.abc import Callable

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.tablet_page.gate import Paired, Refusal, Status, TabletGate, TabletParams


def _counter_bytes() -> Callable[[int], bytes]:
    """Distinct, deterministic 'random' bytes: each call a new counter value."""
    counter = itertools.count(1)
    return lambda n: next(counter).to_bytes(n, "big")


def _paired(params: TabletParams | None = None) -> tuple[TabletGate, str]:
    gate = TabletGate(_counter_bytes(), params)
    paired = gate.pair(gate.code, 0.0)
    assert isinstance(paired, Paired)
    return gate, paired.token


def test_the_right_code_pairs_once_and_changes() -> None:
    gate = TabletGate(_counter_bytes())
    code = gate.code
    assert len(code) == 6 and code.isdigit()
    assert isinstance(gate.pair(code, 0.0), Paired)
    assert gate.code != code
    again = gate.pair(code, 0.1)
    assert isinstance(again, Refusal) and again.status is Status.FORBIDDEN


def test_a_second_tablet_pairing_ends_the_first_ones_session() -> None:
    gate, first = _paired()
    assert gate.hold(first, 1, True, 1.0) is None and gate.held(1.0)
    second = gate.pair(gate.code, 1.05)
    assert isinstance(second, Paired)
    assert not gate.held(1.05)  # the new tablet starts with nothing held
    refused = gate.hold(first, 2, True, 1.1)
    assert isinstance(refused, Refusal) and refused.status is Status.UNAUTHORIZED


def test_guessing_the_code_locks_pairing_and_changes_the_code() -> None:
    params = TabletParams(max_pairing_failures=3, pairing_lockout_s=60.0)
    gate = TabletGate(_counter_bytes(), params)
    code = gate.code
    for attempt in range(3):
        assert isinstance(gate.pair("000000" if code != "000000" else "111111", attempt), Refusal)
    assert gate.code != code
    locked = gate.pair(gate.code, 10.0)
    assert isinstance(locked, Refusal) and locked.status is Status.TOO_MANY_REQUESTS
    assert isinstance(gate.pair(gate.code, 63.0), Paired)


@pytest.mark.parametrize("token", [None, "", "0" * 32, 12345, b"bytes"])
def test_no_token_or_a_wrong_one_is_refused(token: object) -> None:
    gate, _ = _paired()
    refused = gate.hold(token, 1, True, 1.0)
    assert isinstance(refused, Refusal) and refused.status is Status.UNAUTHORIZED
    assert not gate.held(1.0)


def test_a_replayed_request_is_refused_and_changes_nothing() -> None:
    gate, token = _paired()
    assert gate.hold(token, 5, True, 1.0) is None
    assert gate.hold(token, 6, False, 1.05) is None
    replayed = gate.hold(token, 5, True, 1.1)  # the captured press, sent again
    assert isinstance(replayed, Refusal) and replayed.status is Status.CONFLICT
    assert not gate.held(1.1)


@pytest.mark.parametrize("seq", [0, -1, 1.5, "7", True, None, 2**60])
def test_a_malformed_seq_is_refused(seq: object) -> None:
    gate, token = _paired()
    refused = gate.hold(token, seq, True, 1.0)
    assert isinstance(refused, Refusal) and refused.status is Status.BAD_REQUEST


def test_the_hold_lapses_after_the_timeout_and_ends_at_once_on_release() -> None:
    gate, token = _paired(TabletParams(hold_timeout_s=0.3))
    assert gate.hold(token, 1, True, 1.0) is None
    assert gate.held(1.3) and not gate.held(1.3001)
    assert not gate.held(1.2)  # lapsed: only a new beat presses it again
    assert gate.hold(token, 2, True, 2.0) is None and gate.held(2.0)
    assert gate.hold(token, 3, False, 2.01) is None and not gate.held(2.01)


def test_a_flood_is_refused_beyond_the_rate_and_beats_pass_again_after() -> None:
    gate, token = _paired(TabletParams(max_requests_per_s=40.0, burst_requests=20))
    answers = [gate.hold(token, seq, True, 1.0) for seq in range(1, 101)]
    assert sum(a is None for a in answers) == 20
    assert all(a.status is Status.TOO_MANY_REQUESTS for a in answers[20:] if a is not None)
    assert gate.hold(token, 101, True, 1.1) is None  # 0.1 s later: 4 more allowed


def test_a_silent_session_expires() -> None:
    gate, token = _paired(TabletParams(session_idle_s=10.0))
    assert gate.hold(token, 1, False, 5.0) is None
    refused = gate.hold(token, 2, True, 15.5)
    assert isinstance(refused, Refusal) and refused.status is Status.UNAUTHORIZED
    assert not gate.paired


_operation = st.one_of(
    st.tuples(st.just("pair"), st.sampled_from(["right", "wrong", "none"])),
    st.tuples(
        st.just("hold"),
        st.sampled_from(["token", "wrong", "none"]),
        st.one_of(st.integers(-3, 60), st.floats(allow_nan=True), st.none(), st.text(max_size=3)),
        st.one_of(st.booleans(), st.none(), st.integers(0, 2)),
    ),
    st.tuples(st.just("unpair")),
)


@settings(max_examples=300, deadline=None)
@given(
    operations=st.lists(st.tuples(_operation, st.floats(0.0, 0.5, allow_nan=False)), max_size=60)
)
def test_held_only_within_the_timeout_of_an_accepted_beat(
    operations: list[tuple[tuple[object, ...], float]],
) -> None:
    """Against an independent model: held means the last accepted hold request was a
    press, no release, unpair or new pairing since, and at most the timeout ago."""
    params = TabletParams(hold_timeout_s=0.3, burst_requests=5, max_requests_per_s=20.0)
    gate = TabletGate(_counter_bytes(), params)
    token: str | None = None
    now = 0.0
    last_press: float | None = None  # the model
    for operation, dt in operations:
        now += dt
        if last_press is not None and now - last_press > params.hold_timeout_s:
            last_press = None
        if operation[0] == "pair":
            code = {"right": gate.code, "wrong": "x", "none": None}[str(operation[1])]
            result = gate.pair(code, now)
            if isinstance(result, Paired):
                token, last_press = result.token, None
        elif operation[0] == "unpair":
            gate.unpair()
            token, last_press = None, None
        else:
            _, which, seq, held = operation
            sent = {"token": token, "wrong": "f" * 32, "none": None}[str(which)]
            answer = gate.hold(sent, seq, held, now)
            if answer is None:
                assert sent == token and isinstance(held, bool)
                last_press = now if held else None
            elif answer.status is Status.UNAUTHORIZED and not gate.paired:
                token, last_press = None, None  # expired by silence
        assert gate.held(now) == (last_press is not None)
