"""The `route` autopilot source: Stanley et al.'s route following on the autopilot seam.

The operator selects a route (the vehicle file's ``route.selected``, or `dbw route select`
at run time, as the paper's GUI did), drives to it and engages; the source then steers
along it and caps the speed by the route's profile (curves, its limit, its end). Every
wish goes through the mode machine and the safety layer like any other; what makes the
source refuse is said in words an operator can act on (``no route selected``, ``12.4 m
from route, limit 10 m``, ``fix degraded: σ 0.80 m (limit 0.15 m)``, ...).

Routes are read from the vehicle's route store and converted once into the vehicle's
local east-north frame (``positioning.origin``); the chain itself is
:class:`~appliance.guidance.route_follow.RouteFollower`. Each new GNSS epoch is handed to
it once (by its sequence number), whatever the control rate.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np

from appliance.config.models import VehicleConfig
from appliance.core.route_tuning import RouteTuning
from appliance.core.wish import AutopilotWish, Observation
from appliance.guidance.lookahead_tuning import TuningParams
from appliance.guidance.pure_pursuit import LookaheadSchedule, PursuitParams
from appliance.guidance.route_follow import RouteFollower, RouteFollowParams
from appliance.guidance.speed_profile import SpeedProfileParams
from appliance.localization.gnss_quality import FixVerdictParams, fix_verdict
from appliance.localization.local_frame import LocalFrame
from appliance.routes import (
    Route,
    RouteFileError,
    RouteStore,
    check_route,
    min_turn_radius_m,
    routes_dir,
)
from appliance.routes.store import ROUTE_SUFFIX
from drivers.geometry import Pose2D
from drivers.gnss.sentences import FixQuality
from drivers.pc104.messages import MotionPattern

NEARBY_LIMIT = 5  # routes listed in the status, nearest first
WINDOW_RADIUS_M = 30.0  # the operator page's route view is 60 m across
WINDOW_POINTS = 400


def follow_params(
    config: VehicleConfig, schedule: LookaheadSchedule | None = None
) -> RouteFollowParams:
    """The chain's parameters from the vehicle file; the look-ahead ``schedule`` tuned on
    the vehicle where there is one (the calibration file's), else the tracker's default."""
    positioning, route = config.positioning, config.route
    pursuit = PursuitParams.from_config(config)
    if schedule is not None:
        pursuit = replace(pursuit, schedule=schedule)
    return RouteFollowParams(
        pursuit=pursuit,
        profile=SpeedProfileParams(lateral_accel_mps2=route.lateral_accel_mps2),
        fix=FixVerdictParams(
            max_fix_age_s=positioning.max_fix_age_s,
            max_sigma_m=positioning.max_sigma_m,
            accepted_qualities=tuple(
                FixQuality[name.upper()] for name in positioning.accepted_fix_qualities
            ),
            min_satellites=positioning.min_satellites,
        ),
        antenna_forward_m=positioning.antenna_forward_m,
        antenna_left_m=positioning.antenna_left_m,
        counter_steer_ratio_k=config.geometry.counter_steer_ratio_k,
        engage_max_distance_m=route.max_engage_distance_m,
        engage_max_heading_rad=math.radians(route.max_engage_heading_deg),
    )


def tuning_params(config: VehicleConfig) -> TuningParams:
    """The look-ahead tuning's runs for ``config`` (the daemon's, the step's and the
    simulation's: one list, so a run's number means the same run everywhere)."""
    return config.lookahead_tuning.params(PursuitParams.from_config(config).turn_floor_m)


class RouteAutopilot:
    """The `route` source (see the module)."""

    name = "route"

    def __init__(
        self,
        config: VehicleConfig,
        store: RouteStore | None = None,
        schedule: LookaheadSchedule | None = None,
    ) -> None:
        origin = config.positioning.origin
        if origin is None:
            raise ValueError("the route source needs positioning.origin")
        self.config = config
        self.frame = LocalFrame(origin.lat_deg, origin.lon_deg, origin.alt_m)
        self.store = store if store is not None else RouteStore(routes_dir(config))
        self.params = follow_params(config, schedule)
        # The look-ahead tuning's runs, while `dbw calibrate lookahead` has them armed.
        self.tuning: RouteTuning | None = None
        self.max_speed_mps = min(config.limits.max_speed_mps, config.engagement.max_set_speed_mps)
        self.route: Route | None = None
        self.follower: RouteFollower | None = None
        self.selection_problem = "no route selected"
        self._gnss_seq: int | None = None
        self._last_speed_mps = 0.0
        self._last_steer_rad = 0.0
        self._last_pose: Pose2D | None = None
        self._points_cache: dict[str, tuple[tuple[int, int, int], np.ndarray | None]] = {}
        if config.route.selected:
            self.select(config.route.selected)

    # ---- selection ---------------------------------------------------------------------
    def select(self, name: str) -> tuple[bool, str]:
        """Load route ``name`` from the store and follow it from the next engagement; the
        route stays as it was if this one cannot be used (and says why)."""
        try:
            route = self.store.load(name)
            points = route.points_enu_m(self.frame)
        except (RouteFileError, OSError, ValueError) as exc:
            return False, f"route {name!r} not selected: {exc}"
        report = check_route(points, min_turn_radius_m(self.config), frame=self.frame)
        refusals = [p.message for p in report.problems if p.severity.value == "refused"]
        if refusals:
            return False, f"route {name!r} not selected: " + "; ".join(refusals[:3])
        previous = self.follower
        self.route = route
        self.follower = RouteFollower(
            self.params,
            points,
            allowed=route.directions.value,
            speed_limit_mps=route.speed_limit_mps,
        )
        if previous is not None and previous.last_fix is not None:
            self.follower.update_fix(previous.last_fix, previous.last_fix.measurement_time_s)
        self.selection_problem = ""
        return True, f"route {route.name!r} selected ({route.length_m:.0f} m)"

    # ---- the look-ahead tuning -------------------------------------------------------
    def start_tuning(self, first_run: int) -> tuple[bool, str]:
        """Arm the tuning's runs from ``first_run``: the source drives their courses (laid
        where the vehicle stands) until :meth:`stop_tuning`."""
        params = tuning_params(self.config)
        runs = len(params.runs)
        if not 0 <= first_run < runs:
            return False, f"the look-ahead tuning has runs 0..{runs - 1}, not {first_run}"
        self.tuning = RouteTuning(self.params, params, first_run)
        return True, f"the look-ahead tuning is armed at run {first_run + 1} of {runs}"

    def stop_tuning(self, engaged: bool) -> str:
        """Disarm: at once when not engaged; engaged, the course is kept at speed 0 (the
        vehicle stops and holds on it) until the operator disengages."""
        tuning = self.tuning
        if tuning is None:
            return ""
        if engaged:
            tuning.stopping = True
            return "; stopping on the tuning course: disengage to take over"
        self.tuning = None
        return ""

    # ---- the seam ----------------------------------------------------------------------
    def reset(self) -> None:
        if self.tuning is not None:
            self.tuning.reset(self._last_speed_mps, self._last_steer_rad)
        if self.follower is not None:
            self.follower.reset(self._last_speed_mps, self._last_steer_rad)

    def update(self, observation: Observation) -> AutopilotWish:
        speed = observation.speed_mps
        steer = observation.steer_tyre_rad
        self._last_speed_mps = speed if speed is not None and math.isfinite(speed) else 0.0
        self._last_steer_rad = steer if steer is not None and math.isfinite(steer) else 0.0
        tuning = self.tuning
        if tuning is not None:
            if tuning.stopping and not observation.engaged:
                self.tuning = None
            else:
                tuned = tuning.update(observation, speed, self._last_steer_rad)
                self._last_pose = tuned.pose or self._last_pose
                return tuned
        follower = self.follower
        if follower is None:
            return AutopilotWish(ready=False, reason=self.selection_problem, status=self._status())
        if observation.gnss is not None and observation.gnss_seq != self._gnss_seq:
            self._gnss_seq = observation.gnss_seq
            follower.update_fix(observation.gnss, observation.now_s)
        if speed is None or not math.isfinite(speed):
            # The speed comes from the same receiver: a lost fix is the cause to state.
            verdict = fix_verdict(follower.last_fix, observation.now_s, follower.params.fix)
            reason = "speed unknown" if verdict.ok else verdict.reason
            return AutopilotWish(ready=False, reason=reason, status=self._status())
        wish = follower.update(
            observation.now_s, speed, self.max_speed_mps, observation.engaged, steer
        )
        self._last_pose = wish.pose
        status = self._status() | {"follow": wish.status}
        if not wish.ready:
            return AutopilotWish(ready=False, reason=wish.reason, status=status)
        return AutopilotWish(
            ready=True,
            steer_tyre_rad=wish.front_steer_rad,
            max_speed_mps=wish.target_speed_mps if observation.engaged else None,
            pattern=MotionPattern.COUNTER_STEER,
            status=status,
            pose=wish.pose,
        )

    # ---- status ------------------------------------------------------------------------
    def _status(self) -> dict[str, Any]:
        route = self.route
        return {
            "route": None if route is None else route.name,
            "route_length_m": None if route is None else round(route.length_m, 1),
            "route_speed_limit_mps": None if route is None else route.speed_limit_mps,
            "selection": self.selection_problem or "ok",
        }

    def route_window(self, radius_m: float = WINDOW_RADIUS_M) -> dict[str, Any]:
        """The selected route's points within ``radius_m`` of the vehicle's last pose, in
        the local east-north frame (the operator page draws them, as Stanley et al.'s
        GUI did); at most ``WINDOW_POINTS``, evenly thinned. Asked at status time."""
        pose, follower = self._last_pose, self.follower
        if pose is None or follower is None:
            return {"points_m": [], "radius_m": radius_m}
        points = np.asarray(follower.route_m, dtype=float)
        near = points[np.hypot(points[:, 0] - pose.x_m, points[:, 1] - pose.y_m) <= radius_m]
        if len(near) > WINDOW_POINTS:
            near = near[np.linspace(0, len(near) - 1, WINDOW_POINTS).astype(int)]
        return {
            "points_m": [[round(float(e), 3), round(float(n), 3)] for e, n in near],
            "radius_m": radius_m,
        }

    def _stored_points(self) -> dict[str, np.ndarray]:
        """Every readable stored route's points, parsed again only when its file changed.

        Why the cache: the status (asked for by `dbw status`, the operator page, the
        heartbeat) lists the routes nearby, and it runs on the event loop; parsing every
        route file on every call would stall the loop for as long as the files take. A
        stat per file stays: a route recorded or replaced while the daemon runs is seen.
        """
        directory = self.store.directory
        try:
            paths = sorted(directory.glob(f"*{ROUTE_SUFFIX}"))
        except OSError:
            return {}
        cache = self._points_cache
        seen: dict[str, np.ndarray] = {}
        for path in paths:
            name = path.name[: -len(ROUTE_SUFFIX)]
            if name.startswith("."):
                continue  # the atomic writer's temporary files
            try:
                stat = path.stat()
            except OSError:
                continue
            key = (stat.st_ino, stat.st_mtime_ns, stat.st_size)  # atomic writes: a new inode
            cached = cache.get(name)
            if cached is None or cached[0] != key:
                try:
                    points: np.ndarray | None = self.store.load(name).points_enu_m(self.frame)
                except (RouteFileError, OSError, ValueError):
                    points = None  # unreadable: listed by `dbw route list`, not nearby
                cached = cache[name] = (key, points)
            if cached[1] is not None:
                seen[name] = cached[1]
        for gone in set(cache) - {p.name[: -len(ROUTE_SUFFIX)] for p in paths}:
            del cache[gone]
        return seen

    def nearby(self) -> list[dict[str, Any]]:
        """Stored routes near the vehicle's last pose, nearest first, and whether
        engagement would be allowed by distance and heading (for `dbw status`)."""
        pose = self._last_pose
        if pose is None:
            return []
        found = []
        for name, points in self._stored_points().items():
            distance, heading_error = _distance_and_heading(points, pose)
            allowed = (
                distance <= self.params.engage_max_distance_m
                and heading_error <= self.params.engage_max_heading_rad
            )
            found.append(
                {
                    "name": name,
                    "distance_m": round(distance, 1),
                    "heading_error_deg": round(math.degrees(heading_error), 1),
                    "engage_allowed": allowed,
                }
            )
        found.sort(key=lambda r: float(str(r["distance_m"])))
        return found[:NEARBY_LIMIT]


def _distance_and_heading(points: np.ndarray, pose: Pose2D) -> tuple[float, float]:
    """Distance from ``pose`` to the polyline, and the heading's angle to its nearest
    segment either way (a route can be driven both ways; the selection says which)."""
    start, end = points[:-1], points[1:]
    delta = end - start
    length2 = np.maximum(np.einsum("ij,ij->i", delta, delta), 1e-12)
    here = np.array([pose.x_m, pose.y_m])
    along = np.clip(np.einsum("ij,ij->i", here - start, delta) / length2, 0.0, 1.0)
    gap = np.hypot(*(start + along[:, None] * delta - here).T)
    nearest = int(np.argmin(gap))
    tangent = math.atan2(float(delta[nearest, 1]), float(delta[nearest, 0]))
    off = abs(math.remainder(pose.yaw_rad - tangent, math.tau))
    return float(gap[nearest]), min(off, math.pi - off)
