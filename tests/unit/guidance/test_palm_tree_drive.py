"""The palm-tree program on its own: phases, pauses, the wheel's checks, the targets.

Driven by a toy vehicle of its own (the wheel turning at a fixed rate towards its target,
the speed approaching the target at a fixed rate): what is tested is the program's logic,
not any vehicle's dynamics.
"""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.guidance.palm_tree_drive import (
    DrivePhase,
    PalmTreeDrive,
    PalmTreeDriveParams,
    half_turn_targets,
)

DT_S = 0.02
PARAMS = PalmTreeDriveParams(
    wheel_targets_rad=(6.0, math.pi, 0.0, -math.pi, -6.0), arc_m=8.0, speed_mps=1.0
)


class ToyVehicle:
    def __init__(self) -> None:
        self.wheel_rad = 0.0
        self.speed_mps = 0.0
        self.now_s = 0.0
        self.distance_m = 0.0
        # The wheel angle at which each metre was driven (the arcs' held angles).
        self.wheel_while_moving: list[float] = []
        self.aims: list[float] = []

    def step(
        self, program: PalmTreeDrive, in_control: bool = True, steering: bool = True
    ) -> DrivePhase:
        command = program.update(self.wheel_rad, self.speed_mps, self.now_s, in_control, steering)
        self.aims.append(command.wheel_aim_rad)
        target_speed = command.speed_mps if in_control else 0.0
        self.speed_mps += max(-2.0 * DT_S, min(2.0 * DT_S, target_speed - self.speed_mps))
        if steering:  # a servo faster than the program turns it
            self.wheel_rad += max(
                -6.0 * DT_S, min(6.0 * DT_S, command.wheel_aim_rad - self.wheel_rad)
            )
        if self.speed_mps > 0.0:
            self.wheel_while_moving.append(self.wheel_rad)
        self.distance_m += self.speed_mps * DT_S
        self.now_s += DT_S
        return command.phase

    def run_until(self, program: PalmTreeDrive, phase: DrivePhase, limit_s: float = 300.0) -> None:
        end = self.now_s + limit_s
        while self.step(program) is not phase:
            assert self.now_s < end, f"never reached {phase}"


def test_every_arc_at_its_held_wheel_angle_then_centred_and_done() -> None:
    program, vehicle = PalmTreeDrive(PARAMS), ToyVehicle()
    vehicle.run_until(program, DrivePhase.DONE)
    assert program.arc == PARAMS.arcs
    assert abs(vehicle.wheel_rad) <= PARAMS.wheel_tolerance_rad and vehicle.speed_mps == 0.0
    # Each arc its length (the stop adds its braking distance), and the wheel only ever
    # at one of the targets while moving: it turns standing.
    assert vehicle.distance_m >= PARAMS.arcs * PARAMS.arc_m
    assert vehicle.distance_m < PARAMS.arcs * (PARAMS.arc_m + 1.0)
    for wheel in vehicle.wheel_while_moving:
        assert min(abs(wheel - t) for t in PARAMS.wheel_targets_rad) <= PARAMS.wheel_tolerance_rad
    # Done stands: no speed target, whatever comes.
    command = program.update(0.0, 0.0, vehicle.now_s + 10.0, True)
    assert command.phase is DrivePhase.DONE and command.speed_mps == 0.0


def test_a_pause_keeps_the_arc_stands_checks_the_wheel_and_drives_only_the_rest() -> None:
    program, vehicle = PalmTreeDrive(PARAMS), ToyVehicle()
    vehicle.run_until(program, DrivePhase.DRIVE)
    while program.driven_m < 3.0:
        vehicle.step(program)
    for _ in range(200):  # let go: the program has nothing, the vehicle stops
        assert vehicle.step(program, in_control=False) is DrivePhase.PAUSED
    driven = program.driven_m
    assert vehicle.speed_mps == 0.0 and driven >= 3.0
    vehicle.wheel_rad = 5.0  # somebody turned the wheel meanwhile
    phases = [vehicle.step(program) for _ in range(10)]
    assert phases[0] is DrivePhase.STEER  # back to the held angle before moving again
    assert program.arc == 0 and program.driven_m == driven
    start = vehicle.distance_m
    vehicle.run_until(program, DrivePhase.STOP)
    assert vehicle.distance_m - start == pytest.approx(PARAMS.arc_m - driven, abs=0.05)


def test_no_reading_stands_and_a_stuck_wheel_is_said() -> None:
    program = PalmTreeDrive(PARAMS)
    command = program.update(None, 0.0, 0.0, True)
    assert command.phase is DrivePhase.NO_READING and command.speed_mps == 0.0
    command = program.update(0.0, math.nan, 0.1, True)
    assert command.phase is DrivePhase.NO_READING
    # A wheel that stays where it is (a servo that cannot turn it): given its turn's
    # time at the program's pace, and the timeout beyond.
    budget_s = PARAMS.steer_timeout_s + 6.0 / PARAMS.steer_rate_rad_per_s
    now = 1.0
    while now < 1.0 + budget_s - 0.5:
        command = program.update(0.0, 0.0, now, True)
        assert command.stuck is None and command.speed_mps == 0.0
        now += 0.5
    command = program.update(0.0, 0.0, now + 1.0, True)
    assert command.stuck is not None and "+6.00" in command.stuck
    assert command.speed_mps == 0.0 and command.phase is DrivePhase.STEER


def test_the_wheel_is_turned_at_its_pace_standing_and_only_with_the_vehicle() -> None:
    program, vehicle = PalmTreeDrive(PARAMS), ToyVehicle()
    vehicle.wheel_rad = 1.0
    for _ in range(100):  # engaged, not in control: held where the operator left it
        assert vehicle.step(program, in_control=False) is DrivePhase.PAUSED
    assert vehicle.aims[-1] == 1.0 and vehicle.wheel_rad == 1.0
    vehicle.wheel_rad = 2.0  # the operator turned it, not engaged: followed, not fought
    vehicle.step(program, in_control=False, steering=False)
    assert vehicle.aims[-1] == 2.0
    followed = len(vehicle.aims)
    vehicle.run_until(program, DrivePhase.DONE)
    steps = [abs(b - a) for a, b in itertools.pairwise(vehicle.aims[followed - 1 :])]
    assert max(steps) <= PARAMS.steer_rate_rad_per_s * DT_S + 1e-9
    assert max(vehicle.aims) == PARAMS.wheel_targets_rad[0]


def test_resumed_from_an_arc_and_refuses_one_past_the_end() -> None:
    program = PalmTreeDrive(PARAMS)
    program.reset(3)
    assert program.wheel_target_rad == -math.pi
    with pytest.raises(ValueError, match=r"arcs 0\.\.4"):
        program.reset(5)
    with pytest.raises(ValueError, match="at least one"):
        PalmTreeDriveParams(wheel_targets_rad=(), arc_m=8.0, speed_mps=1.0)
    with pytest.raises(ValueError, match="speed_mps"):
        PalmTreeDriveParams(wheel_targets_rad=(0.0,), arc_m=8.0, speed_mps=-1.0)


@given(
    low=st.floats(-12.0, -0.5),
    high=st.floats(0.5, 12.0),
    half=st.floats(0.5, 4.0),
)
def test_half_turn_targets_span_the_range_in_half_turns(
    low: float, high: float, half: float
) -> None:
    targets = half_turn_targets(low, high, half)
    assert targets[0] == high and targets[-1] == low  # both ends measured
    steps = [a - b for a, b in itertools.pairwise(targets)]
    assert all(s > 0.0 for s in steps)  # full left to full right
    # Every half-turn bin in the range has a target in it (the fit's coverage), and
    # between the ends each target sits on its bin's centre.
    for k in range(round(low / half), round(high / half) + 1):
        assert any(round(t / half) == k for t in targets)
    assert all(t / half == pytest.approx(round(t / half)) for t in targets[1:-1])
    bins = [round(t / half) for t in targets]
    assert len(set(bins)) == len(bins) or len(targets) == 2  # no bin driven twice


def test_half_turn_targets_refuse_an_empty_range() -> None:
    with pytest.raises(ValueError, match="increasing"):
        half_turn_targets(1.0, 1.0, math.pi)
