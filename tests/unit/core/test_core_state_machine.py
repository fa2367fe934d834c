"""The whole control core under random operation: a hypothesis state machine.

Rules do to the bench vehicle what an operator, a flaky cable or a failing board would;
``advance`` runs cycles and checks the safety invariants on every cycle's output. Every
expectation is written from the rule it tests (the override dwell, the e-stop reset
procedure, ...), with the bench vehicle's own bookkeeping, never from the core's state.
Three machines share the rules: with everything that can break, with a healthy vehicle
(so the steps go where operator and autopilot share it), and with hold-to-move.
"""

from __future__ import annotations

import math
from collections import Counter

from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, initialize, precondition, rule

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core.core import BENCH_REQUESTS, ControlCore
from appliance.core.observe import NON_HARDWARE_FAULTS
from appliance.core.output import SAFE_MODES, CoreOutput
from appliance.core.panel import MAX_PRESSES_PER_FRAME
from appliance.modes import AUTOMATIC_MODES, Mode
from drivers.actuators.messages import Buttons, FaultCode, SteeringMode
from drivers.pc104.messages import ControlSource, MotionPattern, Pc104Faults
from tests.unit.core.vehicle import BOARDS, SIM_CALIBRATION, BenchVehicle

CONFIG = load_config("sim")
_data = CONFIG.model_dump()
_data["engagement"] |= {"hold_to_move": True, "max_set_speed_mps": 2.0}
HOLD_TO_MOVE = VehicleConfig.model_validate(_data)  # stops from 2 m/s within its distance
SAFETY = CONFIG.safety
THRESHOLD_RAD = math.radians(SAFETY.steer_override_threshold_deg)
MARGIN_RAD = math.radians(0.05)  # keeps the bookkeeping clear of the threshold's edge
CRITICAL = ControlCore(CONFIG, SIM_CALIBRATION).staleness.critical
HARDWARE_FAULTS = [code for code in FaultCode if code not in NON_HARDWARE_FAULTS]
PRESS_EVENTS = {
    Buttons.ENGAGE: "engage",
    Buttons.SPEED_PLUS: "speed",
    Buttons.SPEED_MINUS: "speed",
    Buttons.MANUAL_OVERRIDE: "override",
}
REQUEST_EVENTS = {
    "engage": "engage",
    "speed_plus": "speed",
    "speed_minus": "speed",
    "estop_reset": "estop_reset",
}


# Rules that break the vehicle (or stop it: the mushroom); a machine without them spends
# its steps where the operator and the autopilot share the vehicle.
trouble = precondition(lambda self: self.TROUBLE)


class CoreMachine(RuleBasedStateMachine):
    TROUBLE = True

    def __init__(self) -> None:
        super().__init__()
        self.core = ControlCore(CONFIG, SIM_CALIBRATION)
        self.vehicle = BenchVehicle()
        self.since_step: set[str] = set()  # presses, requests and restarts since the last cycle
        self.presses: Counter[Buttons] = Counter()  # panel presses since the last cycle
        self.pushing_since_s: float | None = None  # hands on the wheel, from the rule
        self.self_check_passed = False
        self.panel_seen = False  # the decoder has a baseline from the last cycle
        self.mushroom_was_down = False
        self.exercised: Counter[str] = Counter()  # how often each invariant had to hold

    @initialize()
    def first_cycle(self) -> None:
        self.cycle(0.01)

    # ---- the operator --------------------------------------------------------------------
    def _press(self, button: Buttons) -> None:
        self.vehicle.press(button)
        self.since_step.add(PRESS_EVENTS[button])
        self.presses[button] += 1

    @rule()
    def press_engage(self) -> None:
        self._press(Buttons.ENGAGE)

    @rule(button=st.sampled_from([Buttons.SPEED_PLUS, Buttons.SPEED_MINUS]))
    def press_speed(self, button: Buttons) -> None:
        self._press(button)

    @rule()
    def press_override(self) -> None:
        self._press(Buttons.MANUAL_OVERRIDE)

    @rule(down=st.booleans())
    def hold_engage(self, down: bool) -> None:
        if down and not self.vehicle.buttons_down & Buttons.ENGAGE:
            self.since_step.add("engage")  # pushing it down is a press
        self.vehicle.hold_button(Buttons.ENGAGE, down)

    @rule(degrees=st.floats(-25.0, 25.0))
    def hold_wheel(self, degrees: float) -> None:
        self.vehicle.hold_wheel(math.radians(degrees))

    @rule()
    def let_go(self) -> None:
        self.vehicle.let_go()

    @rule(down=st.booleans())
    def brake_pedal(self, down: bool) -> None:
        self.vehicle.brake_pedal(50.0 if down else 0.0)

    @rule(down=st.booleans())
    def throttle_pedal(self, down: bool) -> None:
        self.vehicle.throttle_pedal(50.0 if down else 0.0)

    @trouble
    @rule(down=st.booleans())
    def mushroom(self, down: bool) -> None:
        self.vehicle.estop(down)

    @rule(name=st.sampled_from(BENCH_REQUESTS))
    def request(self, name: str) -> None:
        ok, _ = self.core.request(name, self.vehicle.now_s)
        if ok and name in REQUEST_EVENTS:
            self.since_step.add(f"{REQUEST_EVENTS[name]}_request")

    @rule()
    def restart(self) -> None:
        self.core.reset()
        assert self.core.state.mode is Mode.BOOT
        self.since_step.add("reset")

    # ---- the vehicle ----------------------------------------------------------------------
    @trouble
    @rule(name=st.sampled_from(CRITICAL), health=st.sampled_from(["stale", "unplugged", "fresh"]))
    def input_health(self, name: str, health: str) -> None:
        if health == "stale":
            self.vehicle.make_stale(name)
        elif health == "unplugged":
            self.vehicle.unplug(name)
        else:
            self.vehicle.make_fresh(name)

    @trouble
    @rule(board=st.sampled_from(BOARDS), code=st.sampled_from([*HARDWARE_FAULTS, None]))
    def board_fault(self, board: str, code: FaultCode | None) -> None:
        if code is None:
            self.vehicle.board_faults.pop(board, None)
        else:
            self.vehicle.board_fault(board, code)

    @trouble
    @rule(cab=st.booleans())
    def cab_control(self, cab: bool) -> None:
        self.vehicle.pc104_source = ControlSource.CAB if cab else ControlSource.AUTOMATIC

    @trouble
    @rule(fault=st.booleans())
    def pc104_fault(self, fault: bool) -> None:
        self.vehicle.pc104_faults = Pc104Faults(hydraulic=fault)

    @trouble
    @rule(errors=st.integers(1, SAFETY.pc104_error_budget_limit))
    def link_errors(self, errors: int) -> None:
        self.vehicle.bump_link_errors(errors)

    @trouble
    @rule(trouble=st.sampled_from(["broken_pot", "torque_loss", None]))
    def steering_trouble(self, trouble: str | None) -> None:
        self.vehicle.pot_counts = 4095 if trouble == "broken_pot" else None
        self.vehicle.torque_loss = trouble == "torque_loss"

    @trouble
    @rule()
    def repair(self) -> None:
        """Every cable plugged in, every board healthy, the PC104 back in AUTOMATIC."""
        vehicle = self.vehicle
        vehicle.stale.clear()
        vehicle.unplugged.clear()
        vehicle.board_faults.clear()
        vehicle.pot_counts = None
        vehicle.torque_loss = False
        vehicle.pc104_source = ControlSource.AUTOMATIC
        vehicle.pc104_faults = Pc104Faults()

    # ---- one cycle and its invariants -----------------------------------------------------
    @rule(dt_s=st.floats(0.01, 0.3), cycles=st.integers(1, 20))
    def advance(self, dt_s: float, cycles: int) -> None:
        for _ in range(cycles):
            self.cycle(dt_s)

    def cycle(self, dt_s: float) -> None:
        vehicle = self.vehicle
        before = vehicle.last
        before_mode = Mode.BOOT if "reset" in self.since_step or before is None else before.mode
        if "reset" in self.since_step:
            self.self_check_passed = self.panel_seen = False
        out = vehicle.step(self.core, dt_s)
        happened, self.since_step = self.since_step, set()
        override_presses, self.presses = self.presses[Buttons.MANUAL_OVERRIDE], Counter()
        seen = self.panel_seen and self.fresh("board.panel")  # the decoder has a baseline
        if seen and 1 <= override_presses <= MAX_PRESSES_PER_FRAME:  # a person's presses
            happened.add("override_seen")
        self.check_commands(out)
        self.check_operator_wins(out, before, happened)
        self.check_faults_are_safe(out)
        self.check_estop(out, before_mode, happened)
        self.check_no_automatic_engagement(out, before_mode, happened)
        if out.mode in (Mode.READY, *AUTOMATIC_MODES):
            self.self_check_passed = True
        self.panel_seen = self.fresh("board.panel")
        self.mushroom_was_down = bool(vehicle.buttons_down & Buttons.ESTOP)

    def fresh(self, name: str) -> bool:
        return name not in self.vehicle.stale and name not in self.vehicle.unplugged

    def check_commands(self, out: CoreOutput) -> None:
        assert out.throttle.enable is False  # the PC104 drives: never a throttle actuator
        if out.mode not in AUTOMATIC_MODES:
            self.exercised["released_unless_engaged"] += 1
            assert out.steering.mode is SteeringMode.RELEASE
            assert out.pc104.pattern is MotionPattern.STOP
        assert out.brake.enable is (out.mode in SAFE_MODES)
        if out.brake.enable:
            assert out.brake.position_pct > 0.0
        if out.mode is Mode.ESTOP:
            assert out.brake.position_pct == CONFIG.limits.brake_max_pct

    def check_operator_wins(
        self, out: CoreOutput, before: CoreOutput | None, happened: set[str]
    ) -> None:
        vehicle = self.vehicle
        commanded = None if before is None or "reset" in happened else before.steer_tyre_rad
        steering_seen = self.fresh("board.steering") and self.fresh("steering.pot")
        measured = vehicle.pot_tyre_rad if steering_seen else None
        pushing = (
            commanded is not None
            and measured is not None
            and abs(measured - commanded) > THRESHOLD_RAD + MARGIN_RAD
            and vehicle.torque_nm >= SAFETY.steer_override_min_torque_nm
        )
        if not pushing:
            self.pushing_since_s = None
        elif self.pushing_since_s is None:
            self.pushing_since_s = out.now_s
        held_long = (
            self.pushing_since_s is not None
            and out.now_s - self.pushing_since_s >= SAFETY.steer_override_dwell_s
        )
        if before is not None and before.mode in AUTOMATIC_MODES:
            self.exercised["hands_on_wheel"] += held_long
            self.exercised["override_press"] += "override_seen" in happened
        if held_long or "override_seen" in happened:
            assert out.steering.mode is SteeringMode.RELEASE
            assert out.mode not in AUTOMATIC_MODES
        foot_pct = vehicle.brake_foot_pct - vehicle.brake_actuator_pct
        if foot_pct > SAFETY.pedal_override_margin_pct + 1e-6:
            self.exercised["brake_pedal"] += before is not None and before.mode is Mode.SPEED_HOLD
            assert out.mode is not Mode.SPEED_HOLD

    def check_faults_are_safe(self, out: CoreOutput) -> None:
        vehicle = self.vehicle
        stale = [name for name in CRITICAL if not self.fresh(name)]
        hardware = [
            board
            for board, code in vehicle.board_faults.items()
            if f"board.{board}" not in vehicle.unplugged and code not in NON_HARDWARE_FAULTS
        ]
        if self.fresh("pc104.status") and vehicle.pc104_faults.any:
            hardware.append("pc104")
        if not (stale or hardware):
            return
        self.exercised["fault"] += self.self_check_passed
        if stale or self.self_check_passed:
            assert out.mode in SAFE_MODES
        if self.self_check_passed:
            assert out.mode in (Mode.ERROR, Mode.ESTOP), (stale, hardware)
        if out.mode in SAFE_MODES:
            assert out.brake.enable
            assert out.steering.mode is SteeringMode.RELEASE
            assert out.pc104.pattern is MotionPattern.STOP

    def check_estop(self, out: CoreOutput, before_mode: Mode, happened: set[str]) -> None:
        down = bool(self.vehicle.buttons_down & Buttons.ESTOP)
        if down and "board.panel" not in self.vehicle.unplugged:
            self.exercised["estop_down"] += 1
            assert out.mode is Mode.ESTOP  # seen, however old the panel's frame
        if before_mode is Mode.ESTOP and out.mode is not Mode.ESTOP:
            by_panel = "override_seen" in happened and not down
            by_bench = "estop_reset_request" in happened and not self.mushroom_was_down
            self.exercised["estop_left"] += 1
            assert by_panel or by_bench, happened

    def check_no_automatic_engagement(
        self, out: CoreOutput, before_mode: Mode, happened: set[str]
    ) -> None:
        engage = {"engage", "engage_request"} & happened
        speed = {"speed", "speed_request"} & happened
        if out.mode in AUTOMATIC_MODES and before_mode not in AUTOMATIC_MODES:
            self.exercised["engaged"] += 1
            assert engage, (before_mode, out.mode, happened)
        if out.mode is Mode.SPEED_HOLD and before_mode is not Mode.SPEED_HOLD:
            self.exercised["speed_hold"] += 1
            assert speed, (before_mode, out.mode, happened)


CoreMachine.TestCase.settings = settings(max_examples=400, stateful_step_count=60, deadline=None)
TestCore = CoreMachine.TestCase


class HealthyVehicleMachine(CoreMachine):
    """Nothing breaks: the operator's hands, feet and buttons against the core."""

    TROUBLE = False


HealthyVehicleMachine.TestCase.settings = settings(
    max_examples=400, stateful_step_count=80, deadline=None
)
TestHealthyVehicle = HealthyVehicleMachine.TestCase


class HoldToMoveMachine(CoreMachine):
    """The same invariants with Kinouchi et al.'s hold-to-move guidance."""

    TROUBLE = False

    def __init__(self) -> None:
        super().__init__()
        self.core = ControlCore(HOLD_TO_MOVE, SIM_CALIBRATION)


HoldToMoveMachine.TestCase.settings = settings(
    max_examples=100, stateful_step_count=60, deadline=None
)
TestHoldToMove = HoldToMoveMachine.TestCase


def test_a_scripted_run_exercises_every_invariant() -> None:
    """Random runs reach some invariants rarely; this run makes each of them matter once."""
    machine = CoreMachine()
    machine.first_cycle()
    machine.press_engage()
    machine.advance(0.05, 2)
    machine.press_speed(Buttons.SPEED_PLUS)
    machine.advance(0.05, 2)
    machine.brake_pedal(True)  # in speed hold
    machine.advance(0.05, 2)
    machine.brake_pedal(False)
    machine.hold_wheel(10.0)  # while steering engaged
    machine.advance(0.05, 5)
    machine.let_go()
    machine.press_engage()
    machine.advance(0.05, 2)
    machine.press_override()
    machine.advance(0.05, 2)
    machine.input_health("board.brake", "stale")
    machine.advance(0.05, 2)
    machine.repair()
    machine.mushroom(True)
    machine.advance(0.05, 2)
    machine.mushroom(False)
    machine.press_override()
    machine.advance(0.05, 2)
    machine.restart()
    machine.advance(0.05, 2)
    machine.teardown()
    assert set(machine.exercised) == {
        "released_unless_engaged",
        "hands_on_wheel",
        "override_press",
        "brake_pedal",
        "fault",
        "estop_down",
        "estop_left",
        "engaged",
        "speed_hold",
    }
    assert all(machine.exercised.values()), machine.exercised
