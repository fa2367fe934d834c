"""The simulated technician: the hands and feet a calibration maneuver done by hand needs.

On the vehicle a technician turns the wheel and presses the pedals while ``dbw calibrate
STEP`` watches through the daemon. On the simulated vehicle nobody sits in the cab, so
this module plays that part through the bench socket (``appliance.sim.bench``), as a
person would: the wheel turned at a hand's pace and held still in the pauses, the
vehicle driven straight with a driver's small corrections. It knows only what a person
at the wheel knows (where the wheel stops, how long to pause), nothing of the pot's
mapping the maneuver measures.

The schedules are pure (time in, wheel angle and pedal out); :func:`play` sends them.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from appliance.control_client import ControlClient

HALF_TURN_RAD = math.pi


@dataclass(frozen=True)
class Pose:
    """What the technician does from ``t_s`` on (until the next pose)."""

    t_s: float
    wheel_rad: float | None  # None: hands off the wheel
    throttle_pct: float = 0.0
    brake_pct: float = 0.0
    reverse: bool = False  # the gear selector


def half_turns(start_rad: float, end_rad: float, half_turn_rad: float) -> list[float]:
    """The wheel's stops from ``start_rad`` towards ``end_rad`` by half turns, ending at
    ``end_rad`` itself (the lock) however short the last step."""
    step = math.copysign(half_turn_rad, end_rad - start_rad)
    stops = [start_rad]
    while abs(end_rad - stops[-1]) > half_turn_rad + 1e-9:
        stops.append(stops[-1] + step)
    stops.append(end_rad)
    return stops


def pot_map_schedule(
    lock_rad: float,
    *,
    half_turn_rad: float = HALF_TURN_RAD,
    pause_s: float = 2.0,
    rate_rad_per_s: float = 1.5,
    step_s: float = 0.05,
    final_rest_s: float = 2.0,
) -> list[Pose]:
    """Stanley et al., Fig. 17: from the centre to full right, then half turns with
    pauses to full left, and back the same way to full right; then the centre, hands off.
    Right is negative (left positive, as everywhere in dbw). The rest back at full right
    is at least ``final_rest_s``, as the command's instructions ask: it is how the
    command knows the sweep is over."""
    stops = half_turns(-lock_rad, lock_rad, half_turn_rad)
    stops += stops[-2::-1]  # back to full right through the same stops
    poses: list[Pose] = []
    t_s, wheel = 0.0, 0.0
    for number, stop in enumerate([*stops, 0.0]):
        t_s, wheel = _ramp(poses, t_s, wheel, stop, rate_rad_per_s, step_s)  # ends at stop
        t_s += max(pause_s, final_rest_s) if number == len(stops) - 1 else pause_s
    poses.append(Pose(t_s, None))
    return poses


def straight_legs_schedule(
    legs: int = 3,
    *,
    leg_s: float = 14.0,
    turn_s: float = 5.0,
    turn_wheel_rad: float = 2.0,
    throttle_pct: float = 25.0,
    correction_rad: float = 0.05,
    correction_period_s: float = 7.0,
    stop_s: float = 6.0,
    step_s: float = 0.1,
) -> list[Pose]:
    """Stanley et al.'s first step: ``legs`` stretches along a visual reference, the
    wheel near straight with a driver's slow small corrections (a few hundredths of a
    radian), a turn between stretches; then off the throttle, hands off."""
    poses = []
    t_s = 0.0
    for leg in range(legs):
        if leg:
            for i in range(int(turn_s / step_s)):
                poses.append(Pose(t_s + i * step_s, turn_wheel_rad, throttle_pct))
            t_s += turn_s
        for i in range(int(leg_s / step_s)):
            now = t_s + i * step_s
            wheel = correction_rad * math.sin(2.0 * math.pi * now / correction_period_s)
            poses.append(Pose(now, wheel, throttle_pct))
        t_s += leg_s
    # Off the throttle, braking to a stop, then hands and feet off.
    poses.append(Pose(t_s, 0.0, 0.0, 60.0))
    poses.append(Pose(t_s + stop_s, None, 0.0, 0.0))
    return poses


def palm_tree_schedule(
    lock_rad: float,
    *,
    half_turn_rad: float = HALF_TURN_RAD,
    rate_rad_per_s: float = 2.0,
    arc_s: float = 8.0,
    launch_pct: float = 70.0,
    launch_s: float = 2.2,
    cruise_pct: float = 8.0,
    brake_s: float = 3.0,
    brake_pct: float = 60.0,
    step_s: float = 0.05,
    back_up: bool = True,
    to_rad: float | None = None,
) -> list[Pose]:
    """Stanley et al., Fig. 18: at a standstill the wheel to full left; an arc forward for
    ``arc_s`` (pressed to get going for ``launch_s``, then eased to a walking pace: the
    simulated Husky's 1.5 m/s with the defaults), braked to a stop, the same back in
    reverse, braked (``back_up``; without it the arcs go on forward, on a simulated
    ground without end); half a turn right at the standstill; again, to full right (or
    to ``to_rad``: a run broken off, to be resumed). Then the wheel back to the centre,
    hands off.

    The stops between arcs are the technician's: the wheel is only turned with the vehicle
    standing, so every arc is driven at one held angle (the fit cuts arcs where it moves).
    """
    return _drives_at(
        half_turns(lock_rad, -lock_rad if to_rad is None else to_rad, half_turn_rad),
        drive_s=arc_s,
        back_up=back_up,
        pace=_Pace(launch_pct, launch_s, cruise_pct, brake_s, brake_pct),
        rate_rad_per_s=rate_rad_per_s,
        step_s=step_s,
    )


def steady_turns_schedule(
    wheels_rad: Sequence[float] = (2 * HALF_TURN_RAD, -2 * HALF_TURN_RAD),
    *,
    rate_rad_per_s: float = 2.0,
    turn_s: float = 14.0,
    launch_pct: float = 70.0,
    launch_s: float = 2.2,
    cruise_pct: float = 8.0,
    brake_s: float = 3.0,
    brake_pct: float = 60.0,
    step_s: float = 0.05,
) -> list[Pose]:
    """The k ratio's turning tests: at a standstill the wheel to each of ``wheels_rad``
    (a full turn each way by default, as the command asks: k from a turn errs by the tyre
    map's error over the tyre angle, so the larger angle halves it), a steady circle at a
    walking pace for ``turn_s``, braked to a stop. Then the wheel back to the centre,
    hands off."""
    return _drives_at(
        wheels_rad,
        drive_s=turn_s,
        back_up=False,
        pace=_Pace(launch_pct, launch_s, cruise_pct, brake_s, brake_pct),
        rate_rad_per_s=rate_rad_per_s,
        step_s=step_s,
    )


@dataclass(frozen=True)
class _Pace:
    """How the technician drives off and stops: pressed to get going, eased to a pace."""

    launch_pct: float
    launch_s: float
    cruise_pct: float
    brake_s: float
    brake_pct: float


def _drives_at(
    wheels_rad: Sequence[float],
    *,
    drive_s: float,
    back_up: bool,
    pace: _Pace,
    rate_rad_per_s: float,
    step_s: float,
) -> list[Pose]:
    """At each wheel angle, turned at a standstill: a drive of ``drive_s`` at ``pace``,
    braked to a stop (and the same back in reverse with ``back_up``). Then the wheel back
    to the centre, hands off. The palm tree's arcs and the k ratio's turns alike."""
    poses: list[Pose] = []
    t_s, wheel = 0.0, 0.0
    for target in wheels_rad:
        t_s, wheel = _ramp(poses, t_s, wheel, target, rate_rad_per_s, step_s)
        for reverse in (False, True) if back_up else (False,):
            poses.append(Pose(t_s, wheel, pace.launch_pct, 0.0, reverse))
            poses.append(Pose(t_s + pace.launch_s, wheel, pace.cruise_pct, 0.0, reverse))
            t_s += drive_s
            poses.append(Pose(t_s, wheel, 0.0, pace.brake_pct, reverse))
            t_s += pace.brake_s
        poses.append(Pose(t_s, wheel))
    t_s, wheel = _ramp(poses, t_s, wheel, 0.0, rate_rad_per_s, step_s)
    poses.append(Pose(t_s + 0.5, None))
    return poses


def _ramp(
    poses: list[Pose], t_s: float, wheel: float, target: float, rate: float, step_s: float
) -> tuple[float, float]:
    steps = max(1, math.ceil(abs(target - wheel) / (rate * step_s)))
    start = wheel
    for k in range(1, steps + 1):
        t_s += step_s
        poses.append(Pose(t_s, start + (target - start) * k / steps))
    return t_s, target


async def play(
    bench_path: str,
    poses: Sequence[Pose],
    *,
    clock: Callable[[], float] = time.monotonic,
    speed: float = 1.0,
) -> None:
    """Act out ``poses`` on the simulated vehicle's bench, on time; hands off and feet
    off at the end, whatever ends it."""
    async with ControlClient(bench_path, timeout_s=5.0) as bench:
        started = clock()
        throttle: float | None = None
        brake: float | None = None
        reverse: bool | None = None
        try:
            for pose in poses:
                delay = started + pose.t_s / speed - clock()
                if delay > 0:
                    await asyncio.sleep(delay)
                await _call(bench, {"op": "hands", "wheel_rad": pose.wheel_rad})
                if pose.reverse != reverse and (pose.reverse or reverse is not None):
                    reverse = pose.reverse
                    await _call(bench, {"op": "gear", "reverse": reverse})
                if pose.throttle_pct != throttle:
                    throttle = pose.throttle_pct
                    await _pedal(bench, throttle)
                if pose.brake_pct != brake:
                    brake = pose.brake_pct
                    await _pedal(bench, brake, "brake")
        finally:
            await asyncio.shield(_let_go(bench))


async def _let_go(bench: ControlClient) -> None:
    await _call(bench, {"op": "hands", "wheel_rad": None})
    await _call(bench, {"op": "gear", "reverse": False})
    await _pedal(bench, 0.0)
    await _pedal(bench, 0.0, "brake")


async def _pedal(bench: ControlClient, pct: float, pedal: str = "throttle") -> None:
    await _call(bench, {"op": "pedal", "pedal": pedal, "pct": pct})


async def _call(bench: ControlClient, request: dict[str, object]) -> None:
    reply = await bench.call(request)
    if not reply.get("ok"):
        raise RuntimeError(f"the bench refused {request}: {reply.get('error')}")
