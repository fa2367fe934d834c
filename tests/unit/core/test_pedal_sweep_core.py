"""The pedal sweep through the whole control core: armed by its request, honoured only in
SPEED_HOLD, taken away by the operator within the cycle, disarmed by a stop or a restart.

On :class:`~tests.unit.core.test_pedals_path.PedalBench` (the pedals path with fake time
and a hand-written longitudinal plant).
"""

from __future__ import annotations

from appliance.config.models import VehicleConfig
from appliance.core.core import ControlCore
from appliance.guidance.pedal_sweep import SweepPhase
from appliance.modes import Mode
from drivers.actuators.messages import Buttons
from tests.unit.core.test_pedals_path import (
    CONFIG,
    PedalBench,
    bench,
    brake_pct,
    pedals_config,
    throttle_pct,
)
from tests.unit.core.vehicle import SIM_CALIBRATION

SWEEP = CONFIG.pedal_sweep


def armed(core: ControlCore, vehicle: PedalBench) -> None:
    accepted, message = core.maneuver_request("start", "pedals", vehicle.now_s)
    assert accepted, message
    assert core.programs.sweeping and "armed" in message


def into_speed_hold(core: ControlCore, vehicle: PedalBench) -> None:
    vehicle.press(Buttons.ENGAGE)
    assert vehicle.step(core).mode is Mode.ENGAGED
    vehicle.press(Buttons.SPEED_PLUS)
    assert vehicle.step(core).mode is Mode.SPEED_HOLD


def test_armed_only_standing_in_ready_on_the_pedals_path() -> None:
    core, vehicle = bench()
    vehicle.press(Buttons.ENGAGE)
    vehicle.step(core)
    accepted, message = core.maneuver_request("start", "pedals", vehicle.now_s)
    assert not accepted and "from READY, not engaged" in message
    assert core.maneuver.step is None  # nothing tapped either
    core, vehicle = bench()
    vehicle.speed_mps = 1.0
    vehicle.step(core)
    accepted, message = core.maneuver_request("start", "pedals", vehicle.now_s)
    assert not accepted and "starts standing" in message
    vehicle.gnss_lost = True
    vehicle.speed_mps = 0.0
    vehicle.step(core)
    accepted, message = core.maneuver_request("start", "pedals", vehicle.now_s)
    assert not accepted and "measured speed" in message


def test_the_sweep_drives_only_in_speed_hold_and_straight_ahead() -> None:
    core, vehicle = bench()
    armed(core, vehicle)
    for out in vehicle.run(core, 1.0):  # READY: armed, but the pedals are the operator's
        assert out.mode is Mode.READY
        assert not out.throttle.enable and not out.brake.enable
    into_speed_hold(core, vehicle)
    throttles = []
    for out in vehicle.run(core, 4.0):
        assert out.mode is Mode.SPEED_HOLD
        assert out.steer_tyre_rad == 0.0
        assert not (throttle_pct(out) > 0.0 and brake_pct(out) > 0.0)
        throttles.append(throttle_pct(out))
    # Standing 1 s on the hold brake, then the first level, reached at the limiter's rate.
    assert (
        core.programs.last_sweep is not None
        and core.programs.last_sweep.phase is SweepPhase.THROTTLE
    )
    assert max(throttles) == SWEEP.throttle_levels_pct[0]
    assert vehicle.speed_mps > 0.3
    sample = core.maneuver.samples_since(0, 10_000)["samples"][-1]
    assert (sample["sweep_phase"], sample["sweep_run"]) == ("throttle", 0)
    assert core.status(vehicle.now_s)["pedal_sweep"]["phase"] == "throttle"


def test_a_brake_tap_takes_the_pedals_within_the_cycle_and_the_run_starts_over() -> None:
    core, vehicle = bench()
    armed(core, vehicle)
    into_speed_hold(core, vehicle)
    vehicle.run(core, 3.0)
    assert (
        core.programs.last_sweep is not None
        and core.programs.last_sweep.phase is SweepPhase.THROTTLE
    )
    vehicle.brake_pedal(30.0)
    out = vehicle.step(core)
    assert out.mode is Mode.ENGAGED
    assert not out.throttle.enable  # in the very cycle the foot came down
    vehicle.brake_pedal(0.0)
    out = vehicle.step(core)
    assert (
        core.programs.last_sweep is not None and core.programs.last_sweep.phase is SweepPhase.PAUSED
    )
    vehicle.press(Buttons.SPEED_PLUS)
    vehicle.step(core)
    out = vehicle.step(core)
    assert out.mode is Mode.SPEED_HOLD
    assert (
        core.programs.last_sweep.phase is SweepPhase.STOPPING and core.programs.last_sweep.run == 0
    )
    assert throttle_pct(out) == 0.0 and brake_pct(out) > 0.0


def test_stopping_the_maneuver_mid_run_stops_and_holds_and_a_restart_disarms() -> None:
    core, vehicle = bench()
    armed(core, vehicle)
    into_speed_hold(core, vehicle)
    vehicle.run(core, 4.0)
    assert vehicle.speed_mps > 0.3  # under way on the first level
    accepted, message = core.maneuver_request("stop", "pedals", vehicle.now_s)
    assert accepted and "disarmed" in message and "stopping and holding" in message
    # Not the set speed the + press locked, nor a coast: a stop on the controller, held.
    assert core.state.mode is Mode.SPEED_HOLD and core.state.set_speed_mps == 0.0
    outs = vehicle.run(core, 10.0)
    assert all(throttle_pct(out) == 0.0 for out in outs)
    assert vehicle.speed_mps == 0.0 and brake_pct(outs[-1]) > 0.0
    assert all(out.mode is Mode.SPEED_HOLD and out.steer_tyre_rad == 0.0 for out in outs)
    assert core.last_wish is not None and core.last_wish.ready  # straight, whatever source
    vehicle.press(Buttons.MANUAL_OVERRIDE)
    vehicle.step(core)
    vehicle.step(core)
    assert core.state.mode is Mode.READY and core.programs.ended_wish is None
    core, vehicle = bench()
    armed(core, vehicle)
    core.reset()  # the supervisor restarted the control service
    assert not core.programs.sweeping
    vehicle.run(core, 1.0)
    assert core.maneuver.active  # the tap goes on: the client sees samples with no sweep
    assert core.maneuver.samples_since(0, 10_000)["samples"][-1]["sweep_phase"] is None


def test_under_hold_to_move_the_sweep_has_the_pedals_only_while_held() -> None:
    data = pedals_config().model_dump()
    data["engagement"] |= {"hold_to_move": True, "max_set_speed_mps": 2.0}
    data["pedal_sweep"] |= {"top_speed_mps": 2.0, "speed_band_edges_mps": (0.5, 1.5)}
    config = VehicleConfig.model_validate(data)
    core = ControlCore(config, SIM_CALIBRATION)
    vehicle = PedalBench()
    vehicle.step(core)
    armed(core, vehicle)
    vehicle.hold_button(Buttons.ENGAGE, True)
    vehicle.step(core)
    vehicle.press(Buttons.SPEED_PLUS)
    vehicle.run(core, 3.0)
    assert core.state.mode is Mode.SPEED_HOLD
    assert (
        core.programs.last_sweep is not None
        and core.programs.last_sweep.phase is SweepPhase.THROTTLE
    )
    vehicle.hold_button(Buttons.ENGAGE, False)
    vehicle.step(core)
    out = vehicle.step(core)
    assert core.programs.last_sweep.phase is SweepPhase.PAUSED
    assert throttle_pct(out) == 0.0 and brake_pct(out) > 0.0  # the controlled stop


def test_a_resumed_sweep_goes_on_from_the_run_it_names() -> None:
    core, vehicle = bench()
    runs = core.programs.sweep.params.runs if core.programs.sweep is not None else 0
    for step, why in (
        (f"pedals@{runs}", f"run 0..{runs - 1}"),
        ("pedals@x", "not 'x'"),
        ("pedals@", "not ''"),
        ("pot-map@1", "the palm tree driven by the daemon resume, not"),
    ):
        accepted, message = core.maneuver_request("start", step, vehicle.now_s)
        assert not accepted and why in message, message
    accepted, message = core.maneuver_request("start", "pedals@2", vehicle.now_s)
    assert accepted and "from run 3" in message
    assert (
        core.maneuver.step == "pedals"
        and core.programs.sweep is not None
        and core.programs.sweep.run == 2
    )
    into_speed_hold(core, vehicle)
    vehicle.run(core, 1.5)
    assert core.programs.last_sweep is not None and core.programs.last_sweep.run == 2
    assert core.programs.last_sweep.phase is SweepPhase.THROTTLE
    assert core.programs.last_sweep.throttle_pct == CONFIG.pedal_sweep.throttle_levels_pct[2 % 3]
