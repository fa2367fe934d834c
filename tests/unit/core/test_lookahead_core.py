"""The look-ahead runs through the whole control core: armed by their request on the route
source from READY, their samples in the tap, stopped on the course when the command ends
engaged, disarmed by a restart. On the pedals bench (fake time, a hand-written plant)."""

from __future__ import annotations

from appliance.config import load_config
from appliance.core.route_autopilot import RouteAutopilot
from appliance.modes import Mode
from drivers.actuators.messages import Buttons
from tests.unit.core.test_pedals_path import bench

HUSKY = load_config("husky-sim")


def test_armed_only_on_the_route_source_from_ready() -> None:
    core, vehicle = bench()  # the sim profile: its source holds straight
    vehicle.run(core, 1.0)
    accepted, message = core.maneuver_request("start", "lookahead", vehicle.now_s)
    assert not accepted and 'autopilot_source = "route"' in message
    core, vehicle = bench(HUSKY)
    accepted, message = core.maneuver_request("start", "lookahead@x", vehicle.now_s)
    assert not accepted and "from a run number" in message
    vehicle.run(core, 1.0)
    accepted, message = core.maneuver_request("start", "lookahead@99", vehicle.now_s)
    assert not accepted and "runs 0..35, not 99" in message and not core.maneuver.active
    accepted, message = core.maneuver_request("start", "lookahead@3", vehicle.now_s)
    assert accepted and "armed at run 4 of 36" in message, message


def test_the_runs_lay_their_course_and_a_stop_engaged_holds_on_it() -> None:
    core, vehicle = bench(HUSKY)
    vehicle.run(core, 1.0)
    assert core.maneuver_request("start", "lookahead", vehicle.now_s)[0]
    vehicle.run(core, 1.0)
    assert core.engage_blockers() == ()
    samples = core.maneuver.samples_since(0, 500)["samples"]
    assert {(s["tune_phase"], s["tune_run"]) for s in samples} == {("stand", 0)}
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ENGAGED
    vehicle.run(core, 0.5)
    assert core.last_wish is not None and core.last_wish.status["tuning"]["phase"] == "runup"
    accepted, message = core.maneuver_request("stop", "lookahead", vehicle.now_s)
    assert accepted and "stopping on the tuning course" in message
    source = core.autopilot
    assert isinstance(source, RouteAutopilot) and source.tuning is not None
    assert source.tuning.follower is not None
    course = source.tuning.follower.route_m
    vehicle.run(core, 0.5)
    assert source.tuning.follower.route_m is course  # kept: nothing laid while stopping
    assert core.state.mode is Mode.ENGAGED  # still steering along its course, speed 0
    assert core.last_wish is not None and core.last_wish.max_speed_mps == 0.0
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    vehicle.run(core, 0.2)
    assert source.tuning is None


def test_a_restart_disarms_the_runs() -> None:
    core, vehicle = bench(HUSKY)
    vehicle.run(core, 1.0)
    assert core.maneuver_request("start", "lookahead", vehicle.now_s)[0]
    core.reset()
    source = core.autopilot
    assert isinstance(source, RouteAutopilot) and source.tuning is None
