"""ControlCore scenarios on the bench vehicle: what each cycle commands, with fake time.

Each test drives the whole core (staleness, override, faults, mode machine, arbitration,
limits, safe state) through :class:`BenchVehicle` and asserts on the CoreOutput of the
cycle in question: the mode, every actuator command, the heartbeat, the lamps, the notes.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from typing import Any

import pytest

from appliance.config import load_config
from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.core.autopilot import AutopilotSource, AutopilotWish, Observation
from appliance.core.core import ControlCore
from appliance.core.output import CoreOutput
from appliance.modes import Mode
from drivers.actuators.messages import Buttons, FaultCode, Lamps, SteeringMode
from drivers.geometry import Pose2D
from drivers.pc104.messages import (
    ControlSource,
    HighLevelState,
    MotionPattern,
    Pc104Faults,
    PoseState,
    SteeringLoop,
)
from tests.unit.core.vehicle import SIM_CALIBRATION, BenchVehicle

CONFIG = load_config("sim")
SAFETY = CONFIG.safety
ENGAGEMENT = CONFIG.engagement
LIMITS = CONFIG.limits
CAP_MPS = min(ENGAGEMENT.max_set_speed_mps, LIMITS.max_speed_mps)
FAULT_BRAKE_PCT = 100.0 * SAFETY.safe_stop_decel_mps2 / SAFETY.full_brake_decel_mps2
DT_S = 0.01


def configured(**engagement: object) -> VehicleConfig:
    """The sim config with engagement fields changed, validated as a vehicle file would be."""
    data = CONFIG.model_dump()
    data["engagement"] |= engagement
    return VehicleConfig.model_validate(data)


# Hold-to-move must be able to stop from the top set speed within its distance.
HOLD_TO_MOVE = configured(hold_to_move=True, max_set_speed_mps=2.0)


def bench(
    config: VehicleConfig = CONFIG,
    calibration: Calibration | None = SIM_CALIBRATION,
    autopilot: AutopilotSource | None = None,
) -> tuple[ControlCore, BenchVehicle]:
    """A core that has run its first cycle on a healthy bench vehicle."""
    core = ControlCore(config, calibration, autopilot=autopilot)
    vehicle = BenchVehicle()
    vehicle.step(core)
    return core, vehicle


def engaged(config: VehicleConfig = CONFIG) -> tuple[ControlCore, BenchVehicle, CoreOutput]:
    core, vehicle = bench(config)
    vehicle.press(Buttons.ENGAGE)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED
    return core, vehicle, out


def speed_hold(throttle_pct: float = 50.0) -> tuple[ControlCore, BenchVehicle, CoreOutput]:
    """Engaged, driven up on the throttle pedal, + pressed, pedal released."""
    core, vehicle, _ = engaged()
    vehicle.throttle_pedal(throttle_pct)
    vehicle.run(core, 6.0)
    vehicle.press(Buttons.SPEED_PLUS)
    out = vehicle.step(core)
    assert out.mode is Mode.SPEED_HOLD
    vehicle.throttle_pedal(0.0)
    return core, vehicle, vehicle.step(core)


def events(out: CoreOutput, name: str) -> list[dict[str, Any]]:
    return [note.fields for note in out.notes if note.event == name]


def assert_safe(out: CoreOutput) -> None:
    """Throttle released, brake on, steering released, PC104 told to stop."""
    assert out.throttle.enable is False
    assert out.brake.enable is True and out.brake.position_pct > 0.0
    assert out.steering.mode is SteeringMode.RELEASE
    assert out.pc104.pattern is MotionPattern.STOP
    assert out.speed_setpoint_mps is None and out.steer_tyre_rad is None


def assert_released(out: CoreOutput) -> None:
    """READY: everything handed to the operator, our brake off."""
    assert out.throttle.enable is False
    assert out.brake.enable is False
    assert out.steering.mode is SteeringMode.RELEASE
    assert out.pc104.pattern is MotionPattern.STOP


def assert_steering(out: CoreOutput) -> None:
    assert out.steering.mode is SteeringMode.POSITION
    assert out.pc104.pattern is MotionPattern.COUNTER_STEER
    assert out.throttle.enable is False and out.brake.enable is False


# ---- bring-up -----------------------------------------------------------------------------
def test_bring_up_boots_checks_and_is_ready_in_the_first_cycle() -> None:
    core = ControlCore(CONFIG, SIM_CALIBRATION)
    assert core.state.mode is Mode.BOOT
    out = BenchVehicle().step(core)
    assert out.mode is Mode.READY
    changes = [(n["from_mode"], n["to_mode"]) for n in events(out, "mode_changed")]
    assert changes == [("boot", "self_check"), ("self_check", "ready")]
    assert_released(out)
    assert out.hl_state is HighLevelState.STANDBY
    assert (out.panel.lamps, out.panel.display_text) == (Lamps.NONE, "READY")


def test_self_check_waits_for_every_input_with_safe_commands() -> None:
    core = ControlCore(CONFIG, SIM_CALIBRATION)
    vehicle = BenchVehicle()
    vehicle.unplug("scan.left")
    for out in vehicle.run(core, 1.0):
        assert out.mode is Mode.SELF_CHECK
        assert out.hl_state is HighLevelState.INIT
        assert_safe(out)
    vehicle.make_fresh("scan.left")
    assert vehicle.step(core).mode is Mode.READY


def test_without_calibration_self_check_fails_after_its_timeout() -> None:
    core = ControlCore(CONFIG, None, "calibration missing")
    vehicle = BenchVehicle()
    started_s = vehicle.step(core).now_s
    ok, message = core.request("engage", vehicle.now_s)
    assert not ok and "self_check" in message
    out = vehicle.step(core)
    while out.now_s - started_s < ENGAGEMENT.self_check_timeout_s:
        assert out.mode is Mode.SELF_CHECK
        assert_safe(out)
        out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert_safe(out)
    assert events(out, "self_check_failed") == [{"problems": ["calibration missing"]}]
    assert [f.reason for f in core.state.faults] == ["self-check: calibration missing"]
    assert out.panel.display_text.startswith("ERROR self-check: calibration")
    assert out.panel.lamps == Lamps.OVERRIDE | Lamps.WARNING
    assert out.hl_state is HighLevelState.FAULT
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    for out in vehicle.run(core, 2.0):
        assert out.mode is Mode.ERROR  # the calibration is still missing
        assert_safe(out)


# ---- engagement ------------------------------------------------------------------------------
def test_engage_by_panel_press_steers_in_the_same_cycle() -> None:
    _, _, out = engaged()
    assert_steering(out)
    assert out.steer_tyre_rad == pytest.approx(0.0, abs=1e-3)
    assert out.pc104.speed_mps == 0.0
    assert out.hl_state is HighLevelState.ENGAGED
    assert out.panel.lamps == Lamps.ENGAGED
    assert events(out, "mode_changed")[0]["cause"] == "EngagePressed"


def test_engage_by_request_goes_out_with_the_next_cycle() -> None:
    core, vehicle = bench()
    assert core.request("engage", vehicle.now_s) == (True, "ready -> engaged")
    assert_steering(vehicle.step(core))
    assert core.request("engage", vehicle.now_s)[0] is False  # already engaged: no effect
    assert core.request("warp", vehicle.now_s)[0] is False


class NotReadySource:
    name = "route"

    def __init__(self) -> None:
        self.ready = False

    def reset(self) -> None:
        pass

    def update(self, observation: Observation) -> AutopilotWish:
        return AutopilotWish(ready=self.ready, reason="no route loaded")


def _brake_pedal(v: BenchVehicle) -> None:
    v.brake_pedal(30.0)


def _moving(v: BenchVehicle) -> None:
    v.pc104_source = ControlSource.CAB  # the operator drives it up to speed by hand
    v.speed_mps = LIMITS.max_engage_speed_mps + 0.5


def _too_fast(v: BenchVehicle) -> None:
    v.speed_mps = LIMITS.max_engage_speed_mps + 0.5


def _cab(v: BenchVehicle) -> None:
    v.pc104_source = ControlSource.CAB


def _not_ready(v: BenchVehicle) -> None:
    v.pc104_ready = False


REFUSALS: list[tuple[str, Callable[[BenchVehicle], None], str]] = [
    ("brake_pedal", _brake_pedal, "operator overriding"),
    ("speed", _too_fast, "speed above engage limit"),
    ("cab", _cab, "autopilot source not ready: PC104 under cab control"),
    ("pc104_not_ready", _not_ready, "autopilot source not ready: PC104 not ready"),
]


@pytest.mark.parametrize("by", ["panel", "request"])
@pytest.mark.parametrize(("setup", "reason"), [pytest.param(s, r, id=i) for i, s, r in REFUSALS])
def test_engage_is_refused_with_its_reason(
    by: str, setup: Callable[[BenchVehicle], None], reason: str
) -> None:
    core, vehicle = bench()
    setup(vehicle)
    vehicle.step(core)
    if by == "panel":
        vehicle.press(Buttons.ENGAGE)
        out = vehicle.step(core)
        assert any(reason in r for r in events(out, "engage_refused")[0]["reasons"])
    else:
        ok, message = core.request("engage", vehicle.now_s)
        assert not ok and reason in message
        out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert_released(out)
    assert any(reason in r for r in core.last_refusal)
    # The status says so before anyone presses, with the same reason.
    assert any(reason in r for r in core.engage_blockers())
    assert any(reason in r for r in core.status(vehicle.now_s)["engage_blockers"])


def test_engage_blockers_are_empty_exactly_when_a_press_is_accepted() -> None:
    source = NotReadySource()
    core, vehicle = bench(autopilot=source)
    vehicle.step(core)
    assert core.engage_blockers() == ("autopilot source not ready: no route loaded",)
    source.ready = True
    vehicle.step(core)
    assert core.engage_blockers() == ()
    assert core.request("engage", vehicle.now_s)[0]
    vehicle.make_stale("board.brake")
    assert vehicle.step(core).mode is Mode.ERROR
    assert core.engage_blockers() == ("cannot engage from error",)


def test_every_reason_is_named_at_once() -> None:
    core, vehicle = bench()
    _brake_pedal(vehicle)
    _moving(vehicle)
    vehicle.step(core)
    ok, message = core.request("engage", vehicle.now_s)
    assert not ok
    for reason in ("operator overriding", "speed above engage limit", "PC104 under cab"):
        assert reason in message


def test_engage_is_refused_while_the_autopilot_source_is_not_ready() -> None:
    source = NotReadySource()
    core, vehicle = bench(autopilot=source)
    ok, message = core.request("engage", vehicle.now_s)
    assert not ok and "autopilot source not ready: no route loaded" in message
    source.ready = True
    vehicle.step(core)
    assert core.request("engage", vehicle.now_s)[0]
    assert vehicle.step(core).mode is Mode.ENGAGED
    source.ready = False  # lost its route while steering: it cannot steer
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert_safe(out)
    assert events(out, "fault_raised")[0]["fault"] == "autopilot_not_ready"


STALE_BRAKE_REFUSAL = "cannot engage from error (faults: stale:board.brake)"


@pytest.mark.parametrize("by", ["panel", "request"])
def test_engage_with_a_stale_input_is_refused_and_the_input_named(by: str) -> None:
    core, vehicle = bench()
    vehicle.make_stale("board.brake")
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR  # a stale critical input is a fault at once
    if by == "panel":
        vehicle.press(Buttons.ENGAGE)
        vehicle.step(core)
        assert core.last_refusal == (STALE_BRAKE_REFUSAL,)
    else:
        assert core.request("engage", vehicle.now_s) == (False, STALE_BRAKE_REFUSAL)
    assert [f.reason for f in core.state.faults] == ["stale:board.brake"]
    assert core.status(vehicle.now_s)["faults"][0]["detail"].startswith("board.brake 200 ms old")


# ---- speed ----------------------------------------------------------------------------------
def test_engaged_forwards_the_throttle_pedal_to_the_pc104_ramped_and_capped() -> None:
    core, vehicle, _ = engaged()
    for pedal_pct in (50.0, 100.0):
        vehicle.throttle_pedal(pedal_pct)
        previous = vehicle.last.speed_setpoint_mps if vehicle.last else 0.0
        for out in vehicle.run(core, 8.0):
            assert out.mode is Mode.ENGAGED
            assert out.speed_setpoint_mps is not None and previous is not None
            assert out.speed_setpoint_mps - previous <= ENGAGEMENT.max_accel_mps2 * DT_S + 1e-9
            assert out.speed_setpoint_mps <= CAP_MPS * pedal_pct / 100.0 + 1e-9
            assert out.pc104.speed_mps == out.speed_setpoint_mps
            previous = out.speed_setpoint_mps
        assert previous == pytest.approx(CAP_MPS * pedal_pct / 100.0)
    vehicle.throttle_pedal(0.0)
    assert vehicle.step(core).pc104.speed_mps == 0.0  # falling is never limited


class PlanningSource:
    """A source with a pose and a plan, as docking has."""

    name = "plan"

    def __init__(self, pose: Pose2D) -> None:
        self.pose = pose

    def reset(self) -> None:
        pass

    def update(self, observation: Observation) -> AutopilotWish:
        return AutopilotWish(
            ready=True,
            pose=self.pose,
            pose_state=PoseState.OK,
            expected_pose=Pose2D(-6.0, 0.0, math.tau + 0.1),
        )


@pytest.mark.parametrize("loop", ["hl", "pc104"])
def test_the_pose_and_the_plan_go_to_the_pc104_the_plan_only_while_engaged(loop: str) -> None:
    data = CONFIG.model_dump()
    data["docking"]["pose_loop"] = loop
    config = VehicleConfig.model_validate(data)
    source = PlanningSource(Pose2D(-12.0, 0.25, -math.pi - 0.2))
    core, vehicle = bench(config, autopilot=source)
    out = vehicle.step(core)
    assert out.mode is Mode.READY and out.pc104_expected_pose is None
    assert out.pc104_pose is not None and out.pc104_pose.state is PoseState.OK
    assert (out.pc104_pose.x_m, out.pc104_pose.y_m) == (-12.0, 0.25)
    assert out.pc104_pose.yaw_rad == pytest.approx(math.pi - 0.2)  # wrapped into [-pi, pi]
    vehicle.press(Buttons.ENGAGE)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED
    assert out.pc104_expected_pose is not None
    assert out.pc104_expected_pose.loop is SteeringLoop(loop)
    assert out.pc104_expected_pose.yaw_rad == pytest.approx(0.1)
    # A pose the frame cannot carry (40 m from the site's origin) is not sent at all: a
    # PC104 steering on pose stops for it, and the control loop carries on.
    source.pose = Pose2D(40.0, 0.0, 0.0)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED and out.pc104_pose is None
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    out = vehicle.step(core)
    assert out.mode is not Mode.ENGAGED and out.pc104_expected_pose is None


def test_speed_hold_locks_the_measured_speed_then_steps_and_caps() -> None:
    core, vehicle, _ = engaged()
    vehicle.throttle_pedal(50.0)
    vehicle.run(core, 6.0)
    vehicle.press(Buttons.SPEED_PLUS)
    out = vehicle.step(core)
    locked = vehicle.speed_mps  # what the core measured in that cycle
    assert out.mode is Mode.SPEED_HOLD and core.state.set_speed_mps == locked
    assert out.panel.display_text == f"SPEED HOLD {locked:.2f} m/s"
    vehicle.throttle_pedal(0.0)  # letting go of the pedal keeps the speed
    out = vehicle.run(core, 3.0)[-1]
    assert out.mode is Mode.SPEED_HOLD
    assert vehicle.speed_mps == pytest.approx(locked, abs=0.01)
    vehicle.press(Buttons.SPEED_PLUS)
    vehicle.step(core)
    assert core.state.set_speed_mps == pytest.approx(locked + ENGAGEMENT.speed_step_mps)
    vehicle.press(Buttons.SPEED_MINUS)
    vehicle.step(core)
    assert core.state.set_speed_mps == pytest.approx(locked)
    for _ in range(20):
        vehicle.press(Buttons.SPEED_PLUS)
        vehicle.step(core)
    assert core.state.set_speed_mps == CAP_MPS
    previous = vehicle.last.speed_setpoint_mps if vehicle.last else None
    for out in vehicle.run(core, 6.0):
        assert out.speed_setpoint_mps is not None and previous is not None
        assert out.speed_setpoint_mps - previous <= ENGAGEMENT.max_accel_mps2 * DT_S + 1e-9
        previous = out.speed_setpoint_mps
    assert previous == CAP_MPS
    assert core.request("speed_minus", vehicle.now_s)[0]
    assert core.state.set_speed_mps == CAP_MPS - ENGAGEMENT.speed_step_mps


def test_brake_tap_in_speed_hold_hands_back_speed_in_the_same_cycle() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.brake_pedal(40.0)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED
    assert_steering(out)
    assert out.pc104.speed_mps == 0.0
    assert events(out, "operator_override") == [{"what": "brake pedal"}]
    vehicle.brake_pedal(0.0)
    vehicle.press(Buttons.SPEED_PLUS)  # speed hold again, at the speed now
    assert vehicle.step(core).mode is Mode.SPEED_HOLD


def test_throttle_pedal_in_speed_hold_hands_back_speed() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.throttle_pedal(30.0)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED
    assert_steering(out)
    assert out.pc104.speed_mps <= CAP_MPS * 0.3 + 1e-9


def test_speed_press_needs_steering_engaged() -> None:
    core, vehicle = bench()
    vehicle.press(Buttons.SPEED_PLUS)
    assert vehicle.step(core).mode is Mode.READY
    assert core.last_refusal == ("steering not engaged",)


# ---- the operator ---------------------------------------------------------------------------
def test_hands_on_the_wheel_release_steering_in_the_first_cycle_after_the_dwell() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.hold_wheel(math.radians(SAFETY.steer_override_threshold_deg + 3.0))
    first = vehicle.step(core)
    assert first.mode is Mode.SPEED_HOLD
    out = vehicle.step(core)
    while out.now_s - first.now_s < SAFETY.steer_override_dwell_s:
        assert out.mode is Mode.SPEED_HOLD
        assert out.steering.mode is SteeringMode.POSITION
        out = vehicle.step(core)
    assert out.mode is Mode.READY and out.operator.steering_override
    assert_released(out)
    assert events(out, "operator_override") == [{"what": "steering"}]


def test_a_small_push_on_the_wheel_is_not_an_override() -> None:
    core, vehicle, _ = engaged()
    vehicle.hold_wheel(math.radians(SAFETY.steer_tracking_tolerance_deg - 0.5))
    for out in vehicle.run(core, 2.0):
        assert out.mode is Mode.ENGAGED and not out.operator.steering_override


@pytest.mark.parametrize("start", ["engaged", "speed_hold"])
def test_manual_override_press_releases_everything_in_the_same_cycle(start: str) -> None:
    core, vehicle, _ = engaged() if start == "engaged" else speed_hold()
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert_released(out)
    assert events(out, "mode_changed")[0]["cause"] == "ManualOverridePressed"


def test_cab_control_while_engaged_gives_the_vehicle_back() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.pc104_source = ControlSource.CAB
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert_released(out)


# ---- faults ---------------------------------------------------------------------------------
def _stale_steering(v: BenchVehicle) -> None:
    v.make_stale("board.steering")


def _unplugged_pc104(v: BenchVehicle) -> None:
    v.unplug("pc104.status")


def _overcurrent(v: BenchVehicle) -> None:
    v.board_fault("steering", FaultCode.OVERCURRENT)


def _brake_board(v: BenchVehicle) -> None:
    v.board_fault("brake", FaultCode.SUPPLY_UNDERVOLTAGE)


def _pc104_fault(v: BenchVehicle) -> None:
    v.pc104_faults = Pc104Faults(hydraulic=True)


def _link_errors(v: BenchVehicle) -> None:
    v.bump_link_errors(SAFETY.pc104_error_budget_limit)


FAULTS = [
    ("stale_steering", _stale_steering, "stale:board.steering stale:steering.pot"),
    ("unplugged_pc104", _unplugged_pc104, "stale:pc104.status"),
    ("overcurrent", _overcurrent, "board.steering:overcurrent"),
    ("brake_board", _brake_board, "board.brake:supply_undervoltage"),
    ("pc104_faults", _pc104_fault, "pc104:faults"),
    ("link_budget", _link_errors, "pc104_link_errors"),
]
FAULT_PARAMS = [pytest.param(s, k, id=i) for i, s, k in FAULTS]


@pytest.mark.parametrize(("cause", "key"), FAULT_PARAMS)
def test_a_fault_is_safe_in_the_same_cycle(cause: Callable[[BenchVehicle], None], key: str) -> None:
    core, vehicle, _ = speed_hold()
    cause(vehicle)
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert_safe(out)
    assert out.hl_state is HighLevelState.FAULT
    assert out.panel.lamps == Lamps.OVERRIDE | Lamps.WARNING
    assert sorted(n["fault"] for n in events(out, "fault_raised")) == key.split()


def _heal(vehicle: BenchVehicle) -> None:
    vehicle.stale.clear()
    vehicle.unplugged.clear()
    vehicle.board_faults.clear()
    vehicle.pc104_faults = Pc104Faults()


@pytest.mark.parametrize(("cause", "key"), FAULT_PARAMS)
def test_a_fault_is_noted_once_latched_and_cleared_only_by_override(
    cause: Callable[[BenchVehicle], None], key: str
) -> None:
    core, vehicle, _ = engaged()
    cause(vehicle)
    outs = vehicle.run(core, 0.05)
    vehicle.press(Buttons.MANUAL_OVERRIDE)  # while the condition is still there
    outs += vehicle.run(core, 0.05)
    assert core.state.last_refusal[0].startswith("cannot leave error")
    _heal(vehicle)
    outs += vehicle.run(core, 1.0)  # the link budget needs good frames to recover
    assert all(o.mode is Mode.ERROR for o in outs)
    assert all(o.brake.enable and o.steering.mode is SteeringMode.RELEASE for o in outs)
    raised = [n["fault"] for o in outs for n in events(o, "fault_raised")]
    cleared = [n["fault"] for o in outs for n in events(o, "fault_cleared")]
    assert (sorted(raised), sorted(cleared)) == (key.split(), key.split())
    assert outs[-1].panel.display_text == "ERROR cleared: press OVERRIDE"
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    out = vehicle.step(core)
    assert out.mode is Mode.READY  # and never straight back to ENGAGED
    assert_released(out)


def test_a_lower_layer_state_is_not_a_hardware_fault() -> None:
    core, vehicle = bench()
    vehicle.board_fault("steering", FaultCode.COMMAND_TIMEOUT)
    assert vehicle.step(core).mode is Mode.READY


def test_steering_that_stops_following_is_a_fault_after_its_time() -> None:
    core, vehicle = bench()
    vehicle.hold_wheel(math.radians(10.0))
    vehicle.step(core)
    vehicle.let_go()
    vehicle.press(Buttons.ENGAGE)
    commanded = vehicle.step(core).steer_tyre_rad  # starts where the wheels stand
    vehicle.torque_loss = True  # the command ramps to straight ahead, the wheels stay
    tolerance_rad = math.radians(SAFETY.steer_tracking_tolerance_deg)
    off_since_s = None
    for _ in range(200):
        out = vehicle.step(core)
        measured = vehicle.pot_tyre_rad
        assert commanded is not None and measured is not None
        if off_since_s is None and abs(measured - commanded) > tolerance_rad:
            off_since_s = out.now_s
        due = (
            off_since_s is not None
            and out.now_s - off_since_s >= SAFETY.steer_tracking_fault_after_s
        )
        assert (out.mode is Mode.ERROR) is due
        if due:
            break
        commanded = out.steer_tyre_rad
    assert_safe(out)
    assert events(out, "fault_raised")[0]["fault"] == "steering_tracking"


def test_a_wheel_nobody_can_see_is_a_fault_at_once() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.pot_counts = 4095  # wire off: full scale, outside the calibrated range
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert_safe(out)


# ---- e-stop ---------------------------------------------------------------------------------
def test_estop_mushroom_brakes_fully_at_once_and_stays_latched() -> None:
    config = CONFIG.model_copy(update={"limits": LIMITS.model_copy(update={"brake_max_pct": 80.0})})
    core, vehicle = bench(config)
    vehicle.press(Buttons.ENGAGE)
    vehicle.step(core)
    vehicle.estop(True)
    out = vehicle.step(core)
    assert out.mode is Mode.ESTOP and out.brake.position_pct == 80.0
    assert_safe(out)
    assert out.panel.display_text == "E-STOP: release, then OVERRIDE"
    for _ in range(3):
        vehicle.press(Buttons.MANUAL_OVERRIDE)
        assert vehicle.step(core).mode is Mode.ESTOP
    assert core.request("estop_reset", vehicle.now_s)[0] is False
    vehicle.estop(False)
    for out in vehicle.run(core, 1.0):
        assert out.mode is Mode.ESTOP and out.brake.position_pct == 80.0
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert events(out, "estop_reset") == [{"by": "panel", "to_mode": "ready"}]


def test_estop_reset_with_a_fault_goes_to_error() -> None:
    core, vehicle = bench()
    vehicle.estop(True)
    vehicle.step(core)
    vehicle.board_fault("throttle", FaultCode.OVERTEMPERATURE)
    assert vehicle.step(core).mode is Mode.ESTOP
    vehicle.estop(False)
    vehicle.step(core)
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert_safe(out)


def test_estop_by_request_and_reset_by_request() -> None:
    core, vehicle, _ = engaged()
    assert core.request("estop", vehicle.now_s) == (True, "engaged -> estop")
    for out in vehicle.run(core, 0.5):
        assert out.mode is Mode.ESTOP and out.brake.position_pct == LIMITS.brake_max_pct
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ESTOP
    assert core.request("estop_reset", vehicle.now_s) == (True, "e-stop reset -> ready")
    assert vehicle.step(core).mode is Mode.READY


# ---- the safe brake -------------------------------------------------------------------------
def test_fault_brake_ramps_to_the_safe_stop_level() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.board_fault("panel", FaultCode.INTERNAL)
    brake = [o.brake.position_pct for o in vehicle.run(core, 0.5)]
    assert brake[0] > 0.0
    for before, after in itertools.pairwise(brake):
        assert 0.0 <= after - before <= SAFETY.safe_stop_brake_ramp_pct_per_s * DT_S + 1e-9
    assert brake[-1] == pytest.approx(FAULT_BRAKE_PCT)
    rising = [b for b in brake if b < FAULT_BRAKE_PCT - 1e-9]
    assert len(rising) >= FAULT_BRAKE_PCT / (SAFETY.safe_stop_brake_ramp_pct_per_s * DT_S) - 3
    vehicle.estop(True)
    assert vehicle.step(core).brake.position_pct == LIMITS.brake_max_pct


# ---- hold-to-move ---------------------------------------------------------------------------
@pytest.mark.parametrize("lock_speed", [False, True])
def test_hold_to_move_moves_only_while_held_and_stops_in_distance(lock_speed: bool) -> None:
    core, vehicle = bench(HOLD_TO_MOVE)
    vehicle.press(Buttons.ENGAGE)
    vehicle.throttle_pedal(100.0)  # up to the top set speed
    for out in vehicle.run(core, 2.0):
        assert out.mode is Mode.ENGAGED and out.pc104.speed_mps == 0.0
    assert vehicle.speed_mps == 0.0
    vehicle.hold_button(Buttons.ENGAGE, True)
    vehicle.run(core, 6.0)
    if lock_speed:
        vehicle.press(Buttons.SPEED_PLUS)
        vehicle.throttle_pedal(0.0)
        vehicle.run(core, 2.0)
    assert vehicle.last is not None and vehicle.last.mode is (
        Mode.SPEED_HOLD if lock_speed else Mode.ENGAGED
    )
    assert vehicle.speed_mps > 0.9 * HOLD_TO_MOVE.engagement.max_set_speed_mps
    vehicle.hold_button(Buttons.ENGAGE, False)
    released_at_m = vehicle.distance_m
    previous = math.inf
    for out in vehicle.run(core, 5.0):
        assert out.pc104.speed_mps <= previous
        previous = out.pc104.speed_mps
    assert previous == 0.0 and vehicle.speed_mps < 1e-3
    assert (
        vehicle.distance_m - released_at_m <= HOLD_TO_MOVE.engagement.hold_to_move_stop_distance_m
    )


# ---- restart and time -----------------------------------------------------------------------
def test_a_restart_boots_and_never_engages_by_itself() -> None:
    core, vehicle, _ = speed_hold()
    vehicle.press(Buttons.ENGAGE)  # made before the restart: an old press
    vehicle.press(Buttons.SPEED_PLUS)
    core.reset()
    assert core.state.mode is Mode.BOOT and core.last_output is None
    outs = vehicle.run(core, 10.0)
    assert outs[0].mode is Mode.READY
    assert all(o.mode is Mode.READY for o in outs)
    for out in outs:
        assert_released(out)


def test_a_thousand_cycles_at_100_hz_run_faster_than_real_time() -> None:
    core, vehicle, _ = engaged()
    vehicle.throttle_pedal(50.0)
    started = time.perf_counter()
    outs = vehicle.run(core, 10.0)
    elapsed_s = time.perf_counter() - started
    assert len(outs) == 1000
    assert all(b.now_s > a.now_s for a, b in itertools.pairwise(outs))
    assert outs[-1].now_s - outs[0].now_s == pytest.approx(9.99)
    assert all(o.mode is Mode.ENGAGED for o in outs)
    assert elapsed_s < 5.0


class _FullLock:
    """A source wishing the steering far past any lock (a large offset, a short look-ahead)."""

    name = "full_lock"

    def reset(self) -> None:
        pass

    def update(self, observation: Observation) -> AutopilotWish:
        return AutopilotWish(ready=True, steer_tyre_rad=math.radians(80.0))


def test_the_servo_is_never_aimed_past_the_calibrated_pot_range() -> None:
    data = CONFIG.model_dump()
    data["limits"]["max_steer_angle_deg"] = 32.0  # the Husky's: past the pot's range
    wide = VehicleConfig.model_validate(data)
    core, vehicle = bench(wide, autopilot=_FullLock())
    vehicle.press(Buttons.ENGAGE)
    outputs = vehicle.run(core, 3.0)
    high = SIM_CALIBRATION.valid_tyre_range_rad[1]
    assert high < math.radians(32.0)  # the pot's range is what stops it, not the limit
    assert outputs[-1].mode is Mode.ENGAGED
    assert max(o.steer_tyre_rad or 0.0 for o in outputs) == pytest.approx(high, abs=1e-9)
    # The wheel angle that tyre angle aims the servo at: the top of the pot's range.
    top_wheel = SIM_CALIBRATION.valid_wheel_range_rad[1]
    assert SIM_CALIBRATION.wheel_rad_from_tyre(high) == pytest.approx(top_wheel, abs=1e-6)
