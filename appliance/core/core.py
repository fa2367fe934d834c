"""The control core: inputs in, every command of the cycle out, time as an argument.

One ``step`` runs, in this order, what Stanley et al.'s mode control (Fig. 4) and the
safety layer ask for: judge the age of every input, convert what is fresh, detect the
operator (hands on the wheel, feet on the pedals), gather fault conditions, feed the mode
machine its events (e-stop first, then faults, then the operator, then buttons), ask the
autopilot source for its wish; then :class:`~appliance.core.commands.CommandPaths` passes
that wish through arbitration and limits. The result is a :class:`CoreOutput` with one
command per actuator path; nothing in here touches a device. The object holds small rule
objects with ``reset()``/``update()``; a fresh core (after any restart) is in BOOT and can
only reach READY on its own.

Actuation paths (see docs/control.md): steering through the servo board (a position
set-point in the servo's relative frame, closed through the calibrated pot) and the
PC104's front set-point; speed by ``speed_path``: ``pc104``, the PC104's own speed loop
(pattern + speed set-point), the brake board applying the safe-state brake and the
throttle board released (nothing opens a throttle actuator); ``pedals`` (no PC104), the
throttle and brake boards driven by our speed controller in SPEED_HOLD, the speed measured
by the GNSS/INS, and the PC104 no input at all (not critical, no readiness, no faults).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import replace
from typing import Any

from appliance.config import parts
from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.core.autopilot import (
    AutopilotSource,
    AutopilotWish,
    Observation,
    RouteAutopilot,
    default_pattern,
    make_source,
)
from appliance.core.commands import CommandPaths
from appliance.core.inputs import ControlInputs
from appliance.core.maneuver_tap import ManeuverTap
from appliance.core.observe import (
    Measurements,
    board_faults,
    measure,
    pc104_faults,
    pedal_path_problems,
)
from appliance.core.output import CoreOutput, Note
from appliance.core.panel import PanelDecoder, PanelEvents
from appliance.core.programs import DrivenPrograms
from appliance.core.report import core_status
from appliance.core.route_tuning import tuning_refusal
from appliance.core.torque_watch import TorqueWatch
from appliance.modes import (
    AUTOMATIC_MODES,
    Action,
    BootDone,
    BrakeTap,
    EngageConditions,
    EngagePressed,
    EStopPressed,
    EStopReset,
    Event,
    FaultCleared,
    HoldToMovePressed,
    HoldToMoveReleased,
    ManualOverridePressed,
    Mode,
    ModeParams,
    ModeState,
    RefuseEngagement,
    SelfCheckFailed,
    SelfCheckPassed,
    SpeedMinusPressed,
    SpeedPlusPressed,
    SteeringOverridden,
    ThrottlePedalPressed,
    refusal_reasons,
    step,
)
from drivers.actuators.messages import Buttons, SteeringMode
from drivers.pc104.messages import ControlSource
from safety.arbitration import OperatorInput
from safety.consistency import CounterDeltas, SteeringTrackingMonitor
from safety.faults import FaultMonitor
from safety.system_health import system_faults

BENCH_REQUESTS = (
    "engage",
    "disengage",
    "speed_plus",
    "speed_minus",
    "estop",
    "estop_reset",
    "hold",
    "release",
)


_NOT_READY = EngageConditions(
    fault_active=True,
    stale_inputs=(),
    calibration_valid=False,
    operator_overriding=False,
    speed_above_limit=True,
    source_ready=False,
    source_reason="no cycle has run yet",
)


SYSTEM_HEALTH_INPUT = "system.health"
# (kind "request", "select_route" or "select_pallet", name, now_s or None, accepted, message)
RequestListener = Callable[[str, str, float | None, bool, str], None]


class ControlCore:
    def __init__(
        self,
        config: VehicleConfig,
        calibration: Calibration | None,
        calibration_problem: str = "",
        autopilot: AutopilotSource | None = None,
    ) -> None:
        self.config = config
        self.calibration = calibration
        self.calibration_problem = calibration_problem or (
            "" if calibration is not None else "calibration missing"
        )
        self.autopilot = autopilot if autopilot is not None else make_source(config, calibration)
        self.pattern = default_pattern(config.kind)
        self.mode_params = ModeParams(
            speed_step_mps=config.engagement.speed_step_mps,
            max_speed_mps=min(config.engagement.max_set_speed_mps, config.limits.max_speed_mps),
        )
        self.pedals = config.speed_path == "pedals"
        self.staleness = parts.staleness_guard(config.staleness, parts.critical_inputs(config))
        self.override = parts.operator_override(config.safety, config.limits)
        self.tracking = SteeringTrackingMonitor(parts.steering_tracking_params(config.safety))
        self.link_budget = parts.error_budget(config.safety)
        self.link_deltas = CounterDeltas()
        self.faults = FaultMonitor()
        self.commands = CommandPaths(
            config, calibration, self.pattern, self.mode_params.max_speed_mps
        )
        self.panel = PanelDecoder()
        self.system_health = parts.system_health_params(config)
        # Told of every request and route selection, with the answer (the recorder).
        self.request_listeners: list[RequestListener] = []
        # The calibration maneuvers' tap: kept across a core restart (it only reads; the
        # samples show the mode the core restarted in, and a fault on the way ends a run).
        self.maneuver = ManeuverTap()
        # The maneuvers the daemon drives (the pedal sweep, the palm tree), armed by their
        # maneuver requests, their wishes judged like any source's.
        self.programs = DrivenPrograms(config, calibration)
        # The servo's load against the look-ahead tuning's (Fig. 21), where it has one.
        guidance = None if calibration is None else calibration.guidance
        baseline = None if guidance is None else guidance.servo_torque
        self.torque_watch = None if baseline is None else TorqueWatch(baseline.stats())
        self.reset()

    def reset(self) -> None:
        """The state after any (re)start: BOOT, nothing engaged, every rule forgotten."""
        self.last_wish: AutopilotWish | None = None
        self.state = ModeState()
        self.mode_since_s: float | None = None
        self.self_check_since_s: float | None = None
        for rule in (
            self.staleness,
            self.override,
            self.tracking,
            self.link_budget,
            self.link_deltas,
            self.faults,
            self.commands,
            self.panel,
            self.autopilot,
        ):
            rule.reset()
        self._brake_pedal_was = False
        self._throttle_pedal_was = False
        self._held = False
        self._bench_hold = False
        self._tablet_held = False
        self._bench_estop = False
        self._conditions = _NOT_READY
        self._measured: Measurements | None = None
        self._notes: list[Note] = []
        self.last_output: CoreOutput | None = None
        self.last_refusal: tuple[str, ...] = ()
        self.stale: tuple[str, ...] = ()
        # A restart disarms the sweep and the look-ahead runs: the client sees it and ends.
        if isinstance(self.autopilot, RouteAutopilot):
            self.autopilot.stop_tuning(engaged=False)
        self.programs.reset()
        if self.torque_watch is not None:
            self.torque_watch.reset()
        self._torque_retune: bool | None = None

    # ---- the cycle --------------------------------------------------------------------
    def step(self, inputs: ControlInputs, now_s: float) -> CoreOutput:
        # Notes from bench requests since the last cycle go out with this cycle's output.
        stale = self.staleness.update(inputs.ages_s, now_s)
        self.stale = stale
        fresh = frozenset(
            name
            for name in self.staleness.age_limits_s
            if not self.staleness.is_stale(name, inputs.ages_s)
        )
        m = measure(
            inputs,
            fresh,
            self.calibration,
            speed_path=self.config.speed_path,
            now_s=now_s,
            gnss_max_age_s=self.config.positioning.max_fix_age_s,
        )
        self._measured = m
        operator = self.override.update(
            commanded_steer_rad=self.commands.last_steer_rad,
            measured_steer_rad=m.steer_tyre_rad,
            servo_torque_nm=m.servo_torque_nm,
            brake_pedal_pct=m.brake_pedal_pct,
            brake_actuator_pct=m.brake_actuator_pct,
            throttle_pedal_pct=m.throttle_pedal_pct,
            throttle_actuator_pct=m.throttle_actuator_pct,
            now_s=now_s,
        )
        panel = self.panel.update(
            inputs.panel if "board.panel" in fresh else None, inputs.panel_seq
        )
        wish = self._wish(m, inputs, now_s)
        self.last_wish = wish
        conditions = self._engage_conditions(stale, m, operator, wish)
        self._conditions = conditions

        # 1. e-stop outranks everything, seen or remembered
        if m.estop_reasons or self._bench_estop:
            self._apply(EStopPressed(), now_s)
        # 2. bring-up
        self._self_check(stale, m, now_s)
        # 3. faults: raised once, cleared once
        active = self._fault_conditions(inputs, stale, fresh, m, operator, wish, now_s)
        changes = self.faults.update(active, now_s)
        for record in changes.raised:
            self._note("fault_raised", fault=record.key, detail=record.detail)
        for record in changes.cleared:
            self._note("fault_cleared", fault=record.key, after_s=round(now_s - record.raised_s, 3))
        for event in changes.mode_events():
            self._apply(event, now_s)
        for latched in self.state.faults:  # e.g. a failed self-check whose problems are gone
            if latched.reason not in active:
                self._apply(FaultCleared(latched.reason), now_s)
        # 4. the operator's hands and feet
        self._operator_events(operator, m, now_s)
        # 5. buttons
        self._panel_events(panel, m, now_s)
        tablet_held = self._tablet_events(inputs, m, now_s)
        held = bool(panel.down & Buttons.ENGAGE) or self._bench_hold or tablet_held
        if held != self._held:
            self._held = held
            self._apply(HoldToMovePressed() if held else HoldToMoveReleased(), now_s)

        output = self.commands.update(self.state, operator, m, wish, tuple(self._notes), now_s)
        self._notes = []
        self.last_output = output
        if self.torque_watch is not None:
            self._watch_torque(output, m, now_s, self.torque_watch)
        if self.maneuver.active:
            sweep, palm = self.programs.tapped()
            tuning = wish.status.get("tuning") if self.maneuver.step == "lookahead" else None
            tuning = tuning if isinstance(tuning, Mapping) else None
            self.maneuver.update(
                inputs, fresh, m, output, stale, self.faults.active_faults, sweep, tuning, palm
            )
        return output

    def _watch_torque(
        self, output: CoreOutput, m: Measurements, now_s: float, watch: TorqueWatch
    ) -> None:
        steering = output.steering.mode is SteeringMode.POSITION
        made = watch.update(
            now_s, steering, m.steer_wheel_rad, m.servo_position_rad, m.servo_torque_nm
        )
        if made is not None and made.retune != self._torque_retune:
            self._torque_retune = made.retune
            if made.retune:
                self._note("servo_torque_changed", reasons=list(made.reasons), then="re-tune")
            else:
                self._note("servo_torque_as_tuned", change_pct=round(100 * made.relative_change))

    # ---- bench requests (the control socket) -------------------------------------------
    def request(self, name: str, now_s: float) -> tuple[bool, str]:
        """A bench command, decided now against the last cycle's conditions.

        The commands it changes go out with the next cycle (within one period). Every
        request and its answer also goes to the request listeners (the recorder): a
        request changes the core's state between cycles, so replay needs it.
        """
        accepted, message = self._request(name, now_s)
        for listener in self.request_listeners:
            listener("request", name, now_s, accepted, message)
        return accepted, message

    def _request(self, name: str, now_s: float) -> tuple[bool, str]:
        m = self._measured
        speed = m.speed_mps if m is not None and m.speed_mps is not None else 0.0
        before = self.state
        match name:
            case "engage":
                actions = self._apply(EngagePressed(), now_s)
            case "disengage":
                actions = self._apply(ManualOverridePressed(), now_s)
            case "speed_plus":
                actions = self._apply(SpeedPlusPressed(speed), now_s)
            case "speed_minus":
                actions = self._apply(SpeedMinusPressed(speed), now_s)
            case "estop":
                self._bench_estop = True
                actions = self._apply(EStopPressed(), now_s)
            case "estop_reset":
                return self._estop_reset(now_s, "bench")
            case "hold":
                self._bench_hold = True
                return True, "hold-to-move held (bench)"
            case "release":
                self._bench_hold = False
                return True, "hold-to-move released (bench)"
            case _:
                return False, f"unknown request {name!r}; known: {', '.join(BENCH_REQUESTS)}"
        refused = [a for a in actions if isinstance(a, RefuseEngagement)]
        if refused:
            return False, "; ".join(refused[0].reasons)
        if self.state.mode is before.mode and self.state.set_speed_mps == before.set_speed_mps:
            reason = "; ".join(self.state.last_refusal) or f"no effect in {self.state.mode}"
            return False, reason
        if self.state.mode is before.mode:
            return True, f"set speed {self.state.set_speed_mps or 0.0:.2f} m/s"
        return True, f"{before.mode} -> {self.state.mode}"

    def select_route(self, name: str) -> tuple[bool, str]:
        """`dbw route select`: the route the `route` source follows. Refused while under
        automatic control (a route is changed standing, between engagements), and by
        any other source. Told to the request listeners as a request is."""
        accepted, message = self._select_route(name)
        for listener in self.request_listeners:
            listener("select_route", name, None, accepted, message)
        return accepted, message

    def _select_route(self, name: str) -> tuple[bool, str]:
        select = getattr(self.autopilot, "select", None)
        if select is None:
            return False, f"the autopilot source is {self.autopilot.name!r}, not 'route'"
        if self.state.mode in AUTOMATIC_MODES:
            return False, f"cannot change the route in {self.state.mode}: disengage first"
        accepted, message = select(name)
        self._note("route_selected" if accepted else "route_refused", route=name, message=message)
        return bool(accepted), str(message)

    def select_pallet(self, name: str) -> tuple[bool, str]:
        """The tablet's "Select the object": the pallet the `pallet` source goes to.
        Refused while under automatic control, and by any other source. Told to the
        request listeners, so replay selects it at the same place."""
        accepted, message = self._select_pallet(name)
        for listener in self.request_listeners:
            listener("select_pallet", name, None, accepted, message)
        return accepted, message

    def _select_pallet(self, name: str) -> tuple[bool, str]:
        select = getattr(self.autopilot, "select_pallet", None)
        if select is None:
            return False, f"the autopilot source is {self.autopilot.name!r}, not 'pallet'"
        if self.state.mode in AUTOMATIC_MODES:
            return False, f"cannot change the pallet in {self.state.mode}: let go first"
        accepted, message = select(name)
        event = "pallet_selected" if accepted else "pallet_refused"
        self._note(event, pallet=name, message=message)
        return bool(accepted), str(message)

    def maneuver_request(self, action: str, step: str, now_s: float) -> tuple[bool, str]:
        """`dbw calibrate STEP` starts (``start``) or ends (``stop``) the tap on the cycles.
        The tap only reads: the mode machine and the safety layer stay as they are. The
        pedals step also arms (and its stop disarms) the pedal sweep, a source whose
        wishes they judge like any other's; "palm-tree@N" the palm tree driven by the
        daemon from its arc N (plain "palm-tree" is the one by hand, only tapped). Told
        to the request listeners, so replay taps the same cycles and runs the same
        programs."""
        # "pedals@N": the sweep resumed from its run N (the step's name as the tap knows it
        # before the @; the whole text is what the recorder keeps, so replay resumes too).
        base, resumed, run_text = step.partition("@")
        programs = self.programs
        if action == "start":
            refusal = None
            if programs.drives(base, bool(resumed)):
                speed = None if self._measured is None else self._measured.speed_mps
                refusal = programs.refusal(base, bool(resumed), run_text, self.state.mode, speed)
            elif base == "lookahead":
                refusal = tuning_refusal(self.config, self.autopilot, self.state.mode, run_text)
            elif resumed:
                refusal = (
                    "only the pedal sweep, the look-ahead runs and the palm tree driven by "
                    f"the daemon resume, not {base!r}"
                )
            if refusal is not None:
                accepted, message = False, refusal
            else:
                accepted, message = self.maneuver.start(base, now_s)
            if accepted and base == "lookahead" and isinstance(self.autopilot, RouteAutopilot):
                armed, said = self.autopilot.start_tuning(int(run_text) if resumed else 0)
                message += "; " + said
                if not armed:  # a run past the list's end
                    self.maneuver.stop(now_s)
                    accepted, message = False, said
            if accepted and programs.drives(base, bool(resumed)):
                message += programs.arm(base, run_text)
        elif action == "stop":
            accepted, message = self.maneuver.stop(now_s)
            if accepted and isinstance(self.autopilot, RouteAutopilot):
                message += self.autopilot.stop_tuning(self.state.mode in AUTOMATIC_MODES)
            program = programs.disarm(self.state.mode) if accepted else None
            if program is not None:
                message += f"; the {program.replace('_', ' ')} is disarmed"
                if self.state.mode is Mode.SPEED_HOLD:
                    # However the command ended (done, Ctrl-C, gone), never left to the
                    # speed controller at whatever set speed the operator's + press
                    # locked, nor coasting: a stop on the controller, held at standstill
                    # until the operator takes over (OVERRIDE, a brake tap).
                    self.state = replace(self.state, set_speed_mps=0.0)
                    self._note(program + "_ended", then="stop and hold in speed hold")
                    message += ": stopping and holding; OVERRIDE or a brake tap to take over"
        else:
            accepted, message = False, f"unknown maneuver action {action!r}: start or stop"
        if accepted:
            self._note("maneuver_" + action, step=step, message=message)
        for listener in self.request_listeners:
            listener("maneuver", f"{action}:{step}", now_s, accepted, message)
        return accepted, message

    def engage_blockers(self) -> tuple[str, ...]:
        """Why an engage press would be refused now (empty: it would be accepted), judged
        on the last cycle's conditions. READY means the vehicle is safe to hand over, not
        that every source is up: a PC104 that has just booted reports its command timeout
        until our commands reach it. `dbw status` shows this so the operator knows before
        pressing."""
        mode = self.state.mode
        if mode is not Mode.READY and mode not in AUTOMATIC_MODES:
            return (f"cannot engage from {mode}",)
        return refusal_reasons(self.state, self._conditions)

    def status(self, now_s: float) -> dict[str, Any]:
        document = self._core_status(now_s)
        nearby = getattr(self.autopilot, "nearby", None)
        if nearby is not None:  # the route source: routes near the vehicle, engageable?
            document["routes_nearby"] = nearby()
        pilot = document.get("autopilot")
        for extra in ("route_window", "launcher"):
            method = getattr(self.autopilot, extra, None)
            if method is not None and isinstance(pilot, dict):  # for the operator page
                pilot[extra] = method()
        if self.torque_watch is not None:
            document["servo_torque"] = self.torque_watch.status()
        maneuver = self.maneuver.status()
        if maneuver is not None:
            document["maneuver"] = maneuver
        document.update(self.programs.status())
        pedal = self.commands.last_pedal
        if self.pedals:  # what the throttle/brake speed controller is doing, and why
            # No PC104 on this vehicle: the STOP frame nobody receives is not a command.
            document.get("commands", {}).pop("pc104", None)
            document["pedal_speed"] = (
                None
                if pedal is None
                else {
                    "state": str(pedal.state),
                    "reason": pedal.reason,
                    "reference_speed_mps": round(pedal.reference_speed_mps, 3),
                }
            )
        return document

    def _core_status(self, now_s: float) -> dict[str, Any]:
        return core_status(
            state=self.state,
            mode_since_s=self.mode_since_s,
            measured=self._measured,
            hold_to_move_required=self.config.engagement.hold_to_move,
            last_refusal=self.last_refusal,
            engage_blockers=self.engage_blockers(),
            faults=self.faults,
            last_output=self.last_output,
            now_s=now_s,
            autopilot_name=self.autopilot.name,
            last_wish=self.last_wish,
        )

    # ---- pieces of the cycle -------------------------------------------------------------
    def _apply(self, event: Event, now_s: float) -> list[Action]:
        before = self.state
        after, actions = step(before, event, self._conditions, now_s, self.mode_params)
        self.state = after
        if after.mode is not before.mode:
            self.mode_since_s = now_s
            self._note(
                "mode_changed",
                from_mode=str(before.mode),
                to_mode=str(after.mode),
                cause=type(event).__name__,
            )
            if after.mode in AUTOMATIC_MODES and before.mode not in AUTOMATIC_MODES:
                self.autopilot.reset()
                self.commands.engaged()
            if after.mode is Mode.SPEED_HOLD and before.mode is not Mode.SPEED_HOLD:
                self.commands.speed_hold_entered()
        for action in actions:
            if isinstance(action, RefuseEngagement) and action.reasons != self.last_refusal:
                self._note("engage_refused", reasons=list(action.reasons))
            if isinstance(action, RefuseEngagement):
                self.last_refusal = action.reasons
        if after.last_refusal and after.last_refusal != before.last_refusal:
            self.last_refusal = after.last_refusal  # e.g. an override press refused in ERROR
        return actions

    def _note(self, event: str, **fields: Any) -> None:
        self._notes.append(Note(event, fields))

    def _wish(self, m: Measurements, inputs: ControlInputs, now_s: float) -> AutopilotWish:
        programmed = self.programs.wish(m, now_s, self.state.mode, self._held)
        if programmed is not None:
            return programmed
        engaged = self.state.mode in AUTOMATIC_MODES
        observation = Observation(
            now_s,
            m.speed_mps,
            m.steer_tyre_rad,
            inputs.scans,
            engaged,
            gnss=inputs.gnss,
            gnss_seq=inputs.gnss_seq,
            jobs_done=inputs.jobs_done,
        )
        try:
            return self.autopilot.update(observation)
        except Exception as exc:  # a broken source must not take the safety layer with it
            return AutopilotWish(ready=False, reason=f"{type(exc).__name__}: {exc}")

    def _engage_conditions(
        self,
        stale: tuple[str, ...],
        m: Measurements,
        operator: OperatorInput,
        wish: AutopilotWish,
    ) -> EngageConditions:
        blockers: list[str] = []
        if self.pedals:
            blockers.extend(self._pedal_problems(m, wish).values())
        elif m.pc104_source is not None and m.pc104_source is not ControlSource.AUTOMATIC:
            blockers.append(f"PC104 under {m.pc104_source} control")
        elif not m.pc104_ready:
            blockers.append("PC104 not ready")
        if m.steer_tyre_rad is None and "board.steering" not in stale:
            blockers.append("steering angle unknown (pot outside its calibrated range)")
        if not wish.ready:
            blockers.append(wish.reason or "unknown")
        speed = m.speed_mps
        return EngageConditions(
            fault_active=bool(self.faults.active_faults),
            stale_inputs=stale,
            calibration_valid=self.calibration is not None,
            operator_overriding=operator.steering_override or operator.brake_pedal,
            speed_above_limit=speed is None or abs(speed) > self.config.limits.max_engage_speed_mps,
            source_ready=not blockers,
            source_reason="; ".join(blockers),
        )

    def _self_check(self, stale: tuple[str, ...], m: Measurements, now_s: float) -> None:
        mode = self.state.mode
        if mode is Mode.BOOT:
            self._apply(BootDone(), now_s)
            self.self_check_since_s = now_s
            mode = self.state.mode
        if mode is not Mode.SELF_CHECK:
            return
        problems = self.self_check_problems(stale, m)
        if not problems:
            self._apply(SelfCheckPassed(), now_s)
            self.self_check_since_s = None
            return
        started = self.self_check_since_s if self.self_check_since_s is not None else now_s
        if now_s - started >= self.config.engagement.self_check_timeout_s:
            self._note("self_check_failed", problems=list(problems))
            self._apply(SelfCheckFailed(problems), now_s)

    def self_check_problems(self, stale: tuple[str, ...], m: Measurements) -> tuple[str, ...]:
        problems = [f"no fresh {name}" for name in stale]
        if self.calibration is None:
            problems.append(self.calibration_problem or "calibration missing")
        elif m.steer_tyre_rad is None and "board.steering" not in stale:
            problems.append("steering pot outside its calibrated range")
        return tuple(problems)

    def _fault_conditions(
        self,
        inputs: ControlInputs,
        stale: tuple[str, ...],
        fresh: frozenset[str],
        m: Measurements,
        operator: OperatorInput,
        wish: AutopilotWish,
        now_s: float,
    ) -> dict[str, str]:
        mode = self.state.mode
        if mode in (Mode.BOOT, Mode.SELF_CHECK):
            return {}
        active: dict[str, str] = {}
        if self.state.mode is Mode.ERROR:
            # A failed self-check stays a fault until its problems are gone.
            for fault in self.state.faults:
                if fault.reason.startswith("self-check: ") and self.self_check_problems(stale, m):
                    active[fault.reason] = fault.reason
        for name in stale:
            age = inputs.ages_s.get(name, math.inf)
            limit = self.staleness.age_limits_s[name]
            shown = "never received" if not math.isfinite(age) else f"{age * 1e3:.0f} ms old"
            active[f"stale:{name}"] = f"{name} {shown} (limit {limit * 1e3:.0f} ms)"
        for name, why in inputs.service_faults.items():
            active[f"service:{name}"] = f"critical service {name} {why}"
        steering_engaged = mode in AUTOMATIC_MODES
        active.update(board_faults(inputs, steering_engaged))
        if self.pedals:  # no PC104; the speed loop is ours and needs a speed
            if steering_engaged:
                active.update(self._pedal_problems(m, wish))
        else:
            active.update(pc104_faults(inputs, fresh, actuating=steering_engaged))
            deltas = self.link_deltas.update(
                {"errors": inputs.pc104_link.errors, "good": inputs.pc104_link.good}
            )
            if self.link_budget.update(deltas["errors"], deltas["good"]):
                active["pc104_link_errors"] = (
                    "PC104 link: CRC/counter errors exhausted the budget of "
                    f"{self.link_budget.limit}"
                )
        steering_fresh = {"board.steering", "steering.pot"} <= fresh
        if self.calibration is not None and steering_fresh and self.override.steering_unknown:
            # Fresh telemetry, but the angle cannot be known (pot outside its calibrated
            # range, a non-finite reading): a steering nobody can see is not steered.
            active["steering_unknown"] = "steering angle unknown (pot outside its calibrated range)"
        if self.tracking.update(
            self.commands.last_steer_rad, m.steer_tyre_rad, operator.steering_override, now_s
        ):
            active["steering_tracking"] = (
                "steering does not follow its command (servo torque loss, slip or lost pot)"
            )
        if steering_engaged and not wish.ready:
            active["autopilot_not_ready"] = f"autopilot source: {wish.reason or 'not ready'}"
        if self.system_health is not None and SYSTEM_HEALTH_INPUT in inputs.ages_s:
            # Judged where the daemon monitors the PC (it registers the input); a monitor
            # that stopped reporting is a fault like any stale input.
            system = inputs.system
            active.update(
                system_faults(
                    self.system_health,
                    inputs.ages_s[SYSTEM_HEALTH_INPUT],
                    None if system is None else system.disk_free_mb,
                    None if system is None else system.temperature_c,
                    None if system is None else system.memory_available_mb,
                )
            )
        return active

    def _pedal_problems(self, m: Measurements, wish: AutopilotWish) -> dict[str, str]:
        return pedal_path_problems(m, wish.reverse, self.config.positioning.max_fix_age_s)

    def _operator_events(self, operator: OperatorInput, m: Measurements, now_s: float) -> None:
        if operator.steering_override:
            if self.state.mode in AUTOMATIC_MODES:
                self._note("operator_override", what="steering")
            self._apply(SteeringOverridden(), now_s)
        cab = m.pc104_source is not None and m.pc104_source is not ControlSource.AUTOMATIC
        if cab and self.state.mode in AUTOMATIC_MODES:
            self._note("operator_override", what=f"PC104 under {m.pc104_source} control")
            self._apply(SteeringOverridden(), now_s)
        if operator.brake_pedal and not self._brake_pedal_was:
            if self.state.mode is Mode.SPEED_HOLD:
                self._note("operator_override", what="brake pedal")
            self._apply(BrakeTap(), now_s)
        if operator.throttle_pedal and not self._throttle_pedal_was:
            if self.state.mode is Mode.SPEED_HOLD:
                self._note("operator_override", what="throttle pedal")
            self._apply(ThrottlePedalPressed(), now_s)
        self._brake_pedal_was = operator.brake_pedal
        self._throttle_pedal_was = operator.throttle_pedal

    def _panel_events(self, panel: PanelEvents, m: Measurements, now_s: float) -> None:
        if panel.implausible:
            self._note(
                "panel_counter_implausible", buttons=[str(b.name) for b in panel.implausible]
            )
        speed = m.speed_mps if m.speed_mps is not None else math.nan
        for button in panel.presses:
            if button is Buttons.ENGAGE:
                self._apply(EngagePressed(), now_s)
            elif button is Buttons.SPEED_PLUS:
                self._apply(SpeedPlusPressed(speed if math.isfinite(speed) else 0.0), now_s)
            elif button is Buttons.SPEED_MINUS:
                self._apply(SpeedMinusPressed(speed if math.isfinite(speed) else 0.0), now_s)
            elif button is Buttons.MANUAL_OVERRIDE:
                if self.state.mode is Mode.ESTOP:
                    self._estop_reset(now_s, "panel")
                else:
                    self._apply(ManualOverridePressed(), now_s)

    def _tablet_events(self, inputs: ControlInputs, m: Measurements, now_s: float) -> bool:
        """The tablet's hold button (Kinouchi et al., Fig. 6) as the panel's: a press
        engages (ENGAGE) and, engaged, lets the source set the speed (SPEED+ at the
        measured speed); held, it is ENGAGE held for hold-to-move. Nothing else: the
        mode machine refuses what it would refuse the panel. Held only until its last
        beat's time runs out, whatever the page last said."""
        tablet = inputs.tablet
        held = tablet is not None and tablet.held and now_s <= tablet.until_s
        if held and not self._tablet_held:
            if self.state.mode is Mode.READY:
                self._apply(EngagePressed(), now_s)
            if self.state.mode is Mode.ENGAGED:
                speed = m.speed_mps if m.speed_mps is not None else math.nan
                self._apply(SpeedPlusPressed(speed if math.isfinite(speed) else 0.0), now_s)
            self._note("tablet_pressed", now_in=str(self.state.mode))
        elif self._tablet_held and not held:
            self._note("tablet_released")
        self._tablet_held = held
        return held

    def _estop_reset(self, now_s: float, by: str) -> tuple[bool, str]:
        """The reset procedure: the mushroom twisted out, then the override button."""
        if self.state.mode is not Mode.ESTOP:
            return False, f"no e-stop to reset (mode {self.state.mode})"
        m = self._measured
        if m is None or not m.panel_fresh:
            # Deny by default: with the panel silent the mushroom may still be down.
            return False, "e-stop release not seen: the operator panel is silent"
        if m.estop_reasons:
            return False, "e-stop still active: " + "; ".join(m.estop_reasons)
        self._bench_estop = False
        self._apply(EStopReset(), now_s)
        self._note("estop_reset", by=by, to_mode=str(self.state.mode))
        return True, f"e-stop reset -> {self.state.mode}"


__all__ = ["BENCH_REQUESTS", "ControlCore", "CoreOutput", "Note"]
