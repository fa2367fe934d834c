"""The simulated vehicle's bench: requests checked before they act, replies as plain JSON."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterator
from typing import Any

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.sim.bench import OPS, BenchRequestError, SimBench, parse_request
from appliance.sim.twins.board_set import ActuatorTwins
from appliance.sim.twins.pc104 import Pc104Twin
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.actuators.messages import BrakeCommand, Buttons, SteeringCommand, SteeringMode

SCALARS = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12)
# Small on purpose: a nested strategy inside a dictionary tripped hypothesis' too_slow
# health check once in a census run.
JSON = st.recursive(
    SCALARS,
    lambda children: (
        st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=8), children, max_size=3)
    ),
    max_leaves=8,
)


@pytest.fixture
def bench() -> Iterator[SimBench]:
    world = SimWorld(VehicleParams.from_config(load_config("sim")))
    boards = ActuatorTwins(world)
    pc104 = Pc104Twin(lambda: can.Bus(interface="virtual", channel="bench-unit"), world)
    try:
        yield SimBench(world, boards, pc104, {}, clock=lambda: 12.5)
    finally:
        boards.close()


def handle(bench: SimBench, message: Any) -> dict[str, Any]:
    reply = asyncio.run(bench.handle(message))
    json.dumps(reply, allow_nan=False)  # every reply is strict JSON
    return reply


@settings(max_examples=300, deadline=None)
@given(JSON)
def test_any_json_is_a_request_or_a_bench_request_error(message: Any) -> None:
    try:
        request = parse_request(message)
    except BenchRequestError as exc:
        error = str(exc)
        assert error
    else:
        assert request.op in OPS


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(OPS),
    st.dictionaries(
        st.sampled_from(["button", "pct", "board", "side", "on", "x"]),
        SCALARS | st.lists(SCALARS, max_size=2),
        max_size=4,
    ),
)
def test_known_ops_with_any_fields_never_raise_anything_else(op: str, fields: dict) -> None:
    try:
        parse_request({"op": op, **fields})
    except BenchRequestError as exc:
        error = str(exc)
        assert op in error


@pytest.mark.parametrize(
    ("message", "names"),
    [
        ({"op": "press", "button": "estop"}, "button"),  # the mushroom is `estop`, not a press
        ({"op": "pedal", "pedal": "brake", "pct": 100.5}, "pct"),
        ({"op": "pedal", "pedal": "brake", "pct": float("nan")}, "pct"),
        ({"op": "pedal", "pedal": "brake", "pct": "30"}, "pct"),  # strict: no coercion
        ({"op": "hands", "wheel_rad": 1e9}, "wheel_rad"),
        ({"op": "unplug", "board": "steering", "extra": 1}, "extra"),
        ({"op": "corrupt", "board": "brake", "frames": 0}, "frames"),
        ({"op": "pc104_faults", "drop_all": 1}, "drop_all"),
        ({"op": "hold", "button": "engage"}, "seconds"),
        ({"op": "reboot"}, "unknown op"),
        ({"button": "engage"}, "unknown op"),
        (["observe"], "JSON object"),
    ],
)
def test_bad_requests_name_what_is_wrong_and_change_nothing(
    bench: SimBench, message: Any, names: str
) -> None:
    before = handle(bench, {"op": "observe"})["state"]
    counts = list(bench.boards.panel.press_counts)
    reply = handle(bench, message)
    assert reply["ok"] is False and names in reply["error"], reply
    assert handle(bench, {"op": "observe"})["state"] == before
    assert bench.boards.panel.press_counts == counts
    assert bench.pc104 is not None and not bench.pc104.faults.drop_all


def test_operator_actions_reach_the_twins(bench: SimBench) -> None:
    boards = bench.boards
    assert handle(bench, {"op": "press", "button": "speed_plus"}) == {"ok": True}
    assert boards.panel.press_counts[1] == 1
    handle(bench, {"op": "hold", "button": "engage", "seconds": 0.5})
    assert boards.panel.buttons_down & Buttons.ENGAGE
    handle(bench, {"op": "estop", "pressed": True})
    assert boards.panel.buttons_down & Buttons.ESTOP and boards.brake.estop_active
    handle(bench, {"op": "pedal", "pedal": "throttle", "pct": 25.0})
    assert boards.throttle.operator_pedal_pct == 25.0
    handle(bench, {"op": "pedal", "pedal": "brake", "pct": 40})  # an integer is a number
    assert boards.brake.operator_pedal_pct == 40.0
    handle(bench, {"op": "hands", "wheel_rad": 1.5})
    assert boards.steering._hands_wheel_rad == 1.5
    handle(bench, {"op": "hands", "wheel_rad": None})
    assert boards.steering._hands_wheel_rad is None


def test_the_gear_selector_reverses_the_vehicle_and_the_pc104_still_can(bench: SimBench) -> None:
    world = bench.world
    assert handle(bench, {"op": "gear", "reverse": True}) == {"ok": True}
    assert world.command.reverse
    assert handle(bench, {"op": "gear", "reverse": False}) == {"ok": True}
    assert not world.command.reverse
    world.set_inputs("pc104", reverse=True)  # the PC104's own reverse is not overridden
    assert world.command.reverse
    reply = handle(bench, {"op": "gear", "reverse": "yes"})
    assert not reply["ok"] and "reverse" in reply["error"]


def test_fault_switches_and_cables(bench: SimBench) -> None:
    boards, pc104 = bench.boards, bench.pc104
    assert pc104 is not None
    pc104.faults.stuck_counter = True
    reply = handle(bench, {"op": "pc104_faults", "drop_all": True, "delay_s": 0.05})
    assert reply["pc104_faults"]["drop_all"] is True
    # Switches not named keep their value.
    assert pc104.faults.stuck_counter and pc104.faults.drop_all and pc104.faults.delay_s == 0.05
    handle(bench, {"op": "unplug", "board": "brake"})
    assert not boards.brake.link.plugged
    assert handle(bench, {"op": "observe"})["state"]["brake"]["plugged"] is False
    handle(bench, {"op": "replug", "board": "brake"})
    assert boards.brake.link.plugged
    handle(bench, {"op": "corrupt", "board": "throttle", "frames": 3})
    assert boards.throttle._corrupt_frames == 3
    reply = handle(bench, {"op": "scanner_power", "side": "left", "on": False})
    assert reply == {"ok": False, "error": "this simulated vehicle has no left scanner"}


def test_observe_shows_commands_as_plain_json(bench: SimBench) -> None:
    boards = bench.boards
    boards.steering.command = SteeringCommand(SteeringMode.POSITION, 0.25)
    boards.brake.command = BrakeCommand(enable=True, position_pct=100.0)
    state = handle(bench, {"op": "observe"})["state"]
    assert state["now_s"] == 12.5
    assert state["steering"]["command"] == {
        "mode": "position",
        "wheel_angle_setpoint_rad": 0.25,
        "torque_setpoint_nm": 0.0,
    }
    assert BrakeCommand(**state["brake"]["command"]) == boards.brake.command
    assert state["throttle"]["command"] is None
    assert state["panel"]["lamps"] == [] and state["panel"]["estop"] is False
    assert state["pc104"]["command_pattern"] is None
    assert state["pc104"]["applied_pattern"] == "stop" and state["pc104"]["hl_state"] is None
    assert state["scanners"] == {}


def test_a_vehicle_without_a_pc104_says_so(bench: SimBench) -> None:
    bench.pc104 = None
    assert handle(bench, {"op": "observe"})["state"]["pc104"] is None
    reply = handle(bench, {"op": "pc104_restart"})
    assert reply["ok"] is False and "no PC104" in reply["error"]


def test_the_gnss_antenna_shadowed_and_its_cable_pulled(tmp_path: Any) -> None:
    from appliance.sim.twins.gnss import GnssTwin

    world = SimWorld(VehicleParams.from_config(load_config("sim")))
    boards = ActuatorTwins(world)
    receiver = GnssTwin(str(tmp_path / "gnss"))
    try:
        without = SimBench(world, boards, None, {})
        reply = handle(without, {"op": "gnss_signal", "on": False})
        assert not reply["ok"] and "no GNSS/INS receiver" in reply["error"]
        bench = SimBench(world, boards, None, {}, gnss=receiver)
        assert receiver.update(0.0, 1.0, 2.0, 0.0, 0.0) is not None
        assert handle(bench, {"op": "gnss_signal", "on": False})["ok"]
        epoch = receiver.update(0.1, 1.0, 2.0, 0.0, 0.0)
        assert epoch is not None and epoch.dropout and epoch.writes == ()
        gnss = handle(bench, {"op": "observe"})["state"]["gnss"]
        assert gnss["shadowed"] and gnss["dropped_epochs"] == 1 and gnss["plugged"]
        assert handle(bench, {"op": "gnss_signal", "on": True, "plugged": False})["ok"]
        epoch = receiver.update(0.2, 1.0, 2.0, 0.0, 0.0)
        assert epoch is not None and not epoch.dropout
        assert not handle(bench, {"op": "observe"})["state"]["gnss"]["plugged"]
        assert handle(bench, {"op": "gnss_signal", "plugged": True})["ok"]
        assert receiver.link.plugged
        assert not handle(bench, {"op": "gnss_signal", "on": "no"})["ok"]  # strict
    finally:
        receiver.close()
        boards.close()
