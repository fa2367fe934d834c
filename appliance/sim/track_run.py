"""`dbw sim track`: the Husky's route autopilot on the simulated vehicle, faster than real time.

The loop is the daemon's chain without the daemon: fixes of the simulated pose go to the
same :class:`~appliance.guidance.route_follow.RouteFollower`, whose steering wish drives
the kinematic model of Stanley et al. (both axles steered, G_ss with V_char, the servo's
lag and rate limit, engine and brake lags) and whose target speed goes through the
throttle/brake controller of the ``pedals`` speed path. What is measured is the truth: the
anchor point's cross-track error against the course as given, not against the vehicle's
own (jumping, noisy) idea of where it is.

Fixes are made one of two ways. By default straight from the simulated pose (noise of σ
per axis, the paper's switching jumps, a measurement latency): cheap enough that a mile
runs in seconds. With ``through_nmea`` they go the whole way the daemon's do: the
receiver's twin writes NMEA sentences, the sans-I/O receiver parses them and the
assembler builds the pose, at a cost of about 1 ms per fix.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
import numpy.typing as npt

from appliance.config.models import VehicleConfig
from appliance.guidance.pedal_speed import PedalSpeedController, PedalSpeedParams
from appliance.guidance.pure_pursuit import PursuitParams
from appliance.guidance.route_follow import RouteFollower, RouteFollowParams
from appliance.localization.gnss_pose import GnssPose, HeadingSource, SigmaSource
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.geometry import Pose2D
from drivers.gnss.sentences import FixQuality
from drivers.pc104.messages import MotionPattern

FloatArray = npt.NDArray[np.float64]

CONVERGED_M = 0.1


@dataclass(frozen=True)
class TrackRunParams:
    speed_mps: float = 4.47  # the operator's set speed (10 mph)
    start_speed_mps: float | None = None  # None: engaged already at the set speed
    offset_m: float = 0.0  # the start, to the left of the course (negative: right)
    loc_noise_m: float = 0.05  # σ of each fix, per axis
    loc_jump_m: float = 0.0  # the paper's LGPR/GPS switching: an offset on and off
    loc_jump_period_s: float = 20.0
    heading_noise_rad: float = math.radians(0.1)
    fix_rate_hz: float = 10.0
    fix_latency_s: float = 0.05
    fix_stop_s: float | None = None  # the receiver falls silent then (a lost fix)
    control_hz: float = 50.0
    world_hz: float = 100.0
    seed: int = 1
    tracker: Literal["4ws", "plain"] = "4ws"
    settle_m: float = 10.0  # the RMS leaves out the first metres (the offset's recovery)
    timeout_s: float | None = None  # None: long enough for the course at a crawl
    through_nmea: bool = False
    brake_time_constant_s: float = 0.3
    keep_trace: bool = False


@dataclass
class TrackResult:
    reason: str  # "end of course", or why the run stopped early
    course_length_m: float
    distance_m: float
    duration_s: float
    wall_s: float
    rms_cross_track_m: float
    max_cross_track_m: float
    converge_time_s: float | None  # first time below 0.1 m (None: never)
    converge_distance_m: float | None
    max_steer_rate_deg_per_s: float
    rms_speed_error_mps: float  # against the target the profile asked for
    rms_speed_error_vs_set_mps: float
    mean_speed_mps: float
    refusals: int
    jumps_followed: int
    trace: dict[str, list[float]] = field(default_factory=dict)

    @property
    def realtime_factor(self) -> float:
        return self.duration_s / self.wall_s if self.wall_s > 0 else math.inf


def husky_plant(config: VehicleConfig, brake_time_constant_s: float) -> VehicleParams:
    return replace(VehicleParams.from_config(config), brake_time_constant_s=brake_time_constant_s)


class _Fixes:
    """Fixes of the true pose, as a receiver would give them (see the module)."""

    def __init__(self, params: TrackRunParams, antenna_forward_m: float) -> None:
        self.params = params
        self.rng = np.random.default_rng(params.seed)
        self.jump_rng = np.random.default_rng([params.seed, 1])
        self.period_s = 1.0 / params.fix_rate_hz
        self.next_s = 0.0
        self.antenna_forward_m = antenna_forward_m
        self.pending: list[tuple[float, GnssPose]] = []  # (deliver at, fix)
        self._jump_period = -1
        self._jump = (0.0, 0.0)
        self._last_yaw: float | None = None

    def _jump_offset(self, t_s: float) -> tuple[float, float]:
        p = self.params
        if p.loc_jump_m <= 0.0:
            return 0.0, 0.0
        period = int(t_s // p.loc_jump_period_s)
        if period != self._jump_period:
            self._jump_period = period
            angle = float(self.jump_rng.uniform(-math.pi, math.pi))
            on = period % 2 == 1  # off for the first period, then on, off, ...
            self._jump = (
                (p.loc_jump_m * math.cos(angle), p.loc_jump_m * math.sin(angle))
                if on
                else (0.0, 0.0)
            )
        return self._jump

    def update(self, t_s: float, state: VehicleState) -> list[GnssPose]:
        p = self.params
        silent = p.fix_stop_s is not None and t_s >= p.fix_stop_s
        if t_s + 1e-9 >= self.next_s and not silent:
            self.next_s += self.period_s
            yaw = state.yaw_rad
            antenna_x = state.x_m + self.antenna_forward_m * math.cos(yaw)
            antenna_y = state.y_m + self.antenna_forward_m * math.sin(yaw)
            jump_x, jump_y = self._jump_offset(t_s)
            noise = self.rng.normal(0.0, 1.0, 3)
            rate = (
                0.0
                if self._last_yaw is None
                else math.remainder(yaw - self._last_yaw, math.tau) / self.period_s
            )
            self._last_yaw = yaw
            sigma = max(p.loc_noise_m, 0.01)
            fix = GnssPose(
                measurement_time_s=t_s,
                utc_time_of_day_s=43200.0 + t_s,
                east_m=antenna_x + jump_x + p.loc_noise_m * noise[0],
                north_m=antenna_y + jump_y + p.loc_noise_m * noise[1],
                up_m=0.0,
                quality=FixQuality.RTK_FIXED,
                satellites=16,
                hdop=0.7,
                yaw_rad=math.remainder(yaw + p.heading_noise_rad * noise[2], math.tau),
                heading_source=HeadingSource.TRUE_HEADING,
                course_yaw_rad=yaw,
                speed_mps=abs(state.speed_mps),
                yaw_rate_rad_per_s=rate,
                sigma_east_m=sigma,
                sigma_north_m=sigma,
                sigma_worst_m=sigma,
                sigma_source=SigmaSource.GST,
            )
            self.pending.append((t_s + p.fix_latency_s, fix))
        # Made in time order with one latency, so the fixes due are the first ones.
        count = 0
        while count < len(self.pending) and self.pending[count][0] <= t_s + 1e-9:
            count += 1
        due = [fix for _, fix in self.pending[:count]]
        del self.pending[:count]
        return due


class _Truth:
    """The anchor's signed cross-track error against the course as given (left of the
    course's direction positive): the figure the run is judged by, so it is worked out
    here and not taken from the planner under test. A local search from the last
    segment, as the vehicle cannot skip ahead: the nearest of the 44 segments from 4
    behind to 40 ahead. Segments come in groups of 8 with a circle around each; the
    group the vehicle was on is searched first, and another only if its circle comes
    nearer than the nearest segment so far (the same answer, from a fraction of them)."""

    _GROUP = 8

    def __init__(self, course: FloatArray) -> None:
        start = course[:-1]
        delta = np.diff(course, axis=0)
        length = np.hypot(delta[:, 0], delta[:, 1])
        keep = length > 1e-9
        start, delta, length = start[keep], delta[keep], length[keep]
        unit = delta / length[:, None]
        self.start_x: list[float] = start[:, 0].tolist()
        self.start_y: list[float] = start[:, 1].tolist()
        self.unit_x: list[float] = unit[:, 0].tolist()
        self.unit_y: list[float] = unit[:, 1].tolist()
        self.length: list[float] = length.tolist()
        self.arc_end: list[float] = np.cumsum(length).tolist()
        self.segment = 0
        # each group's circle: the centre of its end points' box, and the farthest of them
        ends = np.vstack((start, start[-1:] + delta[-1:]))
        self.circles: list[tuple[float, float, float]] = []
        for first in range(0, len(length), self._GROUP):
            points = ends[first : min(first + self._GROUP, len(length)) + 1]
            centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
            radius = float(np.max(np.hypot(*(points - centre).T)))
            self.circles.append((float(centre[0]), float(centre[1]), radius))

    def update(self, x_m: float, y_m: float) -> tuple[float, float]:
        """(cross-track, arc length remaining to the course's end)."""
        lo = max(self.segment - 4, 0)
        hi = min(self.segment + 40, len(self.length))
        group = self._GROUP
        here = self.segment // group
        best = (math.inf, 0, 0.0)  # gap, segment, along
        best = self._search(x_m, y_m, max(lo, here * group), min(hi, here * group + group), best)
        for g in range(lo // group, (hi - 1) // group + 1):
            first, last = max(lo, g * group), min(hi, g * group + group)
            if g == here:
                continue  # searched first
            cx, cy, radius = self.circles[g]
            if math.hypot(x_m - cx, y_m - cy) - radius > best[0] + 1e-9:
                continue  # no segment of it comes nearer
            best = self._search(x_m, y_m, first, last, best)
        _, i, along = best
        self.segment = i
        ux, uy = self.unit_x[i], self.unit_y[i]
        cross = ux * (y_m - self.start_y[i]) - uy * (x_m - self.start_x[i])
        remaining = self.arc_end[-1] - (self.arc_end[i] - self.length[i] + along)
        return cross, remaining

    def _search(
        self,
        x_m: float,
        y_m: float,
        first: int,
        last: int,
        best: tuple[float, int, float],
    ) -> tuple[float, int, float]:
        """The nearer of ``best`` and segments first..last-1 (a tie: the lower index)."""
        sx, sy, ux, uy, length = self.start_x, self.start_y, self.unit_x, self.unit_y, self.length
        best_gap, best_i, best_along = best
        for i in range(first, last):
            rel_x, rel_y = x_m - sx[i], y_m - sy[i]
            along = rel_x * ux[i] + rel_y * uy[i]
            along = 0.0 if along < 0.0 else length[i] if along > length[i] else along
            gap = math.hypot(x_m - (sx[i] + along * ux[i]), y_m - (sy[i] + along * uy[i]))
            if gap < best_gap or (gap == best_gap and i < best_i):
                best_gap, best_i, best_along = gap, i, along
        return best_gap, best_i, best_along


def _start_state(course: FloatArray, offset_m: float, speed_mps: float) -> VehicleState:
    (x0, y0), (x1, y1) = course[0], course[1]
    yaw = math.atan2(y1 - y0, x1 - x0)
    return VehicleState(
        x_m=x0 - offset_m * math.sin(yaw),
        y_m=y0 + offset_m * math.cos(yaw),
        yaw_rad=yaw,
        speed_mps=speed_mps,
        brake_level=0.0,
    )


def run_track(config: VehicleConfig, course: FloatArray, params: TrackRunParams) -> TrackResult:
    started = time.perf_counter()
    pursuit = PursuitParams.from_config(config)
    if params.tracker == "plain":
        pursuit = PursuitParams.plain_two_wheel(pursuit)
    follow = RouteFollowParams(
        pursuit=pursuit,
        antenna_forward_m=config.geometry.anchor_point_forward_m,
        counter_steer_ratio_k=config.geometry.counter_steer_ratio_k,
    )
    follower = RouteFollower(follow, course)
    truth = _Truth(course)
    pedals = PedalSpeedController(PedalSpeedParams.from_limits(config.limits))
    plant = husky_plant(config, params.brake_time_constant_s)
    fixes = _Fixes(params, config.geometry.anchor_point_forward_m)
    start_speed = params.speed_mps if params.start_speed_mps is None else params.start_speed_mps
    state = _start_state(course, params.offset_m, start_speed)
    timeout_s = params.timeout_s or 60.0 + 3.0 * _length(course) / max(params.speed_mps, 0.3)

    world_dt = 1.0 / params.world_hz
    control_dt = 1.0 / params.control_hz
    next_control = 0.0
    engaged = False
    command = VehicleCommand(pattern=MotionPattern.COUNTER_STEER, brake_pct=0.0)
    t_s = 0.0
    reason = "timeout"
    refusals = 0
    xte: list[float] = []
    speed_err: list[float] = []
    speed_err_set: list[float] = []
    converge: tuple[float, float] | None = None  # after engagement: time, distance
    engaged_at_s, engaged_at_m = 0.0, None
    max_rate = 0.0
    trace: dict[str, list[float]] = {
        k: [] for k in ("t_s", "x_m", "y_m", "xte_m", "speed_mps", "front_deg")
    }
    last_front = state.front_steer_rad
    pedals.reset(throttle_pct=0.0, brake_pct=0.0)

    while t_s < timeout_s:
        for fix in fixes.update(t_s, state):
            follower.update_fix(fix, t_s)
        if t_s + 1e-9 >= next_control:
            next_control += control_dt
            wish = follower.update(
                t_s, state.speed_mps, params.speed_mps, engaged, state.front_steer_rad
            )
            if wish.ready and not engaged:
                engaged = True
                engaged_at_s, engaged_at_m = t_s, state.odometer_m
                follower.reset(state.speed_mps, state.front_steer_rad)
                pedals.reset(throttle_pct=0.0, brake_pct=0.0)
                wish = follower.update(
                    t_s, state.speed_mps, params.speed_mps, engaged, state.front_steer_rad
                )
            if engaged and not wish.ready:
                refusals += 1
                reason = f"autopilot refused: {wish.reason}"
                break
            if engaged:
                pedal = pedals.update(wish.target_speed_mps, state.speed_mps, None, t_s)
                command = VehicleCommand(
                    pattern=MotionPattern.COUNTER_STEER,
                    front_steer_rad=wish.front_steer_rad,
                    throttle_pct=pedal.throttle_pct,
                    brake_pct=pedal.brake_pct,
                )
                assert wish.planner is not None
                speed_err.append(state.speed_mps - wish.target_speed_mps)
                speed_err_set.append(state.speed_mps - params.speed_mps)
                if wish.planner.remaining_m < 1.0 and abs(state.speed_mps) < 0.01:
                    reason = "end of course"
                    break
        state = step(state, command, world_dt, plant)
        t_s += world_dt
        rate = abs(state.front_steer_rad - last_front) / world_dt
        last_front = state.front_steer_rad
        max_rate = max(max_rate, rate)
        if t_s + 1e-9 < next_control:
            continue  # judged at the control rate: 9 cm apart at 10 mph is plenty
        anchor = pursuit_anchor(state, config.geometry.anchor_point_forward_m)
        error, remaining = truth.update(anchor.x_m, anchor.y_m)
        travelled = state.odometer_m - engaged_at_m if engaged_at_m is not None else 0.0
        if engaged_at_m is not None and converge is None and abs(error) < CONVERGED_M:
            converge = (t_s - engaged_at_s, travelled)
        if travelled >= params.settle_m and remaining > 1.0:
            xte.append(error)
        if params.keep_trace:
            for key, value in zip(
                trace,
                (
                    t_s,
                    state.x_m,
                    state.y_m,
                    error,
                    state.speed_mps,
                    math.degrees(state.front_steer_rad),
                ),
                strict=True,
            ):
                trace[key].append(value)
    errors = np.asarray(xte)
    return TrackResult(
        reason=reason,
        course_length_m=_length(course),
        distance_m=state.odometer_m,
        duration_s=t_s,
        wall_s=time.perf_counter() - started,
        rms_cross_track_m=float(np.sqrt(np.mean(errors**2))) if len(errors) else math.nan,
        max_cross_track_m=float(np.max(np.abs(errors))) if len(errors) else math.nan,
        converge_time_s=None if converge is None else converge[0],
        converge_distance_m=None if converge is None else converge[1],
        max_steer_rate_deg_per_s=math.degrees(max_rate),
        rms_speed_error_mps=_rms(speed_err),
        rms_speed_error_vs_set_mps=_rms(speed_err_set),
        mean_speed_mps=state.odometer_m / t_s if t_s > 0 else 0.0,
        refusals=refusals,
        jumps_followed=follower.transform.jumps_followed,
        trace=trace if params.keep_trace else {},
    )


def pursuit_anchor(state: VehicleState, anchor_forward_m: float) -> Pose2D:
    yaw = state.yaw_rad
    return Pose2D(
        state.x_m + anchor_forward_m * math.cos(yaw),
        state.y_m + anchor_forward_m * math.sin(yaw),
        yaw,
    )


def _length(course: FloatArray) -> float:
    return float(np.sum(np.hypot(*np.diff(course, axis=0).T)))


def _rms(values: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(values)))) if values else math.nan
