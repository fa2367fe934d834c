"""PanelDecoder: press counters to button events, baseline first, deny by default.

A press is a counter step (mod 256), never a button seen down; the first frame after a
(re)start or a gap only sets the baseline, so nothing engages on a press nobody made now.
"""

from __future__ import annotations

from hypothesis import example, given, settings
from hypothesis import strategies as st

from appliance.core.panel import MAX_PRESSES_PER_FRAME, PanelDecoder
from drivers.actuators.messages import BUTTON_ORDER, BoardStatus, Buttons, FaultCode, PanelTelemetry

ZERO = (0, 0, 0, 0, 0)


def frame(counts: tuple[int, ...] = ZERO, down: Buttons = Buttons.NONE) -> PanelTelemetry:
    c0, c1, c2, c3, c4 = (c % 256 for c in counts)
    return PanelTelemetry(BoardStatus.NONE, FaultCode.NONE, 0, down, (c0, c1, c2, c3, c4))


def counts_with(button: Buttons, count: int) -> tuple[int, ...]:
    counts = [0] * len(BUTTON_ORDER)
    counts[BUTTON_ORDER.index(button)] = count
    return tuple(counts)


def test_first_frame_is_a_baseline_even_with_nonzero_counters() -> None:
    decoder = PanelDecoder()
    events = decoder.update(frame((7, 3, 1, 200, 9), down=Buttons.ENGAGE), seq=1)
    assert events.presses == ()
    assert events.implausible == ()
    assert events.down is Buttons.ENGAGE  # held buttons are read at once


def test_one_press_is_one_event_and_not_repeated() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 1)), seq=2).presses == (Buttons.ENGAGE,)
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 1)), seq=3).presses == ()


def test_presses_come_in_button_order() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    events = decoder.update(frame((0, 0, 0, 1, 1)), seq=2)
    assert events.presses == (Buttons.MANUAL_OVERRIDE, Buttons.ESTOP)
    events = decoder.update(frame((1, 1, 0, 1, 1)), seq=3)
    assert events.presses == (Buttons.ENGAGE, Buttons.SPEED_PLUS)


def test_counter_wraps_at_256() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(counts_with(Buttons.SPEED_PLUS, 255)), seq=1)
    events = decoder.update(frame(counts_with(Buttons.SPEED_PLUS, 0)), seq=2)
    assert events.presses == (Buttons.SPEED_PLUS,)
    assert events.implausible == ()


def test_same_sample_twice_is_not_a_second_press() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    pressed = frame(counts_with(Buttons.SPEED_MINUS, 1), down=Buttons.ESTOP)
    assert decoder.update(pressed, seq=2).presses == (Buttons.SPEED_MINUS,)
    again = decoder.update(pressed, seq=2)
    assert again.presses == ()
    assert again.down is Buttons.ESTOP


def test_a_gap_forgets_the_baseline_and_a_press_during_it_is_not_replayed() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    gap = decoder.update(None, seq=None)
    assert gap.presses == ()
    assert gap.down is Buttons.NONE  # nothing held is assumed while blind
    # ENGAGE was pressed while the panel was stale: the next frame is a new baseline.
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 1)), seq=5).presses == ()
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 2)), seq=6).presses == (Buttons.ENGAGE,)


def test_missing_seq_is_a_gap_too() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 1)), seq=None).presses == ()
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 1)), seq=2).presses == ()


def test_reset_is_a_restart() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    decoder.reset()
    assert decoder.update(frame(counts_with(Buttons.ENGAGE, 1)), seq=2).presses == ()


def test_an_implausible_jump_is_ignored_and_reported() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    jump = MAX_PRESSES_PER_FRAME + 1
    events = decoder.update(frame((jump, 1, 0, 0, 0)), seq=2)
    assert events.presses == (Buttons.SPEED_PLUS,)
    assert events.implausible == (Buttons.ENGAGE,)
    # The jump is the new baseline: the next single step is one press again.
    assert decoder.update(frame((jump + 1, 1, 0, 0, 0)), seq=3).presses == (Buttons.ENGAGE,)


def test_a_counter_going_backwards_is_implausible() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(counts_with(Buttons.ENGAGE, 10)), seq=1)
    events = decoder.update(frame(counts_with(Buttons.ENGAGE, 9)), seq=2)  # 255 steps ahead
    assert events.presses == ()
    assert events.implausible == (Buttons.ENGAGE,)


def test_the_most_presses_a_person_can_make_in_a_frame_are_plausible() -> None:
    decoder = PanelDecoder()
    decoder.update(frame(), seq=1)
    events = decoder.update(frame(counts_with(Buttons.ENGAGE, MAX_PRESSES_PER_FRAME)), seq=2)
    assert Buttons.ENGAGE in events.presses
    assert events.implausible == ()


deltas = st.lists(
    st.tuples(*(st.integers(0, MAX_PRESSES_PER_FRAME) for _ in BUTTON_ORDER)), max_size=40
)
start = st.tuples(*(st.integers(0, 255) for _ in BUTTON_ORDER))


def _replay(first: tuple[int, ...], steps: list[tuple[int, ...]]) -> dict[Buttons, int]:
    decoder = PanelDecoder()
    counts = list(first)
    reported = dict.fromkeys(BUTTON_ORDER, 0)
    events = decoder.update(frame(tuple(counts)), seq=0)
    assert events.presses == ()
    for seq, delta in enumerate(steps, start=1):
        counts = [(c + d) % 256 for c, d in zip(counts, delta, strict=True)]
        events = decoder.update(frame(tuple(counts)), seq=seq)
        assert events.implausible == ()
        for button in events.presses:
            reported[button] += 1
    return reported


@settings(max_examples=200, deadline=None)
@given(start, deltas)
def test_every_plausible_frame_reports_each_button_that_moved(
    first: tuple[int, ...], steps: list[tuple[int, ...]]
) -> None:
    """A button is reported in a frame iff it moved, once per press, in BUTTON_ORDER."""
    decoder = PanelDecoder()
    counts = list(first)
    decoder.update(frame(tuple(counts)), seq=0)
    for seq, delta in enumerate(steps, start=1):
        counts = [(c + d) % 256 for c, d in zip(counts, delta, strict=True)]
        events = decoder.update(frame(tuple(counts)), seq=seq)
        moved = tuple(b for b, d in zip(BUTTON_ORDER, delta, strict=True) for _ in range(d))
        assert events.presses == moved
        assert events.implausible == ()


@settings(max_examples=200, deadline=None)
@given(start, deltas)
@example(first=ZERO, steps=[(0, 0, 2, 0, 0)])  # two SPEED_MINUS presses in one frame
def test_reported_presses_add_up_to_the_counter_deltas(
    first: tuple[int, ...], steps: list[tuple[int, ...]]
) -> None:
    reported = _replay(first, steps)
    for index, button in enumerate(BUTTON_ORDER):
        assert reported[button] == sum(delta[index] for delta in steps), button
