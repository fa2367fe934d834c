"""Mode machine tests: every state × event from an explicit table, then properties.

The table is written out by hand (like openpilot's test_state_machine.py) so a change
in behaviour has to be a visible change here, not an accident of the implementation.
"""

from __future__ import annotations

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from appliance.modes import (
    AUTOMATIC_MODES,
    Action,
    Announce,
    BootDone,
    BrakeTap,
    CommandSafeState,
    ControlledStop,
    EngageConditions,
    EngagePressed,
    EStopPressed,
    EStopReset,
    Event,
    FaultCleared,
    FaultRaised,
    HandBackSteering,
    HandBackThrottle,
    HoldToMovePressed,
    HoldToMoveReleased,
    LatchedFault,
    ManualOverridePressed,
    Mode,
    ModeParams,
    ModeState,
    RefuseEngagement,
    SelfCheckFailed,
    SelfCheckPassed,
    SetLamps,
    SetSpeed,
    SpeedMinusPressed,
    SpeedPlusPressed,
    SteeringOverridden,
    ThrottlePedalPressed,
    lamps,
    motion_permitted,
    refusal_reasons,
    step,
)

PARAMS = ModeParams(speed_step_mps=0.5, max_speed_mps=5.0)
OK = EngageConditions(
    fault_active=False,
    stale_inputs=(),
    calibration_valid=True,
    operator_overriding=False,
    speed_above_limit=False,
    source_ready=True,
)

B, SC, R, EN, SH, ER, ES = (
    Mode.BOOT,
    Mode.SELF_CHECK,
    Mode.READY,
    Mode.ENGAGED,
    Mode.SPEED_HOLD,
    Mode.ERROR,
    Mode.ESTOP,
)

STATES: dict[str, ModeState] = {
    "boot": ModeState(),
    "self_check": ModeState(mode=SC),
    "ready": ModeState(mode=R, self_check_passed=True),
    "engaged": ModeState(mode=EN, self_check_passed=True),
    "speed_hold": ModeState(mode=SH, set_speed_mps=2.0, self_check_passed=True),
    "error_latched": ModeState(mode=ER, faults=(LatchedFault("x", 0.0),), self_check_passed=True),
    "error_cleared": ModeState(mode=ER, self_check_passed=True),
    "estop": ModeState(mode=ES, estop_latched=True, self_check_passed=True),
}

EVENTS: dict[str, Event] = {
    "boot_done": BootDone(),
    "check_ok": SelfCheckPassed(),
    "check_fail": SelfCheckFailed(("lidar missing",)),
    "engage": EngagePressed(),
    "plus": SpeedPlusPressed(3.0),
    "minus": SpeedMinusPressed(3.0),
    "brake": BrakeTap(),
    "override": ManualOverridePressed(),
    "fault": FaultRaised("pc104 stale"),
    "cleared": FaultCleared("x"),
    "estop": EStopPressed(),
    "reset": EStopReset(),
    "hold": HoldToMovePressed(),
    "release": HoldToMoveReleased(),
    "wheel": SteeringOverridden(),
    "gas": ThrottlePedalPressed(),
}

# fmt: off
# columns: boot_done check_ok check_fail engage plus minus brake override fault cleared
#          estop reset hold release wheel gas (the order of EVENTS)
TABLE: dict[str, tuple[Mode, ...]] = {
    "boot":          (SC, B,  B,  B,  B,  B,  B,  B,  ER, B,  ES, B,  B,  B,  B,  B),
    "self_check":    (SC, R,  ER, SC, SC, SC, SC, SC, ER, SC, ES, SC, SC, SC, SC, SC),
    "ready":         (R,  R,  R,  EN, R,  R,  R,  R,  ER, R,  ES, R,  R,  R,  R,  R),
    "engaged":       (EN, EN, EN, EN, SH, SH, EN, R,  ER, EN, ES, EN, EN, EN, R,  EN),
    "speed_hold":    (SH, SH, SH, SH, SH, SH, EN, R,  ER, SH, ES, SH, SH, SH, R,  EN),
    "error_latched": (ER, ER, ER, ER, ER, ER, ER, ER, ER, ER, ES, ER, ER, ER, ER, ER),
    "error_cleared": (ER, ER, ER, ER, ER, ER, ER, R,  ER, ER, ES, ER, ER, ER, ER, ER),
    "estop":         (ES, ES, ES, ES, ES, ES, ES, ES, ES, ES, ES, R,  ES, ES, ES, ES),
}
# fmt: on

CASES = [
    pytest.param(s, e, TABLE[s][i], id=f"{s}-{e}") for s in STATES for i, e in enumerate(EVENTS)
]


def test_table_covers_every_mode_and_event() -> None:
    assert {st.mode for st in STATES.values()} == set(Mode)
    assert all(len(row) == len(EVENTS) for row in TABLE.values())
    assert {type(e) for e in EVENTS.values()} == set(Event.__args__)


@pytest.mark.parametrize(("state_name", "event_name", "expected"), CASES)
def test_transition_table(state_name: str, event_name: str, expected: Mode) -> None:
    before = STATES[state_name]
    after, actions = step(before, EVENTS[event_name], OK, 10.0, PARAMS)
    assert after.mode is expected
    if after.mode is not before.mode:
        assert SetLamps(*lamps(after.mode)) in actions
    if before.mode in AUTOMATIC_MODES and after.mode not in AUTOMATIC_MODES:
        assert HandBackSteering() in actions
        assert HandBackThrottle() in actions


def _safe_states(actions: list[Action]) -> list[CommandSafeState]:
    return [a for a in actions if isinstance(a, CommandSafeState)]


@pytest.mark.parametrize(
    ("conditions", "reason"),
    [
        (EngageConditions(True, (), True, False, False, True), "fault active"),
        (EngageConditions(False, ("pose",), True, False, False, True), "stale: pose"),
        (EngageConditions(False, (), False, False, False, True), "calibration"),
        (EngageConditions(False, (), True, True, False, True), "operator overriding"),
        (EngageConditions(False, (), True, False, True, True), "speed above"),
        (EngageConditions(False, (), True, False, False, False, "off route"), "off route"),
    ],
)
def test_each_failing_condition_refuses_with_its_reason(
    conditions: EngageConditions, reason: str
) -> None:
    after, actions = step(STATES["ready"], EngagePressed(), conditions, 1.0, PARAMS)
    assert after.mode is R
    assert len(after.last_refusal) == 1
    assert reason in after.last_refusal[0]
    assert actions == [RefuseEngagement(after.last_refusal)]


def test_all_failing_conditions_are_all_reported() -> None:
    bad = EngageConditions(True, ("pose", "scan"), False, True, True, False, "no route")
    after, _ = step(STATES["ready"], EngagePressed(), bad, 1.0, PARAMS)
    assert after.mode is R
    assert len(after.last_refusal) == 7  # fault, 2 stale, calibration, override, speed, source


def test_speed_hold_locks_measured_speed_then_steps_and_clamps() -> None:
    state, actions = step(STATES["engaged"], SpeedMinusPressed(4.2), OK, 0.0, PARAMS)
    assert (state.mode, state.set_speed_mps) == (SH, 4.2)
    assert SetSpeed(4.2) in actions
    for _ in range(5):
        state, _ = step(state, SpeedPlusPressed(4.2), OK, 0.0, PARAMS)
    assert state.set_speed_mps == PARAMS.max_speed_mps
    for _ in range(20):
        state, _ = step(state, SpeedMinusPressed(4.2), OK, 0.0, PARAMS)
    assert state.set_speed_mps == 0.0
    state, actions = step(state, BrakeTap(), OK, 0.0, PARAMS)
    assert (state.mode, state.set_speed_mps) == (EN, None)
    assert HandBackThrottle() in actions and HandBackSteering() not in actions


def test_speed_lock_above_max_or_with_bad_conditions_is_refused() -> None:
    state, _ = step(STATES["engaged"], SpeedPlusPressed(9.0), OK, 0.0, PARAMS)
    assert state.mode is EN and "maximum" in state.last_refusal[-1]
    stale = EngageConditions(False, ("pot",), True, False, False, True)
    state, _ = step(STATES["engaged"], SpeedPlusPressed(2.0), stale, 0.0, PARAMS)
    assert state.mode is EN and state.set_speed_mps is None


def test_fault_latches_reason_and_first_time_and_commands_safe_state() -> None:
    state, actions = step(STATES["speed_hold"], FaultRaised("steer slip"), OK, 3.0, PARAMS)
    assert state.mode is ER and state.faults == (LatchedFault("steer slip", 3.0),)
    assert _safe_states(actions) == [CommandSafeState("steer slip", full_brake=False)]
    assert any(isinstance(a, Announce) for a in actions)
    state, _ = step(state, FaultRaised("steer slip"), OK, 9.0, PARAMS)
    assert state.faults == (LatchedFault("steer slip", 3.0),)


def test_error_clears_only_after_every_fault_then_override() -> None:
    state, _ = step(STATES["ready"], FaultRaised("a"), OK, 1.0, PARAMS)
    state, _ = step(state, FaultRaised("b"), OK, 2.0, PARAMS)
    state, _ = step(state, FaultCleared("a"), OK, 3.0, PARAMS)
    state, _ = step(state, ManualOverridePressed(), OK, 4.0, PARAMS)
    assert state.mode is ER and "b" in state.last_refusal[0]
    state, _ = step(state, FaultCleared("b"), OK, 5.0, PARAMS)
    still_faulty = EngageConditions(True, (), True, False, False, True)
    state, _ = step(state, ManualOverridePressed(), still_faulty, 6.0, PARAMS)
    assert state.mode is ER
    state, _ = step(state, ManualOverridePressed(), OK, 7.0, PARAMS)
    assert state.mode is R


def test_estop_brakes_fully_and_reset_with_latched_fault_goes_to_error() -> None:
    state, actions = step(STATES["engaged"], EStopPressed(), OK, 0.0, PARAMS)
    assert state.estop_latched and CommandSafeState("e-stop", True) in actions
    state, actions = step(state, FaultRaised("board"), OK, 1.0, PARAMS)
    assert state.mode is ES and _safe_states(actions)[0].full_brake
    state, _ = step(state, EStopReset(), OK, 2.0, PARAMS)
    assert (state.mode, state.estop_latched) == (ER, False)


def test_recovery_before_self_check_returns_to_boot_not_ready() -> None:
    state, _ = step(ModeState(), EStopPressed(), OK, 0.0, PARAMS)
    state, _ = step(state, EStopReset(), OK, 1.0, PARAMS)
    assert state.mode is B


def test_hold_to_move() -> None:
    state = STATES["engaged"]
    assert not motion_permitted(state)
    state, _ = step(state, HoldToMovePressed(), OK, 0.0, PARAMS)
    assert motion_permitted(state)
    state, actions = step(state, HoldToMoveReleased(), OK, 0.0, PARAMS)
    assert not motion_permitted(state)
    assert actions == [ControlledStop("hold-to-move released")]
    held_ready = ModeState(mode=R, hold_to_move_held=True)
    assert not motion_permitted(held_ready)


def test_lamps() -> None:
    assert lamps(ER) == (True, True)
    assert all(lamps(m) == (False, False) for m in (B, SC, R, EN, SH))


def test_restart_state_is_boot() -> None:
    assert ModeState().mode is B and not ModeState().self_check_passed


# ---------------------------------------------------------------- property test

reasons = st.sampled_from(["a", "b", "x"])
events: st.SearchStrategy[Event] = st.one_of(
    st.sampled_from(
        [
            BootDone(),
            SelfCheckPassed(),
            EngagePressed(),
            BrakeTap(),
            ManualOverridePressed(),
            EStopPressed(),
            EStopReset(),
            HoldToMovePressed(),
            HoldToMoveReleased(),
            SteeringOverridden(),
            ThrottlePedalPressed(),
        ]
    ),
    st.builds(SelfCheckFailed, st.lists(reasons, max_size=2).map(tuple)),
    st.builds(SpeedPlusPressed, st.floats(-1.0, 8.0)),
    st.builds(SpeedMinusPressed, st.floats(-1.0, 8.0)),
    st.builds(FaultRaised, reasons),
)
conditions_st = st.one_of(
    st.just(OK),
    st.builds(
        EngageConditions,
        st.booleans(),
        st.sampled_from([(), ("pose",)]),
        st.booleans(),
        st.booleans(),
        st.booleans(),
        st.booleans(),
        st.just("r"),
    ),
)


class ModeMachine(RuleBasedStateMachine):
    """Random operator, pedal, fault and e-stop sequences with restarts and time."""

    def __init__(self) -> None:
        super().__init__()
        self.state = ModeState()
        self.now_s = 0.0
        self.needs_explicit_engage = True

    @rule()
    def restart(self) -> None:
        self.state = ModeState()
        self.needs_explicit_engage = True

    # Uniform random events spend most of their time in ERROR, so a few rules steer the
    # walk through the happy path (bring-up, engage, lock speed, recover) as well.
    @rule(event=events, conditions=conditions_st, dt_s=st.floats(0.0, 5.0))
    def random_event(self, event: Event, conditions: EngageConditions, dt_s: float) -> None:
        self._apply(event, conditions, dt_s)

    @rule()
    def bring_up(self) -> None:
        self._apply(BootDone(), OK, 0.1)
        self._apply(SelfCheckPassed(), OK, 0.1)

    @rule(conditions=conditions_st)
    def engage(self, conditions: EngageConditions) -> None:
        self._apply(EngagePressed(), conditions, 0.1)

    @rule(speed_mps=st.floats(0.0, 6.0), plus=st.booleans())
    def lock_speed(self, speed_mps: float, plus: bool) -> None:
        press = SpeedPlusPressed(speed_mps) if plus else SpeedMinusPressed(speed_mps)
        self._apply(press, OK, 0.1)

    @rule()
    def estop_reset_procedure(self) -> None:
        self._apply(EStopReset(), OK, 0.1)

    @rule()
    def clear_faults_and_override(self) -> None:
        for fault in self.state.faults:
            self._apply(FaultCleared(fault.reason), OK, 0.1)
        self._apply(ManualOverridePressed(), OK, 0.1)

    def _apply(self, event: Event, conditions: EngageConditions, dt_s: float) -> None:
        self.now_s += dt_s
        before = self.state
        after, actions = step(before, event, conditions, self.now_s, PARAMS)
        entered = after.mode if after.mode is not before.mode else None

        if entered is EN and before.mode is R:
            assert isinstance(event, EngagePressed)
            assert refusal_reasons(before, conditions) == ()
            self.needs_explicit_engage = False
        elif entered is EN:
            assert before.mode is SH and isinstance(event, BrakeTap | ThrottlePedalPressed)
        if entered is SH:
            assert before.mode is EN
            assert isinstance(event, SpeedPlusPressed | SpeedMinusPressed)
            assert refusal_reasons(before, conditions) == ()
        if isinstance(event, FaultRaised):
            assert after.mode in (ER, ES)
            assert _safe_states(actions)
        if isinstance(event, EStopPressed):
            assert after.mode is ES and CommandSafeState("e-stop", True) in actions
        if before.mode is ES and not isinstance(event, EStopReset):
            assert after.mode is ES and after.estop_latched
        if after.mode in (ER, ES):
            self.needs_explicit_engage = True
        if after.mode in AUTOMATIC_MODES:
            assert not self.needs_explicit_engage
        if entered is not None:
            assert SetLamps(*lamps(entered)) in actions
        self.state = after

    @invariant()
    def set_speed_bounded_and_only_in_speed_hold(self) -> None:
        speed = self.state.set_speed_mps
        if self.state.mode is SH:
            assert speed is not None and 0.0 <= speed <= PARAMS.max_speed_mps
        else:
            assert speed is None

    @invariant()
    def estop_flag_matches_mode(self) -> None:
        assert self.state.estop_latched == (self.state.mode is ES)

    @invariant()
    def motion_only_when_engaged_and_held(self) -> None:
        if motion_permitted(self.state):
            assert self.state.mode in AUTOMATIC_MODES and self.state.hold_to_move_held


ModeMachine.TestCase.settings = settings(max_examples=200, stateful_step_count=40, deadline=None)
TestModeMachine = ModeMachine.TestCase
