"""The simulated PC104 closing the steering loop itself on HL_Pose and HL_ExpectedPose.

Driven frame by frame with a fake clock: a fake high level sends the pattern, the speed
and the world's true pose as a PC104 with its own PID per pattern would receive them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.sim.twins.pc104_core import OutFrame, Pc104TwinCore
from appliance.sim.twins.pc104_pose_loop import PoseLoop, pose_errors
from appliance.sim.vehicle import VehicleParams, VehicleState
from appliance.sim.world import SimWorld
from appliance.simulator import pc104_twin_params
from drivers.geometry import Pose2D
from drivers.pc104 import protocol
from drivers.pc104.messages import (
    HlExpectedPose,
    HlPose,
    Message,
    MotionCommand,
    MotionPattern,
    Pc104Status,
    PoseState,
    SteeringLoop,
)

TICK_S = 0.005
CONFIG = load_config("flatbed-sim")
DOCKED = Pose2D(-6.0, 0.0, 0.0)  # the geometric centre when the front end is at the board


class HighLevel:
    """A twin core, its world and a high level sending its three frames every 20 ms."""

    def __init__(self, start: VehicleState) -> None:
        self.world = SimWorld(VehicleParams.from_config(CONFIG), initial=start)
        self.core = Pc104TwinCore(self.world, pc104_twin_params(CONFIG))
        self.t_s = 0.0
        self.counters: dict[type, int] = {}
        self.frames: list[OutFrame] = []

    def send(self, message: Message) -> None:
        counter = self.counters.get(type(message), 0)
        self.counters[type(message)] = (counter + 1) % 16
        self.core.on_frame(*protocol.encode(message, counter), self.t_s)

    def truth(self, state: PoseState = PoseState.OK) -> HlPose:
        s = self.world.state
        return HlPose(s.x_m, s.y_m, math.remainder(s.yaw_rad, math.tau), state)

    def run(
        self,
        seconds: float,
        command: MotionCommand,
        loop: SteeringLoop | None = SteeringLoop.PC104,
        pose_state: PoseState | None = PoseState.OK,
    ) -> None:
        """``loop`` None sends no HL_ExpectedPose, ``pose_state`` None no HL_Pose."""
        end_s = self.t_s + seconds
        next_s = self.t_s
        while self.t_s < end_s - 1e-9:
            self.t_s += TICK_S
            if self.t_s >= next_s - 1e-9:
                self.send(command)
                if pose_state is not None:
                    self.send(self.truth(pose_state))
                if loop is not None:
                    self.send(HlExpectedPose(*DOCKED, loop))
                next_s += 0.02
            self.world.advance_to(self.t_s)
            self.frames.extend(self.core.tick(self.t_s))

    def status(self) -> Pc104Status:
        frame_id = protocol.spec_for(Pc104Status).frame_id
        frame = next(f for f in reversed(self.frames) if f.arbitration_id == frame_id)
        message = protocol.decode(frame.arbitration_id, frame.data, self.t_s).message
        assert isinstance(message, Pc104Status)
        return message

    def heading_and_lateral(self) -> tuple[float, float]:
        s = self.world.state
        front = Pose2D(s.x_m, s.y_m, s.yaw_rad).apply(6.0, 0.0)
        return math.remainder(s.yaw_rad, math.tau), front[1]


STOP = MotionCommand.stop()


def started(x_m: float, y_m: float, yaw_deg: float) -> HighLevel:
    hl = HighLevel(VehicleState(x_m=x_m, y_m=y_m, yaw_rad=math.radians(yaw_deg)))
    hl.run(0.1, STOP)  # the PC104 waits for a STOP before it moves
    return hl


@given(
    st.floats(-20.0, 20.0),
    st.floats(-5.0, 5.0),
    st.floats(-math.pi, math.pi),
    st.floats(-20.0, 20.0),
    st.floats(-5.0, 5.0),
    st.floats(-math.pi, math.pi),
    st.floats(0.0, 10.0),
)
def test_pose_errors_agree_with_a_homogeneous_transform(
    x: float, y: float, yaw: float, ex: float, ey: float, eyaw: float, forward: float
) -> None:
    def matrix(px: float, py: float, pyaw: float) -> np.ndarray:
        c, s = math.cos(pyaw), math.sin(pyaw)
        return np.array([[c, -s, px], [s, c, py], [0.0, 0.0, 1.0]])

    heading, lateral = pose_errors(Pose2D(x, y, yaw), Pose2D(ex, ey, eyaw), forward)
    point = np.linalg.solve(matrix(ex, ey, eyaw), matrix(x, y, yaw) @ [forward, 0.0, 1.0])
    assert lateral == pytest.approx(point[1], abs=1e-9)
    relative = math.atan2(math.sin(yaw - eyaw), math.cos(yaw - eyaw))
    assert abs(math.remainder(heading - relative, math.tau)) < 1e-9


def test_rear_steer_on_pose_turns_the_heading_error_away() -> None:
    hl = started(-16.0, 0.0, 2.0)
    hl.run(25.0, MotionCommand(MotionPattern.REAR_STEER, 0.2))
    heading, _ = hl.heading_and_lateral()
    assert abs(math.degrees(heading)) < 0.05
    assert hl.status().active_pattern is MotionPattern.REAR_STEER
    assert not hl.status().faults.any


def test_oblique_on_pose_brings_the_front_end_onto_the_axis() -> None:
    hl = started(-16.0, 0.3, 0.0)
    hl.run(30.0, MotionCommand(MotionPattern.OBLIQUE, 0.2))
    heading, lateral = hl.heading_and_lateral()
    assert abs(lateral) < 0.003
    assert abs(math.degrees(heading)) < 0.2  # crabbing does not turn the vehicle


def test_the_hl_set_points_are_followed_unless_the_pc104_is_asked_to_steer() -> None:
    command = MotionCommand(MotionPattern.OBLIQUE, 0.2, front_steer_rad=math.radians(5.0))
    for loop in (SteeringLoop.HL, None):
        hl = started(-16.0, 0.3, 0.0)
        hl.run(3.0, command, loop=loop)
        assert hl.world.state.front_steer_rad == pytest.approx(math.radians(5.0), abs=1e-3)
    hl = started(-16.0, 0.3, 0.0)
    hl.run(3.0, command)
    assert hl.world.state.front_steer_rad < 0.0  # its own loop steers right, to the axis


@pytest.mark.parametrize("pose_state", [None, PoseState.DEGRADED, PoseState.LOST])
def test_no_usable_pose_stops_the_vehicle_until_the_hl_sends_stop(
    pose_state: PoseState | None,
) -> None:
    hl = started(-16.0, 0.0, 1.0)
    command = MotionCommand(MotionPattern.REAR_STEER, 0.3)
    hl.run(3.0, command)
    assert hl.world.state.speed_mps > 0.2
    hl.run(0.2, command, pose_state=pose_state)  # the pose goes missing or untrusted
    assert hl.status().faults.pose and hl.status().stop_required
    assert hl.status().active_pattern is MotionPattern.STOP
    hl.run(5.0, command)  # a good pose again is not enough: motion resumes only after STOP
    assert abs(hl.world.state.speed_mps) < 0.01 and hl.status().faults.pose
    hl.run(0.1, STOP)
    assert not hl.status().faults.pose and hl.status().ready


def test_a_reset_loop_behaves_as_a_new_one() -> None:
    """The integral and the rate limit's memory both go: after ``reset()`` the same inputs
    give the same angles as a loop just built, and different ones before it."""
    params = pc104_twin_params(CONFIG).pose_loop
    expected = Pose2D(-6.0, 0.0, 0.0)
    poses = [Pose2D(-10.0 + 0.01 * i, 0.05 - 0.001 * i, 0.01 - 0.0001 * i) for i in range(300)]
    pattern = MotionPattern.REAR_STEER  # a change of pattern would reset it by itself

    def angles(loop: PoseLoop) -> list[tuple[float, float]]:
        return [loop.update(pattern, 0.2, pose, expected, 0.0, 0.0, 0.02) for pose in poses]

    used = PoseLoop(params)
    first = angles(used)
    assert angles(used) != first  # it remembers
    used.reset()
    assert angles(used) == first == angles(PoseLoop(params))
