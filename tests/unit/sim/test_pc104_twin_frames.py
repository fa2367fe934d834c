"""The PC104 twin's remembered frames are the frames `protocol.encode` makes, always.

`Pc104TwinCore` keeps the frames of a report that repeats (see ``_encode``). Two cores run
the same scenario side by side, one of them encoding every frame afresh, and must put the
same frames on the bus at the same ticks, whatever the commands and faults do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.pc104 import protocol
from drivers.pc104.messages import MotionCommand, MotionPattern, Pc104Message, WheelAngles
from drivers.pc104.twin_core import OutFrame, Pc104TwinCore, TwinFaults

TICK_S = 0.005
PARAMS = VehicleParams.from_config(load_config("sim"))


class FreshlyEncoding(Pc104TwinCore):
    """The reference: `protocol.encode` for every frame, nothing remembered."""

    def _encode(self, message: Pc104Message, counter: int) -> tuple[int, bytes]:
        return protocol.encode(message, counter)


COMMANDS = [
    None,  # the high level is silent
    MotionCommand.stop(),
    MotionCommand(MotionPattern.STRAIGHT, 1.0),
    MotionCommand(MotionPattern.STRAIGHT, -0.5),
    MotionCommand(MotionPattern.COUNTER_STEER, 0.5, front_steer_rad=0.2),
    MotionCommand(MotionPattern.COUNTER_STEER, 0.5, front_steer_rad=-0.0),
    MotionCommand(MotionPattern.STRAIGHT, 0.0, level_platform=True),
]
FAULTS = ["none", "stuck_counter", "bad_crc", "drop_one_in", "delay_s", "cab_control", "bus_off"]

steps = st.lists(
    st.tuples(
        st.sampled_from(COMMANDS),
        st.sampled_from(FAULTS),
        st.integers(1, 80),  # ticks
        st.booleans(),  # restart the controller first
    ),
    min_size=1,
    max_size=8,
)


def _apply(faults: TwinFaults, fault: str) -> None:
    faults.stuck_counter = fault == "stuck_counter"
    faults.bad_crc = fault == "bad_crc"
    faults.drop_one_in = 3 if fault == "drop_one_in" else 0
    faults.delay_s = 0.03 if fault == "delay_s" else 0.0
    faults.cab_control = fault == "cab_control"
    faults.bus_off = fault == "bus_off"


def run_side_by_side(
    scenario: Sequence[tuple[MotionCommand | None, str, int, bool]],
) -> list[list[OutFrame]]:
    cores = []
    for kind in (Pc104TwinCore, FreshlyEncoding):
        world = SimWorld(PARAMS)
        cores.append((kind(world, emit_error_frames=True, seed=3), world))
    sent: list[list[OutFrame]] = []
    tick, counter = 0, 0
    for command, fault, ticks, restart in scenario:
        for core, _ in cores:
            _apply(core.faults, fault)
            if restart:
                core.restart(tick * TICK_S)
        for _ in range(ticks):
            tick += 1
            t_s = tick * TICK_S
            out: list[list[OutFrame]] = []
            for core, world in cores:
                if command is not None and tick % 4 == 0:
                    core.on_frame(*protocol.encode(command, counter), t_s)
                world.advance_to(t_s)
                out.append(core.tick(t_s))
            if command is not None and tick % 4 == 0:
                counter = (counter + 1) % protocol.COUNTER_MODULO
            assert out[0] == out[1], f"tick {tick}: {out[0]} != {out[1]}"
            sent.append(out[0])
    (a, world_a), (b, world_b) = cores
    assert world_a.state == world_b.state
    assert (a.frames_sent, a.stop_required, a.applied_pattern) == (
        b.frames_sent,
        b.stop_required,
        b.applied_pattern,
    )
    return sent


def test_a_standstill_repeats_its_frames_and_they_stay_right() -> None:
    scenario = [(MotionCommand.stop(), "none", 400, False)]  # 2 s: every counter many times
    frames = [f for tick in run_side_by_side(scenario) for f in tick]
    assert len(frames) > 250
    for frame in frames:  # each one is still a valid frame of the contract
        protocol.decode(frame.arbitration_id, frame.data, 0.0)


def test_driving_and_steering_against_fresh_encoding() -> None:
    run_side_by_side(
        [
            (MotionCommand.stop(), "none", 40, False),
            (MotionCommand(MotionPattern.STRAIGHT, 1.0), "none", 200, False),
            (MotionCommand(MotionPattern.COUNTER_STEER, 0.5, 0.2), "stuck_counter", 100, False),
            (None, "bad_crc", 100, False),
            (MotionCommand.stop(), "none", 60, True),
        ]
    )


@settings(max_examples=40, deadline=None)
@given(scenario=steps)
def test_any_scenario_sends_what_fresh_encoding_sends(
    scenario: list[tuple[MotionCommand | None, str, int, bool]],
) -> None:
    run_side_by_side(scenario)


def test_negative_zero_encodes_as_zero() -> None:
    """Why equal messages may share frames: -0.0 == 0.0, and both spell raw 0."""
    plus = WheelAngles((0.0, 0.0, 0.0, 0.0))
    minus = WheelAngles((-0.0, -0.0, -0.0, -0.0))
    assert plus == minus and math.copysign(1.0, minus.row_angles_rad[0]) < 0
    assert protocol.encode(plus, 5) == protocol.encode(minus, 5)
