"""The PC104 twin's remembered frames are the frames `protocol` makes and reads, always.

`Pc104TwinCore` keeps the frames of a report that repeats (``_encode``) and the messages of
command frames it has decoded before (``_decode``). Two cores run the same scenario side by
side, one of them encoding and decoding every frame afresh, and must put the same frames on
the bus at the same ticks and count the same bad frames, whatever the commands, the faults
and the frames they are sent (broken ones too) do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.sim.twins.pc104_core import OutFrame, Pc104TwinCore, TwinFaults
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.pc104 import protocol
from drivers.pc104.messages import (
    HighLevelState,
    HlHeartbeat,
    Message,
    MotionCommand,
    MotionPattern,
    Pc104Message,
    WheelAngles,
)

TICK_S = 0.005
PARAMS = VehicleParams.from_config(load_config("sim"))


class FreshlyEncoding(Pc104TwinCore):
    """The reference: `protocol.encode` and `protocol.decode` for every frame."""

    def _encode(self, message: Pc104Message, counter: int) -> tuple[int, bytes]:
        return protocol.encode(message, counter)

    def _decode(self, arbitration_id: int, data: bytes, now_s: float) -> tuple[Message, int]:
        frame = protocol.decode(arbitration_id, data, now_s)
        return frame.message, frame.counter


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
# What the high level sends besides its command: nothing, or one more frame each time.
EXTRAS = ["none", "heartbeat", "bad_crc", "short", "same_counter_again"]
HEARTBEAT = HlHeartbeat(HighLevelState.STANDBY)

steps = st.lists(
    st.tuples(
        st.sampled_from(COMMANDS),
        st.sampled_from(FAULTS),
        st.integers(1, 80),  # ticks
        st.booleans(),  # restart the controller first
        st.sampled_from(EXTRAS),
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


def _frames_in(command: MotionCommand, counter: int, extra: str) -> list[tuple[int, bytes]]:
    frames: list[tuple[int, bytes]] = [protocol.encode(command, counter)]
    arbitration_id, data = frames[0]
    if extra == "heartbeat":
        frames.append(protocol.encode(HEARTBEAT, counter))
    elif extra == "bad_crc":
        frames.append((arbitration_id, data[:-1] + bytes([data[-1] ^ 0x01])))
    elif extra == "short":
        frames.append((arbitration_id, data[:3]))
    elif extra == "same_counter_again":
        frames.append((arbitration_id, data))  # the same frame again: a stuck counter
    return frames


Step = tuple[MotionCommand | None, str, int, bool, str]


def run_side_by_side(scenario: Sequence[Step]) -> list[list[OutFrame]]:
    cores = []
    for kind in (Pc104TwinCore, FreshlyEncoding):
        world = SimWorld(PARAMS)
        cores.append((kind(world, emit_error_frames=True, seed=3), world))
    sent: list[list[OutFrame]] = []
    tick, counter = 0, 0
    for command, fault, ticks, restart, extra in scenario:
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
                    for arbitration_id, data in _frames_in(command, counter, extra):
                        core.on_frame(arbitration_id, data, t_s)
                world.advance_to(t_s)
                out.append(core.tick(t_s))
            if command is not None and tick % 4 == 0:
                counter = (counter + 1) % protocol.COUNTER_MODULO
            assert out[0] == out[1], f"tick {tick}: {out[0]} != {out[1]}"
            sent.append(out[0])
    (a, world_a), (b, world_b) = cores
    assert world_a.state == world_b.state
    assert (a.frames_sent, a.bad_command_frames, a.command) == (
        b.frames_sent,
        b.bad_command_frames,
        b.command,
    )
    assert (a.stop_required, a.applied_pattern) == (b.stop_required, b.applied_pattern)
    assert a.command_monitor.counts == b.command_monitor.counts
    return sent


def test_a_standstill_repeats_its_frames_and_they_stay_right() -> None:
    scenario = [(MotionCommand.stop(), "none", 400, False, "heartbeat")]  # every counter, often
    frames = [f for tick in run_side_by_side(scenario) for f in tick]
    assert len(frames) > 250
    for frame in frames:  # each one is still a valid frame of the contract
        protocol.decode(frame.arbitration_id, frame.data, 0.0)


def test_driving_and_steering_against_fresh_encoding() -> None:
    run_side_by_side(
        [
            (MotionCommand.stop(), "none", 40, False, "none"),
            (MotionCommand(MotionPattern.STRAIGHT, 1.0), "none", 200, False, "heartbeat"),
            (
                MotionCommand(MotionPattern.COUNTER_STEER, 0.5, 0.2),
                "stuck_counter",
                100,
                False,
                "bad_crc",
            ),
            (None, "bad_crc", 100, False, "none"),
            (MotionCommand.stop(), "none", 60, True, "short"),
            (MotionCommand.stop(), "none", 100, False, "same_counter_again"),
        ]
    )


def test_a_command_that_changes_every_frame_against_fresh_decoding() -> None:
    """More distinct frames than the twin keeps: what it forgets, it decodes again."""
    ramp: list[Step] = [(MotionCommand.stop(), "none", 40, False, "none")]
    ramp += [
        (MotionCommand(MotionPattern.STRAIGHT, 0.01 * i), "none", 4, False, "heartbeat")
        for i in range(150)
    ]
    ramp += [(MotionCommand(MotionPattern.STRAIGHT, 1.0), "none", 200, False, "none")]
    run_side_by_side(ramp)


@settings(max_examples=40, deadline=None)
@given(scenario=steps)
def test_any_scenario_sends_what_fresh_encoding_sends(scenario: list[Step]) -> None:
    run_side_by_side(scenario)


def test_negative_zero_encodes_as_zero() -> None:
    """Why equal messages may share frames: -0.0 == 0.0, and both spell raw 0."""
    plus = WheelAngles((0.0, 0.0, 0.0, 0.0))
    minus = WheelAngles((-0.0, -0.0, -0.0, -0.0))
    assert plus == minus and math.copysign(1.0, minus.row_angles_rad[0]) < 0
    assert protocol.encode(plus, 5) == protocol.encode(minus, 5)
