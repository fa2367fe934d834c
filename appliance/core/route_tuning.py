"""The look-ahead tuning runs on the route source's chain (`dbw calibrate lookahead`).

While the tuning is armed the route source drives its courses instead of the selected
route: a follower of its own (its localization warmed from the fixes from arming on), the
run's candidate schedule in its tracker, its speed capped at the run's speed, and the
program (``appliance.guidance.lookahead_tuning``) laying the courses. Everything else is
the route's: the same wish, judged by the same mode machine and safety layer.

Disarmed while engaged (the command stopped, Ctrl-C, the client gone), the tuning does not
hand the vehicle to a route that may be anywhere: it stays on its course with the speed
capped at 0 (the speed controller stops and holds) until the operator disengages.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from appliance.config.models import VehicleConfig
from appliance.config.tuning_models import tuning_problems
from appliance.core.wish import AutopilotWish, Observation
from appliance.guidance.lookahead_tuning import (
    LookaheadTuning,
    TuningParams,
    TuningPhase,
    TuningStep,
    course_points,
)
from appliance.guidance.route_follow import RouteFollower, RouteFollowParams
from appliance.localization.gnss_pose import GnssPose
from appliance.modes import Mode
from appliance.routes import min_turn_radius_m
from drivers.geometry import Pose2D
from drivers.pc104.messages import MotionPattern


class RouteTuning:
    """One armed tuning (see the module); ``update()`` once per cycle."""

    def __init__(self, params: RouteFollowParams, tuning: TuningParams, first_run: int) -> None:
        self.params = params
        self.program = LookaheadTuning(tuning)
        self.program.reset(first_run)
        self.follower: RouteFollower | None = None
        self.stopping = False
        self.last: TuningStep | None = None
        self._gnss_seq: int | None = None
        self._schedule_run: int | None = None

    def reset(self, speed_mps: float, steer_rad: float) -> None:
        """A new engagement: the follower's tracker and speed start from the vehicle's."""
        if self.follower is not None:
            self.follower.reset(speed_mps, steer_rad)

    def _first_follower(self, fix: GnssPose) -> RouteFollower | None:
        """A follower on a course laid at the first fix (the program lays its own once the
        blended pose is there): a route chain needs a route to take fixes."""
        run = self.program.run
        if run is None or fix.yaw_rad is None or not math.isfinite(fix.yaw_rad):
            return None
        course = course_points(
            Pose2D(fix.east_m, fix.north_m, fix.yaw_rad), run, self.program.params
        )
        return RouteFollower(self.params, course, allowed="forward")

    def update(self, observation: Observation, speed: float | None, steer: float) -> AutopilotWish:
        engaged = observation.engaged
        fix = observation.gnss
        if self.follower is None and isinstance(fix, GnssPose):
            self.follower = self._first_follower(fix)
        follower = self.follower
        if follower is None:
            return AutopilotWish(ready=False, reason="look-ahead tuning: waiting for a fix")
        if fix is not None and observation.gnss_seq != self._gnss_seq:
            self._gnss_seq = observation.gnss_seq
            follower.update_fix(fix, observation.now_s)
        if speed is None or not math.isfinite(speed):
            return AutopilotWish(ready=False, reason="speed unknown")
        run = self.program.run
        if run is not None and not engaged and self._schedule_run != run.index:
            follower.set_schedule(run.schedule)
            self._schedule_run = run.index
        set_speed = 0.0 if self.stopping or run is None else run.speed_mps
        wish = follower.update(observation.now_s, speed, set_speed, engaged, steer)
        planned = wish.planner
        if self.stopping:  # the course stays as it is: nothing laid, the program not asked
            last = self.last or TuningStep(TuningPhase.DONE, None, len(self.program.params.runs))
            step = replace(last, lay=None)
        else:
            progress = None if planned is None else planned.progress_m
            step = self.program.update(engaged, speed, wish.pose, progress, observation.now_s)
            self.last = step
        if step.lay is not None:
            follower.replace_route(step.lay)
        status: dict[str, Any] = {"tuning": step.as_status(), "follow": wish.status}
        tracked = wish.tracker
        # The cycle the course moves, the error was against the one it leaves: not the test's.
        moved = step.lay is not None
        status["tuning"] |= {
            "cross_track_m": None if planned is None or moved else planned.cross_track_m,
            "lookahead_m": None if tracked is None else tracked.lookahead_m,
            "stopping": self.stopping,
        }
        if not wish.ready:
            return AutopilotWish(ready=False, reason=wish.reason, status=status, pose=wish.pose)
        if not engaged and step.reason:
            return AutopilotWish(ready=False, reason=step.reason, status=status, pose=wish.pose)
        return AutopilotWish(
            ready=True,
            steer_tyre_rad=wish.front_steer_rad,
            max_speed_mps=wish.target_speed_mps if engaged else None,
            pattern=MotionPattern.COUNTER_STEER,
            status=status,
            pose=wish.pose,
        )


def tuning_refusal(config: VehicleConfig, source: object, mode: Mode, run_text: str) -> str | None:
    """Why the look-ahead runs may not be armed now (None: they may): on the route source,
    from READY (the operator engages knowingly, run by run), with runs the vehicle can
    drive as asked; a resumed tuning from one of its runs."""
    if getattr(source, "name", None) != "route":
        return 'the look-ahead runs need engagement.autopilot_source = "route"'
    tuning = config.lookahead_tuning
    problems = tuning_problems(
        tuning,
        config.limits,
        config.engagement,
        min_turn_radius_m(config),
        config.route.lateral_accel_mps2,
    )
    if problems:
        return "the vehicle file's [lookahead_tuning] does not fit: " + "; ".join(problems)
    if run_text and not run_text.isdigit():
        return f"the look-ahead runs resume from a run number, not {run_text!r}"
    if mode is not Mode.READY:
        return f"the look-ahead runs start from READY, not {mode}"
    return None
