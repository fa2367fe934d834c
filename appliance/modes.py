"""The operator mode machine: a pure transition function, no I/O, no clock, no asyncio.

Why pure: every state × event pair can then be tested from a table (STYLE rule 9, after
openpilot's ``selfdrive/selfdrived/state.py``), and the control loop only has to execute
the returned :class:`Action` values. Time comes in as ``now_s`` (rule 7).

Behaviour follows Stanley et al., Fig. 4 (cruise-control-like autopilot modes) and
Kinouchi et al. (hold-to-move guidance). The stance is deny-by-default (rule 10): the
machine starts in BOOT, reaches READY at best on its own, and only an explicit engage
(or a speed press while steering is engaged) with every condition satisfied can enter
ENGAGED or SPEED_HOLD.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from enum import StrEnum

from safety.faults import FaultCleared as FaultCleared
from safety.faults import FaultRaised as FaultRaised


class Mode(StrEnum):
    BOOT = "boot"
    SELF_CHECK = "self_check"
    READY = "ready"
    ENGAGED = "engaged"  # steering automatic, throttle/brake with the operator
    SPEED_HOLD = "speed_hold"  # steering and speed automatic
    ERROR = "error"
    ESTOP = "estop"


AUTOMATIC_MODES = frozenset({Mode.ENGAGED, Mode.SPEED_HOLD})


# ---------------------------------------------------------------- events


@dataclass(frozen=True)
class BootDone:
    pass


@dataclass(frozen=True)
class SelfCheckPassed:
    pass


@dataclass(frozen=True)
class SelfCheckFailed:
    reasons: tuple[str, ...]


@dataclass(frozen=True)
class EngagePressed:
    pass


@dataclass(frozen=True)
class SpeedPlusPressed:
    measured_speed_mps: float


@dataclass(frozen=True)
class SpeedMinusPressed:
    measured_speed_mps: float


@dataclass(frozen=True)
class BrakeTap:
    pass


@dataclass(frozen=True)
class ManualOverridePressed:
    pass


@dataclass(frozen=True)
class SteeringOverridden:
    """The operator took the wheel (detected by the override rule): everything goes back."""


@dataclass(frozen=True)
class ThrottlePedalPressed:
    """The operator's foot on the throttle in speed hold: the throttle is theirs again."""


@dataclass(frozen=True)
class EStopPressed:
    pass


@dataclass(frozen=True)
class EStopReset:
    """The operator's reset procedure was completed (not merely the button released)."""


@dataclass(frozen=True)
class HoldToMovePressed:
    pass


@dataclass(frozen=True)
class HoldToMoveReleased:
    pass


Event = (
    BootDone
    | SelfCheckPassed
    | SelfCheckFailed
    | EngagePressed
    | SpeedPlusPressed
    | SpeedMinusPressed
    | BrakeTap
    | ManualOverridePressed
    | SteeringOverridden
    | ThrottlePedalPressed
    | FaultRaised
    | FaultCleared
    | EStopPressed
    | EStopReset
    | HoldToMovePressed
    | HoldToMoveReleased
)


# ---------------------------------------------------------------- actions


@dataclass(frozen=True)
class RefuseEngagement:
    reasons: tuple[str, ...]


@dataclass(frozen=True)
class SetLamps:
    override_lamp: bool
    warning_lamp: bool


@dataclass(frozen=True)
class Announce:
    message: str


@dataclass(frozen=True)
class CommandSafeState:
    reason: str
    full_brake: bool


@dataclass(frozen=True)
class HandBackThrottle:
    pass


@dataclass(frozen=True)
class HandBackSteering:
    pass


@dataclass(frozen=True)
class SetSpeed:
    speed_mps: float


@dataclass(frozen=True)
class ControlledStop:
    """Stop within the configured distance; the hold-to-move button was released."""

    reason: str


Action = (
    RefuseEngagement
    | SetLamps
    | Announce
    | CommandSafeState
    | HandBackThrottle
    | HandBackSteering
    | SetSpeed
    | ControlledStop
)


# ---------------------------------------------------------------- inputs and state


@dataclass(frozen=True)
class ModeParams:
    speed_step_mps: float = 0.5
    max_speed_mps: float = 5.0

    def __post_init__(self) -> None:
        if not (self.speed_step_mps > 0 and self.max_speed_mps > 0):
            raise ValueError("speed step and max speed must be positive")


DEFAULT_PARAMS = ModeParams()


@dataclass(frozen=True)
class EngageConditions:
    """What the runtime knows about the vehicle when an event arrives.

    No defaults on purpose: a caller must state every condition, so a forgotten one
    cannot silently read as "fine".
    """

    fault_active: bool
    stale_inputs: tuple[str, ...]
    calibration_valid: bool
    operator_overriding: bool
    speed_above_limit: bool
    source_ready: bool
    source_reason: str = ""


@dataclass(frozen=True)
class LatchedFault:
    reason: str
    since_s: float


@dataclass(frozen=True)
class ModeState:
    """Defaults are the state after any (re)start: BOOT, nothing engaged or passed."""

    mode: Mode = Mode.BOOT
    set_speed_mps: float | None = None
    faults: tuple[LatchedFault, ...] = ()
    estop_latched: bool = False
    hold_to_move_held: bool = False
    self_check_passed: bool = False
    last_refusal: tuple[str, ...] = ()


def lamps(mode: Mode) -> tuple[bool, bool]:
    """(override_lamp, warning_lamp). ERROR lights both, as in Stanley et al."""
    if mode in (Mode.ERROR, Mode.ESTOP):
        return True, True
    return False, False


def motion_permitted(state: ModeState) -> bool:
    """Hold-to-move: the autopilot may move the vehicle only while the button is held."""
    return state.mode in AUTOMATIC_MODES and state.hold_to_move_held and not state.estop_latched


def refusal_reasons(state: ModeState, conditions: EngageConditions) -> tuple[str, ...]:
    """Every reason engagement must be refused (openpilot's no-entry events); empty = OK."""
    reasons: list[str] = []
    if conditions.fault_active or state.faults:
        latched = ", ".join(f.reason for f in state.faults)
        reasons.append(f"fault active{': ' + latched if latched else ''}")
    reasons.extend(f"critical input stale: {name}" for name in conditions.stale_inputs)
    if not conditions.calibration_valid:
        reasons.append("calibration missing or invalid")
    if conditions.operator_overriding:
        reasons.append("operator overriding")
    if conditions.speed_above_limit:
        reasons.append("speed above engage limit")
    if not conditions.source_ready:
        reasons.append(f"autopilot source not ready: {conditions.source_reason or 'unknown'}")
    if state.estop_latched:
        reasons.append("e-stop latched")
    return tuple(reasons)


# ---------------------------------------------------------------- transitions


def _enter(
    state: ModeState, mode: Mode, message: str, **changes: object
) -> tuple[ModeState, list[Action]]:
    """Change mode, drop the set speed outside SPEED_HOLD, and re-drive the lamps."""
    set_speed = state.set_speed_mps if mode is Mode.SPEED_HOLD else None
    new = replace(state, mode=mode, set_speed_mps=set_speed, **changes)  # type: ignore[arg-type]
    override, warning = lamps(mode)
    return new, [SetLamps(override, warning), Announce(message)]


def _hand_back() -> list[Action]:
    return [HandBackThrottle(), HandBackSteering()]


def _resume_mode(state: ModeState) -> Mode:
    """Where ERROR/ESTOP recovery lands: READY at best, BOOT if checks never passed."""
    return Mode.READY if state.self_check_passed else Mode.BOOT


def _latch(state: ModeState, reason: str, now_s: float) -> tuple[LatchedFault, ...]:
    if any(f.reason == reason for f in state.faults):
        return state.faults  # keep the first timestamp: it says when the trouble began
    return (*state.faults, LatchedFault(reason, now_s))


def _fault(
    state: ModeState, reasons: tuple[str, ...], now_s: float
) -> tuple[ModeState, list[Action]]:
    faults = state.faults
    for reason in reasons:
        faults = _latch(replace(state, faults=faults), reason, now_s)
    text = "; ".join(reasons)
    if state.mode is Mode.ESTOP:
        # Latch it for later, but ESTOP outranks ERROR: keep braking fully.
        new = replace(state, faults=faults)
        return new, [CommandSafeState(text, full_brake=True), Announce(f"fault: {text}")]
    new, actions = _enter(state, Mode.ERROR, f"fault: {text}", faults=faults)
    return new, [CommandSafeState(text, full_brake=False), *_hand_back(), *actions]


def _speed_press(
    state: ModeState,
    measured_speed_mps: float,
    delta_mps: float,
    conditions: EngageConditions,
    params: ModeParams,
) -> tuple[ModeState, list[Action]]:
    if state.mode is Mode.SPEED_HOLD and state.set_speed_mps is not None:
        target = min(max(state.set_speed_mps + delta_mps, 0.0), params.max_speed_mps)
        return replace(state, set_speed_mps=target), [SetSpeed(target)]
    if state.mode is not Mode.ENGAGED:
        refused = ("steering not engaged",)
        return replace(state, last_refusal=refused), [RefuseEngagement(refused)]
    reasons = refusal_reasons(state, conditions)
    if measured_speed_mps > params.max_speed_mps:
        reasons = (*reasons, "speed above maximum set speed")
    if reasons:
        return replace(state, last_refusal=reasons), [RefuseEngagement(reasons)]
    target = max(measured_speed_mps, 0.0)
    new, actions = _enter(
        replace(state, set_speed_mps=target), Mode.SPEED_HOLD, "speed hold", last_refusal=()
    )
    return new, [SetSpeed(target), *actions]


def step(
    state: ModeState,
    event: Event,
    conditions: EngageConditions,
    now_s: float,
    params: ModeParams = DEFAULT_PARAMS,
) -> tuple[ModeState, list[Action]]:
    """Advance the mode machine by one event; returns the new state and what to do."""
    mode = state.mode
    match event:
        case EStopPressed():
            if mode is Mode.ESTOP:
                return state, [CommandSafeState("e-stop", full_brake=True)]
            new, actions = _enter(state, Mode.ESTOP, "e-stop", estop_latched=True)
            return new, [CommandSafeState("e-stop", full_brake=True), *_hand_back(), *actions]
        case EStopReset():
            if mode is not Mode.ESTOP:
                return state, []
            target = Mode.ERROR if state.faults else _resume_mode(state)
            return _enter(state, target, "e-stop reset", estop_latched=False)
        case _ if mode is Mode.ESTOP and not isinstance(
            event, FaultRaised | FaultCleared | HoldToMovePressed | HoldToMoveReleased
        ):
            return state, []  # latched: only the reset procedure leaves ESTOP
        case FaultRaised(reason=reason):
            return _fault(state, (reason,), now_s)
        case FaultCleared(reason=reason):
            return replace(state, faults=tuple(f for f in state.faults if f.reason != reason)), []
        case HoldToMovePressed():
            return replace(state, hold_to_move_held=True), []
        case HoldToMoveReleased():
            released = replace(state, hold_to_move_held=False)
            if state.hold_to_move_held and mode in AUTOMATIC_MODES:
                return released, [ControlledStop("hold-to-move released")]
            return released, []
        case BootDone() if mode is Mode.BOOT:
            return _enter(state, Mode.SELF_CHECK, "self-check")
        case SelfCheckPassed() if mode is Mode.SELF_CHECK:
            return _enter(state, Mode.READY, "ready", self_check_passed=True)
        case SelfCheckFailed(reasons=reasons) if mode is Mode.SELF_CHECK:
            return _fault(
                state, tuple(f"self-check: {r}" for r in reasons) or ("self-check",), now_s
            )
        case EngagePressed():
            if mode is not Mode.READY:
                if mode in AUTOMATIC_MODES:
                    return state, []
                why = f"cannot engage from {mode}"
                if mode is Mode.ERROR and state.faults:
                    why += " (faults: " + ", ".join(f.reason for f in state.faults) + ")"
                elif mode is Mode.ERROR:
                    why += " (faults cleared: press manual override first)"
                reasons = (why,)
                return replace(state, last_refusal=reasons), [RefuseEngagement(reasons)]
            reasons = refusal_reasons(state, conditions)
            if reasons:
                return replace(state, last_refusal=reasons), [RefuseEngagement(reasons)]
            return _enter(state, Mode.ENGAGED, "steering engaged", last_refusal=())
        case SpeedPlusPressed(measured_speed_mps=speed):
            return _speed_press(state, speed, params.speed_step_mps, conditions, params)
        case SpeedMinusPressed(measured_speed_mps=speed):
            return _speed_press(state, speed, -params.speed_step_mps, conditions, params)
        case BrakeTap() if mode is Mode.SPEED_HOLD:
            new, actions = _enter(state, Mode.ENGAGED, "speed hold cancelled by brake")
            return new, [HandBackThrottle(), *actions]
        case ThrottlePedalPressed() if mode is Mode.SPEED_HOLD:
            new, actions = _enter(state, Mode.ENGAGED, "speed hold cancelled by throttle pedal")
            return new, [HandBackThrottle(), *actions]
        case SteeringOverridden() if mode in AUTOMATIC_MODES:
            new, actions = _enter(state, Mode.READY, "operator took the wheel")
            return new, [*_hand_back(), *actions]
        case ManualOverridePressed() if mode in AUTOMATIC_MODES:
            new, actions = _enter(state, Mode.READY, "manual override")
            return new, [*_hand_back(), *actions]
        case ManualOverridePressed() if mode is Mode.ERROR:
            if state.faults or conditions.fault_active:
                active = ", ".join(f.reason for f in state.faults) or "fault active"
                reasons = (f"cannot leave error, fault not cleared: {active}",)
                return replace(state, last_refusal=reasons), [Announce(reasons[0])]
            return _enter(state, _resume_mode(state), "error cleared", last_refusal=())
    return state, []
