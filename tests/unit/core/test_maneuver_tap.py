"""The calibration maneuvers' tap in the core: it reads every cycle, changes none.

Checked on the bench vehicle: the samples carry the raw pot counts the bench sends (an
independent computation of the same counts), the tap never alters a command, requests
go to the recorder's listeners, and the ring reports exactly what a slow client lost.
"""

from __future__ import annotations

import dataclasses

from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.core.core import ControlCore
from appliance.core.maneuver_tap import STEPS, ManeuverTap
from drivers.actuators.messages import Buttons
from tests.unit.core.vehicle import SIM_CALIBRATION, BenchVehicle

CONFIG = load_config("sim")


def test_tapped_samples_are_the_cycles_readings_and_the_commands_are_unchanged() -> None:
    tapped, plain = ControlCore(CONFIG, SIM_CALIBRATION), ControlCore(CONFIG, SIM_CALIBRATION)
    one, two = BenchVehicle(), BenchVehicle()
    one.step(tapped)
    two.step(plain)
    assert tapped.maneuver_request("start", "pot-map", one.now_s) == (
        True,
        "tapping pot-map from sample 0",
    )
    for wheel_tyre_rad in (0.0, 0.05, -0.1, 0.2):
        for vehicle in (one, two):
            vehicle.hold_wheel(wheel_tyre_rad)
        for _ in range(20):
            out_tapped, out_plain = one.step(tapped), two.step(plain)
            fields = dataclasses.asdict(out_tapped)
            plain_fields = dataclasses.asdict(out_plain)
            fields.pop("notes"), plain_fields.pop("notes")
            assert fields == plain_fields
    reply = tapped.maneuver.samples_since(0, 200)
    samples = reply["samples"]
    assert len(samples) == 80 and reply["next"] == 80 and reply["missed"] == 0
    assert [s["seq"] for s in samples] == list(range(80))
    last = samples[-1]
    assert last["pot_counts"] == one.inputs().steering.pot_raw_counts  # type: ignore[union-attr]
    assert last["mode"] == "ready" and last["engaged"] is False
    assert last["steer_setpoint_rad"] is None  # the servo is released: nothing commanded
    assert tapped.status(one.now_s)["maneuver"]["samples"] == 80
    assert tapped.maneuver_request("stop", "pot-map", one.now_s)[0] is True
    one.step(tapped)
    assert tapped.maneuver.samples_since(0, 200)["next"] == 80  # stopped: no more samples


def test_requests_are_told_to_the_listeners_and_refusals_say_why() -> None:
    core = ControlCore(CONFIG, SIM_CALIBRATION)
    told: list[tuple[str, str, bool]] = []
    core.request_listeners.append(lambda kind, name, _t, ok, _m: told.append((kind, name, ok)))
    assert core.maneuver_request("stop", "pot-map", 0.0) == (False, "no maneuver is running")
    accepted, message = core.maneuver_request("start", "warp", 0.0)
    assert not accepted and all(step in message for step in STEPS)
    # This vehicle's PC104 closes its speed loop: no pedals of ours to sweep.
    accepted, message = core.maneuver_request("start", "pedals", 0.0)
    assert not accepted and 'speed_path = "pedals"' in message
    assert core.maneuver_request("start", "k-ratio", 0.0)[0]
    assert core.maneuver_request("start", "pot-map", 0.0) == (
        False,
        "maneuver 'k-ratio' is running: stop it first",
    )
    assert core.maneuver_request("jump", "k-ratio", 0.0)[0] is False
    assert told == [
        ("maneuver", "stop:pot-map", False),
        ("maneuver", "start:warp", False),
        ("maneuver", "start:pedals", False),
        ("maneuver", "start:k-ratio", True),
        ("maneuver", "start:pot-map", False),
        ("maneuver", "jump:k-ratio", False),
    ]


def test_a_fault_and_the_engaged_mode_show_in_the_samples() -> None:
    core, vehicle = ControlCore(CONFIG, SIM_CALIBRATION), BenchVehicle()
    vehicle.step(core)
    core.maneuver_request("start", "palm-tree", vehicle.now_s)
    vehicle.press(Buttons.ENGAGE)
    vehicle.step(core)
    vehicle.unplug("board.steering")
    vehicle.run(core, 1.0)
    samples = core.maneuver.samples_since(0, 200)["samples"]
    assert samples[0]["engaged"] is True
    assert samples[-1]["mode"] == "error" and samples[-1]["pot_counts"] is None
    assert any(key.startswith("stale:") for key in samples[-1]["faults"])


@settings(max_examples=60, deadline=None)
@given(
    ring=st.integers(1, 50),
    cycles=st.integers(0, 120),
    since=st.integers(0, 300),
    limit=st.integers(1, 60),
)
def test_the_ring_returns_what_it_holds_and_counts_what_it_lost(
    ring: int, cycles: int, since: int, limit: int
) -> None:
    """Independent of the core: a fake sample per cycle, seq as the only field read."""
    tap = ManeuverTap(ring_samples=ring)
    tap.start("pedals", 0.0)
    vehicle, core = BenchVehicle(), ControlCore(CONFIG, SIM_CALIBRATION)
    core.maneuver = tap
    for _ in range(cycles):
        vehicle.step(core)
    reply = tap.samples_since(since, limit)
    held = list(range(max(0, cycles - ring), cycles))
    wanted = [seq for seq in held if seq >= since][:limit]
    assert [s["seq"] for s in reply["samples"]] == wanted
    lost = [seq for seq in range(since, cycles) if seq not in held]
    assert reply["missed"] == len(lost)
    assert reply["next"] == (wanted[-1] + 1 if wanted else max(since, held[0] if held else 0))
