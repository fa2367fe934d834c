"""The ``pedals`` speed path through the whole control core, with fake time.

A vehicle without a PC104 (Stanley et al.'s Husky): its speed is measured by the GNSS/INS
and held by our throttle and brake actuators in SPEED_HOLD. :class:`PedalBench` is the
core's bench vehicle with the PC104 unplugged for good, a GNSS epoch built by hand each
cycle, and a longitudinal plant written out here (the simulated plant's numbers: 1 m/s²
at full throttle, 3 m/s² at full brake, drag 0.05 /s, a 0.4 s traction lag), so speeds
and pedal positions can be checked against figures worked out by hand.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config, parts
from appliance.config.models import VehicleConfig
from appliance.core.autopilot import AutopilotWish, Observation
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs
from appliance.core.observe import gnss_speed_mps
from appliance.core.output import CoreOutput
from appliance.localization.gnss_pose import GnssNoFix, GnssPose, HeadingSource, SigmaSource
from appliance.modes import Mode
from drivers.actuators.messages import Buttons, FaultCode
from drivers.gnss.sentences import FixQuality
from drivers.pc104.messages import ControlSource, MotionPattern, Pc104Faults, Pc104Status
from tests.unit.core.vehicle import SIM_CALIBRATION, BenchVehicle

ACCEL_PER_THROTTLE_PCT = 0.01  # m/s² per % throttle
DECEL_PER_BRAKE_PCT = 0.03  # m/s² per % brake
DRAG_PER_S = 0.05
TRACTION_LAG_S = 0.4
GNSS_LATENCY_S = 0.05  # each epoch is this old when the core sees it
DT_S = 0.02  # the daemon's 50 Hz
TOL = 1e-9


def pedals_config(**engagement: Any) -> VehicleConfig:
    """The sim profile on the pedals path, validated as a vehicle file would be."""
    data = load_config("sim").model_dump(exclude_unset=True)
    data["speed_path"] = "pedals"
    data["engagement"] = data.get("engagement", {}) | engagement
    return VehicleConfig.model_validate(data)


CONFIG = pedals_config()
LIMITS = CONFIG.limits
MAX_FIX_AGE_S = CONFIG.positioning.max_fix_age_s
THROTTLE_STEP_PCT = LIMITS.max_throttle_rate_pct_per_s * DT_S


def gnss_epoch(
    measured_s: float,
    speed_mps: float | None,
    *,
    yaw_rad: float = 0.0,
    course_yaw_rad: float | None = 0.0,
    heading: HeadingSource = HeadingSource.TRUE_HEADING,
) -> GnssPose:
    return GnssPose(
        measurement_time_s=measured_s,
        utc_time_of_day_s=measured_s % 86400.0,
        east_m=0.0,
        north_m=0.0,
        up_m=0.0,
        quality=FixQuality.RTK_FIXED,
        satellites=12,
        hdop=0.8,
        yaw_rad=yaw_rad,
        heading_source=heading,
        course_yaw_rad=course_yaw_rad,
        speed_mps=speed_mps,
        yaw_rate_rad_per_s=0.0,
        sigma_east_m=0.02,
        sigma_north_m=0.02,
        sigma_worst_m=0.02,
        sigma_source=SigmaSource.GST,
    )


class PedalBench(BenchVehicle):
    """The bench vehicle with no PC104: pedals move it, the GNSS/INS measures it."""

    def __init__(self) -> None:
        super().__init__()
        self.unplug("pc104.status")
        self.gnss_lost = False
        self.gnss_age_s = GNSS_LATENCY_S
        self.pc104_status: Pc104Status | None = None  # a stray status, to be ignored
        self.accel_mps2 = 0.0
        self.max_both_pedals = 0.0

    def advance(self, dt_s: float) -> None:
        before, travelled_m = self.speed_mps, self.distance_m
        super().advance(dt_s)  # steering, actuators following their commands, panel
        throttle = max(self.throttle_actuator_pct, self.throttle_foot_pct)
        brake = max(self.brake_actuator_pct, self.brake_foot_pct)
        drive = ACCEL_PER_THROTTLE_PCT * throttle - DRAG_PER_S * before
        self.accel_mps2 += (drive - self.accel_mps2) * (1.0 - math.exp(-dt_s / TRACTION_LAG_S))
        braking = DECEL_PER_BRAKE_PCT * brake * dt_s
        speed = before + self.accel_mps2 * dt_s
        self.speed_mps = max(speed - braking, 0.0) if speed > 0.0 else 0.0
        self.distance_m = travelled_m + 0.5 * (before + self.speed_mps) * dt_s

    def inputs(self, age_limits_s: dict[str, float] | None = None) -> ControlInputs:
        base = super().inputs(age_limits_s)
        gnss = None if self.gnss_lost else gnss_epoch(self.now_s - self.gnss_age_s, self.speed_mps)
        return dataclasses.replace(
            base, gnss=gnss, gnss_seq=self.panel_seq, pc104_status=self.pc104_status
        )

    def step(self, core: ControlCore, dt_s: float = DT_S) -> CoreOutput:
        return super().step(core, dt_s)

    def run(self, core: ControlCore, duration_s: float, dt_s: float = DT_S) -> list[CoreOutput]:
        return super().run(core, duration_s, dt_s)


def throttle_pct(out: CoreOutput) -> float:
    return out.throttle.position_pct if out.throttle.enable else 0.0


def brake_pct(out: CoreOutput) -> float:
    return out.brake.position_pct if out.brake.enable else 0.0


def bench(config: VehicleConfig = CONFIG) -> tuple[ControlCore, PedalBench]:
    core = ControlCore(config, SIM_CALIBRATION)
    vehicle = PedalBench()
    vehicle.step(core)
    return core, vehicle


def speed_hold(at_mps: float = 2.0) -> tuple[ControlCore, PedalBench, list[CoreOutput]]:
    """Engaged, driven up to ``at_mps`` on the operator's foot, + pressed, foot lifted.
    Returns the outputs of ENGAGED, for the checks on the operator's speed."""
    core, vehicle = bench()
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ENGAGED
    vehicle.throttle_pedal(30.0)
    engaged: list[CoreOutput] = []
    while vehicle.speed_mps < at_mps:
        engaged.append(vehicle.step(core))
        assert len(engaged) < 2000
    vehicle.press(Buttons.SPEED_PLUS)
    out = vehicle.step(core)
    assert out.mode is Mode.SPEED_HOLD
    vehicle.throttle_pedal(0.0)
    return core, vehicle, engaged


def refusal(core: ControlCore) -> str:
    return "; ".join(core.engage_blockers())


# ---- configuration ------------------------------------------------------------------------
def test_the_pc104_is_no_critical_input_on_the_pedals_path() -> None:
    pedals = parts.critical_inputs(CONFIG)
    assert "pc104.status" not in pedals
    assert set(parts.critical_inputs(load_config("sim"))) - set(pedals) == {"pc104.status"}
    params = parts.pedal_speed_params(CONFIG)
    assert params.throttle_max_pct <= LIMITS.throttle_max_pct
    assert params.throttle_rise_pct_per_s <= LIMITS.max_throttle_rate_pct_per_s
    assert params.brake_max_pct <= LIMITS.brake_max_pct


def test_ready_without_any_pc104_where_the_pc104_path_waits_for_it() -> None:
    core, vehicle = bench()
    assert vehicle.last is not None and vehicle.last.mode is Mode.READY
    assert "pc104" not in refusal(core).lower()
    flatbed = ControlCore(load_config("sim"), SIM_CALIBRATION)
    other = PedalBench()
    for out in other.run(flatbed, 0.5):
        assert out.mode is Mode.SELF_CHECK  # no PC104 status: stale on that path


# ---- measured speed -----------------------------------------------------------------------
@pytest.mark.parametrize(
    ("epoch", "now_s", "expected"),
    [
        (gnss_epoch(10.0, 2.5), 10.1, 2.5),
        (gnss_epoch(10.0, 2.5), 10.0 + MAX_FIX_AGE_S, 2.5),  # at the limit: still fresh
        (gnss_epoch(10.0, 2.5), 10.0 + MAX_FIX_AGE_S + 1e-3, None),  # just too old
        (gnss_epoch(10.0, 2.5), 9.99, None),  # from the future: a broken clock
        (gnss_epoch(10.0, 2.5), math.nan, None),
        (gnss_epoch(10.0, None), 10.1, None),  # the epoch had no RMC/VTG
        (gnss_epoch(10.0, math.nan), 10.1, None),
        (gnss_epoch(10.0, math.inf), 10.1, None),
        (GnssNoFix(10.0, "no fix"), 10.1, None),
        (None, 10.1, None),
        # Rolling backwards: the course points 180° from the true heading.
        (gnss_epoch(10.0, 0.4, yaw_rad=0.3, course_yaw_rad=0.3 + math.pi), 10.1, -0.4),
        (gnss_epoch(10.0, 0.4, yaw_rad=3.0, course_yaw_rad=-3.0), 10.1, 0.4),  # 0.28 rad off
        # Heading from the course assumes forward travel: nothing to tell backwards by.
        (
            gnss_epoch(
                10.0, 0.4, yaw_rad=0.0, course_yaw_rad=math.pi, heading=HeadingSource.COURSE
            ),
            10.1,
            0.4,
        ),
    ],
)
def test_speed_is_the_fresh_gnss_speed_over_ground(
    epoch: GnssPose | GnssNoFix | None, now_s: float, expected: float | None
) -> None:
    assert gnss_speed_mps(epoch, now_s, MAX_FIX_AGE_S) == expected


def test_unknown_speed_blocks_engagement_and_a_fresh_one_allows_it() -> None:
    core, vehicle = bench()
    vehicle.gnss_lost = True
    vehicle.step(core)
    assert "speed unknown" in refusal(core)
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.READY
    vehicle.gnss_lost = False
    vehicle.gnss_age_s = MAX_FIX_AGE_S + 0.1  # an epoch, but too old
    vehicle.step(core)
    assert "speed unknown" in refusal(core)
    vehicle.gnss_age_s = GNSS_LATENCY_S
    vehicle.step(core)
    assert core.engage_blockers() == ()
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ENGAGED


def test_a_pc104_status_is_ignored_its_faults_and_its_readiness() -> None:
    core, vehicle = bench()
    vehicle.pc104_status = Pc104Status(
        active_pattern=MotionPattern.STOP,
        ready=False,
        control_source=ControlSource.CAB,
        faults=Pc104Faults(command_timeout=True),
        measured_speed_mps=9.0,
    )
    vehicle.make_fresh("pc104.status")
    out = vehicle.step(core)
    assert core.engage_blockers() == ()
    assert core.status(out.now_s)["measured_speed_mps"] == 0.0  # the GNSS's, not 9.0
    vehicle.press(Buttons.ENGAGE)
    for out in vehicle.run(core, 1.0):
        assert out.mode is Mode.ENGAGED
        assert not core.faults.active_faults


# ---- the operator's speed, then ours --------------------------------------------------------
def test_engaged_leaves_both_pedals_to_the_operator() -> None:
    _, _, engaged = speed_hold()
    assert len(engaged) > 50
    for out in engaged:
        assert out.mode is Mode.ENGAGED
        assert not out.throttle.enable and not out.brake.enable
        assert out.speed_setpoint_mps is None


def test_speed_hold_holds_the_locked_speed_on_the_throttle_within_its_limits() -> None:
    core, vehicle, _ = speed_hold(2.0)
    set_mps = core.state.set_speed_mps
    assert set_mps is not None and 2.0 <= set_mps < 2.1
    outs = vehicle.run(core, 25.0)
    previous = 0.0
    for out in outs:
        assert out.mode is Mode.SPEED_HOLD
        assert out.throttle.enable and out.brake.enable
        throttle = throttle_pct(out)
        assert throttle <= LIMITS.throttle_max_pct + TOL
        assert throttle - previous <= THROTTLE_STEP_PCT + TOL
        assert throttle == 0.0 or brake_pct(out) == 0.0
        previous = throttle
    assert abs(vehicle.speed_mps - set_mps) < 0.05
    # Holding speed on the flat is drag alone: 0.05 /s x v / (0.01 m/s² per %).
    assert throttle_pct(outs[-1]) == pytest.approx(DRAG_PER_S * set_mps / 0.01, abs=0.5)


def test_plus_presses_accelerate_within_the_throttle_limit_and_rate() -> None:
    core, vehicle, _ = speed_hold(1.0)
    for _ in range(6):  # one press a cycle
        vehicle.press(Buttons.SPEED_PLUS)
        vehicle.step(core)
    set_mps = core.state.set_speed_mps
    assert set_mps is not None and set_mps == pytest.approx(
        min(2.5, CONFIG.engagement.max_set_speed_mps), abs=0.05
    )
    outs = vehicle.run(core, 30.0)
    rises = [throttle_pct(b) - throttle_pct(a) for a, b in itertools.pairwise(outs)]
    assert max(rises) <= THROTTLE_STEP_PCT + TOL
    assert max(throttle_pct(o) for o in outs) <= LIMITS.throttle_max_pct + TOL
    assert abs(vehicle.speed_mps - set_mps) < 0.05


def test_minus_presses_to_zero_brake_to_a_stop_and_hold_it() -> None:
    core, vehicle, _ = speed_hold(1.0)
    for _ in range(10):
        vehicle.press(Buttons.SPEED_MINUS)
        vehicle.step(core)
    outs = vehicle.run(core, 15.0)
    assert core.state.set_speed_mps == 0.0 and vehicle.speed_mps == 0.0
    assert max(brake_pct(o) for o in outs) > 0.0
    assert all(throttle_pct(o) == 0.0 or brake_pct(o) == 0.0 for o in outs)
    assert throttle_pct(outs[-1]) == 0.0 and brake_pct(outs[-1]) > 0.0  # held, no creeping


# ---- handing back --------------------------------------------------------------------------
@pytest.mark.parametrize("pedal", ["brake", "throttle"])
def test_a_foot_on_a_pedal_releases_our_throttle_in_the_same_cycle(pedal: str) -> None:
    core, vehicle, _ = speed_hold(1.5)
    vehicle.run(core, 3.0)
    assert vehicle.last is not None and throttle_pct(vehicle.last) > 0.0
    if pedal == "brake":
        vehicle.brake_pedal(30.0)
    else:
        vehicle.throttle_pedal(60.0)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED
    assert not out.throttle.enable and not out.brake.enable
    assert out.steering.mode.name == "POSITION"  # steering stays automatic
    assert core.commands.last_pedal is None


def test_speed_hold_entered_again_starts_from_released_pedals() -> None:
    core, vehicle, _ = speed_hold(1.5)
    vehicle.run(core, 3.0)
    vehicle.brake_pedal(30.0)
    vehicle.step(core)
    vehicle.brake_pedal(0.0)
    vehicle.run(core, 1.0)
    vehicle.press(Buttons.SPEED_PLUS)
    out = vehicle.step(core)
    assert out.mode is Mode.SPEED_HOLD
    assert throttle_pct(out) == 0.0  # a reset controller's first cycle moves nothing
    assert throttle_pct(vehicle.step(core)) <= THROTTLE_STEP_PCT + TOL


def test_a_held_foot_at_the_lock_keeps_the_speed_the_operators_until_lifted() -> None:
    core, vehicle = bench()
    vehicle.press(Buttons.ENGAGE)
    vehicle.step(core)
    vehicle.throttle_pedal(30.0)
    while vehicle.speed_mps < 1.5:
        vehicle.step(core)
    vehicle.press(Buttons.SPEED_PLUS)
    for out in vehicle.run(core, 1.0):  # the foot stays on the pedal
        assert out.mode is Mode.SPEED_HOLD
        assert not out.throttle.enable and not out.brake.enable
    vehicle.throttle_pedal(0.0)
    outs = vehicle.run(core, 1.0)
    assert all(o.throttle.enable for o in outs)
    assert throttle_pct(outs[0]) <= THROTTLE_STEP_PCT + TOL  # from 0, at the rate


def test_manual_override_hands_everything_back() -> None:
    core, vehicle, _ = speed_hold(1.5)
    vehicle.run(core, 2.0)
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert not out.throttle.enable and not out.brake.enable


# ---- faults, e-stop, restart -----------------------------------------------------------------
@pytest.mark.parametrize("fault", ["stale_scan", "board_fault", "gnss_lost"])
def test_a_fault_closes_the_throttle_and_brakes_in_the_same_cycle(fault: str) -> None:
    core, vehicle, _ = speed_hold(1.5)
    vehicle.run(core, 3.0)
    assert vehicle.last is not None and throttle_pct(vehicle.last) > 0.0
    if fault == "stale_scan":
        vehicle.make_stale("scan.left")
    elif fault == "board_fault":
        vehicle.board_fault("throttle", FaultCode.OVERCURRENT)
    else:
        vehicle.gnss_lost = True
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR
    assert not out.throttle.enable and throttle_pct(out) == 0.0
    assert out.brake.enable and out.brake.position_pct > 0.0
    if fault == "gnss_lost":
        assert "speed_unknown" in core.faults.active_faults


def test_a_fault_while_braking_never_brakes_less() -> None:
    core, vehicle, _ = speed_hold(2.0)
    for _ in range(10):
        vehicle.press(Buttons.SPEED_MINUS)
        vehicle.step(core)
    braking = 0.0
    for _ in range(500):
        braking = brake_pct(vehicle.step(core))
        if braking > 20.0:
            break
    assert braking > 20.0
    vehicle.make_stale("scan.left")
    outs = vehicle.run(core, 1.0)
    assert outs[0].mode is Mode.ERROR
    assert all(o.brake.position_pct >= braking for o in outs)


def test_estop_is_full_brake_and_no_throttle() -> None:
    core, vehicle, _ = speed_hold(1.5)
    vehicle.run(core, 2.0)
    vehicle.estop(True)
    out = vehicle.step(core)
    assert out.mode is Mode.ESTOP
    assert not out.throttle.enable
    assert out.brake.enable and out.brake.position_pct == LIMITS.brake_max_pct


def test_a_restart_forgets_the_controller() -> None:
    core, vehicle, _ = speed_hold(1.5)
    vehicle.run(core, 2.0)
    assert core.commands.last_pedal is not None
    core.reset()
    assert core.commands.last_pedal is None and core.commands.brake_floor_pct == 0.0
    out = vehicle.step(core)
    assert out.mode is Mode.READY
    assert not out.throttle.enable and not out.brake.enable


# ---- hold-to-move and reverse --------------------------------------------------------------
def test_hold_to_move_release_closes_the_throttle_and_stops() -> None:
    config = pedals_config(hold_to_move=True, max_set_speed_mps=2.0)
    core, vehicle = bench(config)
    vehicle.press(Buttons.ENGAGE)
    vehicle.hold_button(Buttons.ENGAGE, True)
    vehicle.throttle_pedal(30.0)
    while vehicle.speed_mps < 1.0:
        vehicle.step(core)
    vehicle.press(Buttons.SPEED_PLUS)
    vehicle.throttle_pedal(0.0)
    vehicle.run(core, 3.0)
    assert vehicle.last is not None and vehicle.last.mode is Mode.SPEED_HOLD
    assert throttle_pct(vehicle.last) > 0.0
    vehicle.hold_button(Buttons.ENGAGE, False)
    released_at_m = vehicle.distance_m
    outs = vehicle.run(core, 4.0)
    assert throttle_pct(outs[0]) == 0.0 and brake_pct(outs[0]) > 0.0  # at once
    assert all(throttle_pct(o) == 0.0 for o in outs)
    assert vehicle.speed_mps == 0.0
    assert vehicle.distance_m - released_at_m <= config.engagement.hold_to_move_stop_distance_m


class Reversing:
    """A source that wishes to back up when told to."""

    name = "reversing"

    def __init__(self) -> None:
        self.reverse = False

    def reset(self) -> None:
        pass

    def update(self, observation: Observation) -> AutopilotWish:
        return AutopilotWish(ready=True, reverse=self.reverse)


def test_a_reverse_wish_is_refused_and_stops_the_vehicle_when_engaged() -> None:
    source = Reversing()
    core = ControlCore(CONFIG, SIM_CALIBRATION, autopilot=source)
    vehicle = PedalBench()
    vehicle.step(core)
    source.reverse = True
    vehicle.step(core)
    assert "drives forward only" in refusal(core)
    source.reverse = False
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ENGAGED
    source.reverse = True
    out = vehicle.step(core)
    assert out.mode is Mode.ERROR and "reverse_refused" in core.faults.active_faults
    assert not out.throttle.enable and out.brake.enable


# ---- rules over any sequence -------------------------------------------------------------
ACTIONS = st.sampled_from(
    [
        "engage",
        "plus",
        "minus",
        "override",
        "throttle_foot",
        "brake_foot",
        "feet_off",
        "gnss_lost",
        "gnss_back",
        "stale_scan",
        "fresh_scan",
        "estop",
        "estop_release",
        "hold",
        "release",
        "restart",
        "wait",
    ]
)


def act(core: ControlCore, vehicle: PedalBench, action: str) -> None:
    match action:
        case "engage":
            vehicle.press(Buttons.ENGAGE)
        case "plus":
            vehicle.press(Buttons.SPEED_PLUS)
        case "minus":
            vehicle.press(Buttons.SPEED_MINUS)
        case "override":
            vehicle.press(Buttons.MANUAL_OVERRIDE)
        case "throttle_foot":
            vehicle.throttle_pedal(40.0)
        case "brake_foot":
            vehicle.brake_pedal(30.0)
        case "feet_off":
            vehicle.throttle_pedal(0.0)
            vehicle.brake_pedal(0.0)
        case "gnss_lost" | "gnss_back":
            vehicle.gnss_lost = action == "gnss_lost"
        case "stale_scan":
            vehicle.make_stale("scan.right")
        case "fresh_scan":
            vehicle.make_fresh("scan.right")
        case "estop" | "estop_release":
            vehicle.estop(action == "estop")
        case "hold" | "release":
            vehicle.hold_button(Buttons.ENGAGE, action == "hold")
        case "restart":
            core.reset()
        case _:
            pass


@settings(max_examples=60, deadline=None)
@given(
    steps=st.lists(st.tuples(ACTIONS, st.integers(1, 60)), min_size=1, max_size=25),
    hold_to_move=st.booleans(),
)
def test_pedal_rules_hold_for_any_sequence(
    steps: list[tuple[str, int]], hold_to_move: bool
) -> None:
    config = pedals_config(hold_to_move=True, max_set_speed_mps=2.0) if hold_to_move else CONFIG
    core, vehicle = bench(config)
    previous = 0.0
    for action, cycles in steps:
        act(core, vehicle, action)
        for _ in range(cycles):
            out = vehicle.step(core)
            throttle, brake = throttle_pct(out), brake_pct(out)
            assert not (throttle > 0.0 and brake > 0.0)
            assert 0.0 <= throttle <= LIMITS.throttle_max_pct + TOL
            assert 0.0 <= brake <= LIMITS.brake_max_pct + TOL
            assert throttle - previous <= THROTTLE_STEP_PCT + TOL
            if out.mode is not Mode.SPEED_HOLD:
                assert not out.throttle.enable  # ours only in speed hold
            if out.mode in (Mode.ERROR, Mode.ESTOP, Mode.BOOT, Mode.SELF_CHECK):
                assert out.brake.enable and brake > 0.0
            previous = throttle
