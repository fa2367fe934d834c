"""The palm tree driven by the daemon, through the whole control core: armed only where the
vehicle file allows it, under hold-to-move, standing in READY; its arcs driven only in
SPEED_HOLD with the engage button held; letting go stops the vehicle; a stop request
leaves it standing with the wheel where it was; a restart disarms.

On :class:`~tests.unit.core.test_pedals_path.PedalBench` (the pedals path, fake time, a
hand-written plant whose wheel follows the servo).
"""

from __future__ import annotations

import itertools
import math
from typing import Any

from appliance.config.models import VehicleConfig
from appliance.core.core import ControlCore
from appliance.guidance.palm_tree_drive import DrivePhase
from appliance.modes import Mode
from drivers.actuators.messages import Buttons
from tests.unit.core.test_pedals_path import CONFIG, PedalBench, bench, brake_pct, throttle_pct
from tests.unit.core.vehicle import SIM_CALIBRATION


def palm_config(**drive: Any) -> VehicleConfig:
    data = CONFIG.model_dump(mode="json")
    data["engagement"] |= {"hold_to_move": True, "hold_to_move_stop_distance_m": 2.0}
    data["palm_tree_drive"] = {"allowed": True, "arc_m": 8.0} | drive
    return VehicleConfig.model_validate(data)


PALM = palm_config()


def armed(core: ControlCore, vehicle: PedalBench, arc: int = 0) -> str:
    accepted, message = core.maneuver_request("start", f"palm-tree@{arc}", vehicle.now_s)
    assert accepted, message
    assert core.programs.palm is not None and "armed" in message
    return message


def held_in_speed_hold(core: ControlCore, vehicle: PedalBench) -> None:
    vehicle.hold_button(Buttons.ENGAGE, True)
    assert vehicle.step(core).mode is Mode.ENGAGED
    vehicle.press(Buttons.SPEED_PLUS)
    assert vehicle.step(core).mode is Mode.SPEED_HOLD


def phase(core: ControlCore) -> DrivePhase | None:
    return (
        None
        if core.programs.palm is None or core.programs.palm.last is None
        else core.programs.palm.last.phase
    )


def test_armed_only_where_allowed_under_hold_to_move_standing_in_ready() -> None:
    core, vehicle = bench()  # the plain pedals vehicle: not allowed
    accepted, message = core.maneuver_request("start", "palm-tree@0", vehicle.now_s)
    assert not accepted and "does not allow" in message and "hold-to-move" in message
    assert core.maneuver.step is None  # nothing tapped either
    accepted, message = core.maneuver_request("start", "palm-tree", vehicle.now_s)
    assert accepted and core.programs.palm is None  # by hand: only tapped, whatever the file says
    core, vehicle = bench(PALM)
    for step in ("palm-tree@7", "palm-tree@x", "palm-tree@"):
        accepted, message = core.maneuver_request("start", step, vehicle.now_s)
        assert not accepted and "resumes from an arc 0..6" in message, message
    vehicle.speed_mps = 1.0
    vehicle.step(core)
    accepted, message = core.maneuver_request("start", "palm-tree@0", vehicle.now_s)
    assert not accepted and "starts standing" in message
    vehicle.speed_mps = 0.0
    held_in_speed_hold(core, vehicle)
    accepted, message = core.maneuver_request("start", "palm-tree@0", vehicle.now_s)
    assert not accepted and "from READY, not speed_hold" in message
    uncalibrated = ControlCore(PALM, None)
    accepted, message = uncalibrated.maneuver_request("start", "palm-tree@0", 0.0)
    assert not accepted and "pot-map first" in message


def test_every_arc_at_its_wheel_angle_driven_only_with_the_button_held() -> None:
    core, vehicle = bench(PALM)
    message = armed(core, vehicle)
    assert "arc 1 of 7" in message
    targets = core.programs.palm.program.params.wheel_targets_rad if core.programs.palm else ()
    assert targets[0] > 2.5 * math.pi and targets[-1] < -2.5 * math.pi
    for out in vehicle.run(core, 1.0):  # READY: armed, but nothing is the program's
        assert out.mode is Mode.READY and not out.throttle.enable
    held_in_speed_hold(core, vehicle)
    moving_wheels: list[float] = []
    speeds: list[float] = []
    while phase(core) is not DrivePhase.DONE:
        out = vehicle.step(core)
        assert out.mode is Mode.SPEED_HOLD, out.mode
        assert not (throttle_pct(out) > 0.0 and brake_pct(out) > 0.0)
        if vehicle.speed_mps > 0.05:
            moving_wheels.append(vehicle.wheel_rad)
            speeds.append(vehicle.speed_mps)
        assert vehicle.now_s < 400.0, phase(core)
    # Every metre driven at one of the held angles (the wheel turned standing), all of
    # them driven, at walking pace; at the end the wheel centred and the vehicle held.
    tolerance = PALM.palm_tree_drive.wheel_tolerance_rad + 0.01
    for wheel in moving_wheels:
        assert min(abs(wheel - t) for t in targets) <= tolerance
    for target in targets:
        assert any(abs(wheel - target) <= tolerance for wheel in moving_wheels)
    assert max(speeds) < PALM.palm_tree_drive.speed_mps * 1.15
    assert vehicle.distance_m > len(targets) * 8.0
    vehicle.run(core, 2.0)
    assert vehicle.speed_mps == 0.0 and abs(vehicle.wheel_rad) < tolerance
    assert brake_pct(vehicle.step(core)) > 0.0
    samples = core.maneuver.samples_since(0, 100_000)["samples"]
    assert samples[-1]["palm_phase"] == "done" and samples[-1]["palm_arc"] == len(targets)
    assert core.status(vehicle.now_s)["palm_tree"]["phase"] == "done"


def test_letting_go_stops_and_holding_again_drives_the_rest_of_the_arc() -> None:
    core, vehicle = bench(PALM)
    armed(core, vehicle)
    held_in_speed_hold(core, vehicle)
    while core.programs.palm is not None and core.programs.palm.program.driven_m < 3.0:
        vehicle.step(core)
        assert vehicle.now_s < 60.0
    vehicle.hold_button(Buttons.ENGAGE, False)
    # The cycle that sees the button up stops on the controller (the program judged on
    # the state the cycle began in, as every source; it pauses from the next).
    out = vehicle.step(core)
    assert out.speed_setpoint_mps is not None and out.speed_setpoint_mps < 1.0
    vehicle.step(core)
    assert phase(core) is DrivePhase.PAUSED
    vehicle.run(core, 6.0)
    assert vehicle.speed_mps == 0.0
    start = vehicle.distance_m
    driven = core.programs.palm.program.driven_m if core.programs.palm else math.nan
    vehicle.hold_button(Buttons.ENGAGE, True)
    while phase(core) is not DrivePhase.STOP:
        vehicle.step(core)
        assert vehicle.now_s < 120.0
    assert core.programs.palm is not None and core.programs.palm.program.arc == 0
    assert vehicle.distance_m - start < 8.0 - driven + 0.2  # the rest, not a whole arc


def test_a_stop_request_stands_with_the_wheel_where_it_was_and_a_restart_disarms() -> None:
    core, vehicle = bench(PALM)
    armed(core, vehicle)
    held_in_speed_hold(core, vehicle)
    while phase(core) is not DrivePhase.DRIVE or vehicle.speed_mps < 0.8:
        vehicle.step(core)
        assert vehicle.now_s < 60.0
    wheel = vehicle.wheel_rad
    accepted, message = core.maneuver_request("stop", "palm-tree", vehicle.now_s)
    assert accepted and "disarmed" in message and "stopping and holding" in message
    assert core.programs.palm is None and core.state.set_speed_mps == 0.0
    outs = vehicle.run(core, 6.0)
    assert all(out.mode is Mode.SPEED_HOLD and out.speed_setpoint_mps == 0.0 for out in outs)
    throttles = [throttle_pct(out) for out in outs]
    assert all(b <= a for a, b in itertools.pairwise(throttles))  # let off
    assert throttles[50] == 0.0
    assert vehicle.speed_mps == 0.0 and abs(vehicle.wheel_rad - wheel) < 0.06
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    vehicle.run(core, 0.1)
    assert core.state.mode is Mode.READY and core.programs.ended_wish is None
    core, vehicle = bench(PALM)
    armed(core, vehicle)
    core.reset()  # the supervisor restarted the control service
    assert core.programs.palm is None
    vehicle.run(core, 0.5)
    assert core.maneuver.samples_since(0, 10_000)["samples"][-1]["palm_phase"] is None


def test_engaging_holds_the_wheel_and_the_program_turns_it_through_the_calibration() -> None:
    """Engaged without the program having the vehicle, the wheel stays where it is (no
    swing to a lock on the engage press); in speed hold, button held, it turns at the
    program's pace, the tyre angle wished being the calibration's for the wheel angle
    the program aims at (the servo is aimed back at exactly that)."""
    core, vehicle = bench(PALM)
    armed(core, vehicle)
    vehicle.hold_button(Buttons.ENGAGE, True)
    for out in vehicle.run(core, 2.0):
        assert out.mode is Mode.ENGAGED
    assert abs(vehicle.wheel_rad) < 0.01
    vehicle.press(Buttons.SPEED_PLUS)
    vehicle.run(core, 1.0)
    palm, wish = core.programs.palm, core.last_wish
    assert palm is not None and palm.last is not None and wish is not None
    aim = palm.last.wheel_aim_rad
    assert 0.5 < aim < PALM.palm_tree_drive.steer_rate_rad_per_s * 1.0 + 1e-9
    assert math.isclose(SIM_CALIBRATION.wheel_rad_from_tyre(wish.steer_tyre_rad), aim)
