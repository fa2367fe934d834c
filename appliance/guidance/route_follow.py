"""Following a route: Stanley et al.'s autopilot core, from fixes to steering and speed wishes.

One object holds the chain the paper's Figs. 5-11 describe, each link its own small class:
dead reckoning gives a local pose that never jumps; each GNSS fix, at its measurement
time, feeds the continually varying local/global transform (Fig. 11), so a jump in the
fix moves the route smoothly instead of jerking the wheel; the planner finds the nearest
point and the travel direction (Fig. 5); pure pursuit for proportional counter-steer
(eq. 3/eq. 2) turns the goal into wheel angles; the speed profile slows for curves, the
route's limit and its end.

Everything is worked in the route's (ENU) frame with the vehicle's *blended* pose: the
transform is rigid, so tracking the route from the blended pose is the same geometry as
tracking the transformed route from the local pose, at the cost of one pose instead of a
window of points per cycle. The route then never moves, so what the tracker and the
speed profile read of it (the route in travel order with its arc length, each point's
curve speed) is made once per route, travel direction and parameters, not per cycle.

What comes out is a wish: the daemon's mode machine and safety layer may refuse it, and
``ready`` False (with a reason an operator can act on) stops automatic steering. The
same object runs in the daemon, in `dbw sim track` and in the benchmark; time is an
argument and nothing here does I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy.typing as npt

from appliance.guidance.pure_pursuit import (
    LookaheadSchedule,
    PurePursuitTracker,
    PursuitParams,
    TrackerOutput,
)
from appliance.guidance.route_planner import (
    AllowedDirections,
    PlannerOutput,
    PlannerParams,
    PlannerRefusal,
    RoutePlanner,
    engagement_check,
)
from appliance.guidance.speed_profile import (
    CurveSpeedTable,
    SpeedProfileParams,
    SpeedTarget,
    path_curvature,
)
from appliance.guidance.travel_path import TravelDirection, TravelPaths
from appliance.localization.dead_reckoning import DeadReckoning
from appliance.localization.frame_blend import (
    FrameBlendParams,
    LocalGlobalTransform,
)
from appliance.localization.gnss_pose import GnssNoFix, GnssPose
from appliance.localization.gnss_quality import FixVerdictParams, extrapolate, fix_verdict
from drivers.geometry import Pose2D

# Fixes waiting for the dead reckoning to reach their measurement time (a second at 20 Hz).
MAX_PENDING_FIXES = 20


@dataclass(frozen=True)
class RouteFollowParams:
    pursuit: PursuitParams
    planner: PlannerParams = field(default_factory=PlannerParams)
    blend: FrameBlendParams = field(default_factory=FrameBlendParams)
    profile: SpeedProfileParams = field(default_factory=SpeedProfileParams)
    fix: FixVerdictParams = field(default_factory=FixVerdictParams)
    # The heading between fixes is the last one carried forward at its yaw rate, this far.
    max_extrapolation_s: float = 0.5
    # Where the antenna (the position the receiver reports) sits on the vehicle, from the
    # geometric centre: forward and to the left.
    antenna_forward_m: float = 0.0
    antenna_left_m: float = 0.0
    # The vehicle's own rear/front ratio, for its sideslip in dead reckoning: the
    # linkage's, whatever law steers (the plain two-wheel law assumes k = 0).
    counter_steer_ratio_k: float | None = None  # None: the pursuit's
    # Engagement is allowed only this close to the route and this well aligned with it.
    engage_max_distance_m: float = 10.0
    engage_max_heading_rad: float = math.radians(30.0)


@dataclass(frozen=True)
class FollowWish:
    """One cycle's wish. Angles are tyre angles, left positive; ``rear_steer_rad`` is the
    rear row in the counter-steer direction (k times the front for proportional 4WS)."""

    ready: bool
    reason: str
    front_steer_rad: float = 0.0
    rear_steer_rad: float = 0.0
    target_speed_mps: float = 0.0
    status: dict[str, Any] = field(default_factory=dict)
    tracker: TrackerOutput | None = None
    planner: PlannerOutput | None = None
    pose: Pose2D | None = None  # the blended pose of the vehicle's centre, route frame


def _pose_to_global(transform: Pose2D, local: Pose2D) -> Pose2D:
    """``local`` seen in the global frame, ``transform`` being T (local <- global)."""
    c, s = math.cos(transform.yaw_rad), math.sin(transform.yaw_rad)
    dx, dy = local.x_m - transform.x_m, local.y_m - transform.y_m
    return Pose2D(c * dx + s * dy, -s * dx + c * dy, local.yaw_rad - transform.yaw_rad)


class RouteFollower:
    """Fixes and odometry in, steering and speed wishes out (see the module)."""

    def __init__(
        self,
        params: RouteFollowParams,
        route_enu_m: npt.ArrayLike,
        allowed: AllowedDirections = "both",
        speed_limit_mps: float | None = None,
    ) -> None:
        self.params = params
        self.planner = RoutePlanner(route_enu_m, params.planner, allowed)
        self.route_m = self.planner.route_m
        # Each travel direction's curve speeds, made when first driven (``_curve_table``).
        self._curve_tables: dict[TravelDirection, CurveSpeedTable] = {}
        self._curve_tables_for: tuple[TravelPaths, SpeedProfileParams] | None = None
        self.speed_limit_mps = speed_limit_mps
        self.tracker = PurePursuitTracker(params.pursuit)
        self.speed = SpeedTarget(params.profile)
        self.odometry = DeadReckoning()
        self.transform = LocalGlobalTransform(params.blend)
        # From the antenna back to the centre (the antenna is not turned on the vehicle).
        self._centre_from_antenna = Pose2D(-params.antenna_forward_m, -params.antenna_left_m, 0.0)
        self.reset_localization()
        self._prime_curve_tables()

    # ---- resets ------------------------------------------------------------------------
    def reset(self, speed_mps: float = 0.0, front_steer_rad: float = 0.0) -> None:
        """A new engagement: the direction is chosen again, the tracker and the speed
        target start from what the vehicle does now. Localization is kept: the fit of
        the transform took many fixes and is as good as it was a cycle ago."""
        self.planner.reset()
        self.tracker.reset(front_steer_rad)
        self.speed.reset(speed_mps)
        self._last_now_s: float | None = None

    def replace_route(self, route_enu_m: npt.ArrayLike) -> None:
        """Follow another route from the next cycle on, on the same localization (the
        look-ahead tuning's courses, laid at the vehicle and moved sideways mid-run): the
        direction is decided anew; the tracker and the speed target go on as they were,
        so the wheel and the speed do not jump at the change."""
        self.planner.set_route(route_enu_m, self.planner.allowed)
        self.route_m = self.planner.route_m
        self._prime_curve_tables()

    def set_schedule(self, schedule: LookaheadSchedule) -> None:
        """Another look-ahead schedule (a tuning run's candidate), from a fresh tracker."""
        self.params = replace(self.params, pursuit=replace(self.params.pursuit, schedule=schedule))
        self.tracker = PurePursuitTracker(self.params.pursuit)

    def reset_localization(self) -> None:
        """Forget every fix (a restart, a new origin): nothing is ready until fixes come."""
        self.odometry.reset()
        self.transform.reset()
        self.last_fix: GnssPose | GnssNoFix | None = None
        self._pending_fixes: list[tuple[GnssPose, float]] = []  # (fix, received at)
        self.reset()

    # ---- inputs ------------------------------------------------------------------------
    def update_fix(self, fix: GnssPose | GnssNoFix, now_s: float) -> None:
        """A fix as the assembler emitted it. It is paired with the dead-reckoned pose at
        its measurement time at the next cycle that has reached that time (a fix can be
        measured after the last cycle: the receiver's latency can be shorter than a
        period). Fixes the verdict refuses still count as the latest (so the refusal is
        stated) but do not move the transform."""
        self.last_fix = fix
        usable = isinstance(fix, GnssPose) and fix.yaw_rad is not None
        if usable and fix_verdict(fix, now_s, self.params.fix).ok:
            assert isinstance(fix, GnssPose)
            self._pending_fixes.append((fix, now_s))
            del self._pending_fixes[:-MAX_PENDING_FIXES]

    def _pair_fixes(self, odometry_s: float) -> None:
        waiting = []
        for fix, received_s in self._pending_fixes:
            if fix.measurement_time_s > odometry_s:
                waiting.append((fix, received_s))
                continue
            local = self.odometry.pose_at(fix.measurement_time_s)
            if local is None:  # before the odometry's history: too old to pair
                continue
            assert fix.yaw_rad is not None
            antenna = Pose2D(fix.east_m, fix.north_m, fix.yaw_rad)
            centre = antenna.compose(self._centre_from_antenna)
            sigma = fix.sigma_worst_m if fix.sigma_worst_m is not None else 1.0
            self.transform.update_fix(centre, sigma, local, received_s)
        self._pending_fixes = waiting

    def _slip_rad(self, front_steer_rad: float | None) -> float:
        """The centre's direction of travel against the heading, for proportional
        counter-steer (rear = k x front in the counter-steer direction)."""
        if front_steer_rad is None or not math.isfinite(front_steer_rad):
            return 0.0
        k = self.params.counter_steer_ratio_k
        if k is None:
            k = self.params.pursuit.counter_steer_ratio_k
        return math.atan(0.5 * (math.tan(front_steer_rad) - math.tan(k * front_steer_rad)))

    def _heading_now(self, now_s: float) -> float | None:
        fix = self.last_fix
        if not isinstance(fix, GnssPose):
            return None
        ahead = extrapolate(fix, now_s, self.params.max_extrapolation_s)
        return None if ahead is None else ahead.pose.yaw_rad

    # ---- the cycle ---------------------------------------------------------------------
    def update(
        self,
        now_s: float,
        speed_mps: float,
        set_speed_mps: float,
        engaged: bool,
        front_steer_rad: float | None = None,
    ) -> FollowWish:
        """One control cycle: ``speed_mps`` measured (signed), ``set_speed_mps`` the
        operator's set speed (cruise), ``engaged`` whether the wish will be used,
        ``front_steer_rad`` the measured front tyre angle (for the sideslip of
        counter-steer in dead reckoning; None: taken as straight)."""
        last, self._last_now_s = self._last_now_s, now_s
        dt_s = 0.0 if last is None else max(now_s - last, 0.0)
        heading = self._heading_now(now_s)
        if heading is not None and math.isfinite(speed_mps):
            slip = self._slip_rad(front_steer_rad)
            self.odometry.update(speed_mps, now_s, heading_rad=heading, slip_rad=slip)
            self._pair_fixes(now_s)
        verdict = fix_verdict(self.last_fix, now_s, self.params.fix)
        status: dict[str, Any] = {"fix": verdict.reason or "ok"}
        if not verdict.ok:
            return self._refused(verdict.reason, status)
        if heading is None:
            return self._refused("no heading", status)
        if not self.transform.ready:
            return self._refused("waiting for the first fixes", status)

        centre = _pose_to_global(self.transform.current(now_s), self.odometry.pose)
        anchor = self.params.pursuit.anchor_pose(centre)
        planned = self.planner.update((anchor.x_m, anchor.y_m), anchor.yaw_rad, now_s)
        if isinstance(planned, PlannerRefusal):
            return self._refused(planned.reason, status, centre)
        status |= _planner_status(planned)
        if not engaged:
            blockers = engagement_check(
                planned, self.params.engage_max_distance_m, self.params.engage_max_heading_rad
            )
            if blockers:
                return self._refused("; ".join(blockers), status, centre, planned)
            # Not engaged: the direction is decided again at the engagement.
            self.planner.reset()
            return FollowWish(True, "", status=status, planner=planned, pose=centre)

        path = self.planner.paths.path(planned.direction)
        projection = planned.travel_projection
        tracked = self.tracker.update(anchor, max(speed_mps, 0.0), path, projection, dt_s)
        curve_limit = self._curve_table(planned.direction).limit_mps(planned.progress_m)
        target = self.speed.update_with_curve_limit(
            set_speed_mps, self.speed_limit_mps, curve_limit, planned.remaining_m, now_s
        )
        status |= {
            "lookahead_m": round(tracked.lookahead_m, 2),
            "target_speed_mps": round(target, 2),
            "speed_limited_by": str(self.speed.limited_by),
        }
        return FollowWish(
            ready=True,
            reason="",
            front_steer_rad=tracked.front_steer_rad,
            rear_steer_rad=tracked.rear_steer_rad,
            target_speed_mps=target,
            status=status,
            tracker=tracked,
            planner=planned,
            pose=centre,
        )

    def _prime_curve_tables(self) -> None:
        """The route in each direction it may be driven, made now (at the route's
        selection) rather than in the first cycle that drives it."""
        for direction in TravelDirection:
            if self.planner.allowed in ("both", direction.value):
                self._curve_table(direction)

    def _curve_table(self, direction: TravelDirection) -> CurveSpeedTable:
        """The curve speeds along the route driven in ``direction``: made once for the
        planner's route and the speed target's parameters, made again if either is
        replaced."""
        paths, profile = self.planner.paths, self.speed.params
        made_for = self._curve_tables_for
        if made_for is None or made_for[0] is not paths or made_for[1] is not profile:
            self._curve_tables, self._curve_tables_for = {}, (paths, profile)
        table = self._curve_tables.get(direction)
        if table is None:
            path = paths.path(direction)
            table = CurveSpeedTable(path.arc_m, path_curvature(path.points_m), profile)
            self._curve_tables[direction] = table
        return table

    def _refused(
        self,
        reason: str,
        status: dict[str, Any],
        pose: Pose2D | None = None,
        planned: PlannerOutput | None = None,
    ) -> FollowWish:
        self.speed.reset(0.0)
        return FollowWish(False, reason, status=status, pose=pose, planner=planned)


def _planner_status(planned: PlannerOutput) -> dict[str, Any]:
    return {
        "direction": str(planned.direction),
        "progress_m": round(planned.progress_m, 1),
        "remaining_m": round(planned.remaining_m, 1),
        "progress_pct": round(100.0 * planned.progress_fraction, 1),
        "cross_track_m": round(planned.cross_track_m, 3),
        "distance_to_route_m": round(planned.distance_to_route_m, 2),
        "heading_error_deg": round(math.degrees(planned.heading_error_rad), 1),
        "jumps_refused": planned.jumps_refused,
    }
