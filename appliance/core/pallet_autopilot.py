"""The `pallet` autopilot source: Kinouchi et al.'s forklift to a pallet it cannot see.

What it does, cycle by cycle, with nothing longer than a scan's work in the cycle:

1. localizes on the site's posts (`LandmarkLocalizer`, the vehicle file's
   ``[[pallets.landmarks]]``), with the rear-steer odometry of the pot and the speed;
2. standing localized, finds its own pallets in both scanners' scans and merges the
   worker's map (``pallets.worker_map``, from the floor marker's T0) into them: a
   background job (`appliance.core.jobs`), tried again every few seconds until it holds;
3. when the worker selects a pallet (the tablet's "Select the object"), plans the way
   to where the scanners see inside its reference area: a job too (about a second),
   asked for with the vehicle standing;
4. engaged (the tablet's button held), drives the plan (`PalletApproach`): to the view
   pose, looks again, the last straight along what it sees, stops with the fork tips at
   the openings; a pallet found too far off the line is planned again from the
   detection (at most ``MAX_REPLANS`` times), standing.

Every step that cannot be trusted refuses in words the worker can act on ("no pallet
selected", "planning the way to row_b.r0c1", "the maps are not merged: ..."); a refusal
while engaged is a fault in the core, so the vehicle stops. Letting go of the button
pauses the approach (the plan and what was seen are kept), pressing again goes on.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from functools import partial
from typing import Any

import numpy as np

from appliance.config import parts
from appliance.config.calibration import Calibration
from appliance.config.models import VehicleConfig
from appliance.core.jobs import InlineJobs, JobOutcome, Jobs
from appliance.core.pallet_parts import (
    approach_params,
    landmark_map,
    load_worker_map,
    merge_params,
    plan_params,
    site_obstacles,
    vehicle_shape,
)
from appliance.core.pallet_work import (
    ScanView,
    SiteMerge,
    estimate_document,
    merge_from_scans,
    merged_names,
    order_document,
    pallet_document,
    path_document,
    scan_pallets,
)
from appliance.core.wish import AutopilotWish, Observation
from appliance.guidance.pallet_approach import PalletApproach, PalletOrder, PalletPhase
from appliance.guidance.pallet_plan import (
    PalletPlan,
    PalletTarget,
    PlanRefusal,
    plan_pallet_approach,
)
from appliance.guidance.wheel_follow import WheelFollower, WheelFollowParams
from appliance.localization.landmark_localizer import (
    LandmarkEstimate,
    LandmarkLocalizer,
    LandmarkStatus,
)
from appliance.localization.localizer_params import ScannerSetup
from appliance.mapping.map_file import MapFileError
from appliance.mapping.merge import MergedPallet
from appliance.mapping.pallets import Pallet, PalletMap
from drivers.geometry import Pose2D
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, MountedScan
from drivers.pc104.messages import MotionPattern, PoseState

MAX_REPLANS = 2
STANDING_MPS = 0.02
MERGE_RETRY_S = 5.0
# A plan made before the engagement is made again if the vehicle stands this far from
# where it was planned from (the operator drove it meanwhile).
REPLAN_MOVED_M = 0.10
REPLAN_MOVED_RAD = math.radians(3.0)
# A detection is the target's when of its kind and this near where it is expected.
DETECTION_GATE_M = 0.6


class PalletAutopilot:
    """The `pallet` source (see the module)."""

    name = "pallet"

    def __init__(
        self,
        config: VehicleConfig,
        calibration: Calibration | None = None,
        jobs: Jobs | None = None,
        *,
        scanners: Mapping[str, ScannerSetup] | None = None,
        worker: PalletMap | None = None,
        worker_problem: str = "",
        worker_alternatives: Sequence[Pallet] = (),
    ) -> None:
        """``scanners`` and ``worker`` in place of the calibration's and the vehicle
        file's (the simulation draws its own; a replay has the recorded map, or the
        recorded ``worker_problem`` when there was none)."""
        self.config = config
        self.jobs: Jobs = jobs if jobs is not None else InlineJobs()
        self.setups = (
            dict(scanners) if scanners is not None else parts.scanner_setups(config, calibration)
        )
        self.localizer = LandmarkLocalizer(self.setups, landmark_map(config))
        self.shape = vehicle_shape(config, calibration)
        self.planning = plan_params(config)
        self.approach_params = approach_params(config, calibration)
        self.obstacles = site_obstacles(config, self.planning.clearance_m)
        self.wheels = WheelFollower(
            WheelFollowParams(self.approach_params.max_steer_rate_rad_per_s)
        )
        marker = config.pallets.worker_marker
        self.marker = Pose2D(marker.x_m, marker.y_m, math.radians(marker.yaw_deg))
        self.merge_params = merge_params(config)
        self.worker: PalletMap | None = worker
        self.worker_problem = worker_problem
        # A cloud's faces read as each kind: they may fix the merge, never join the map.
        self.worker_alternatives = tuple(worker_alternatives)
        if worker is None and not worker_problem:
            try:
                read = load_worker_map(config.pallets.worker_map)
                self.worker, self.worker_alternatives = read.pallet_map, read.alternatives
            except MapFileError as exc:
                self.worker_problem = str(exc)
        self.forget()

    # ---- the seam ----------------------------------------------------------------------
    def forget(self) -> None:
        """Everything but the worker's map: the source as it was built."""
        self.localizer.reset()
        # The latest scan of each scanner of the setups, by name (fed once each).
        self._seen: dict[str, MountedScan] = {}
        self.site: SiteMerge | None = None
        self.merge_problem = "the maps are not merged yet: the vehicle stands localized first"
        self.names: tuple[str, ...] = ()
        self._next_merge_s = -math.inf
        self._pending: tuple[float, str] | None = None  # (job key, "merge" | "plan")
        self.target: str | None = None
        self._plan_wanted = False
        self._planned_from: Pose2D | None = None
        self._target_pallet: Pallet | None = None  # what a re-plan is made for
        self.plan: PalletPlan | None = None
        self.plan_problem = ""
        self.controller: PalletApproach | None = None
        self.replans = 0
        self._driven = False  # the controller has been stepped engaged since the plan
        self._paused = True
        self._last: dict[str, Any] = {}
        self.wheels.reset()

    def reset(self) -> None:
        """An engagement (or the loop restarted): the approach goes on where it was, as
        the worker's hold-to-move pauses it; only its waiting clocks start again."""
        self._paused = True

    def update(self, observation: Observation) -> AutopilotWish:
        now_s = observation.now_s
        if observation.speed_mps is not None and observation.steer_tyre_rad is not None:
            self.localizer.odometry(
                now_s,
                observation.speed_mps,
                observation.steer_tyre_rad,
                self.config.geometry.wheelbase_m,
                characteristic_speed_mps=self.config.geometry.characteristic_speed_mps,
            )
        fresh = self._feed(observation.scans, now_s)
        estimate = self.localizer.estimate(now_s)
        self._take_jobs(observation.jobs_done)
        standing = observation.speed_mps is not None and abs(observation.speed_mps) < STANDING_MPS
        localized = estimate.status is LandmarkStatus.OK and estimate.pose is not None
        if localized and standing and self._pending is None:
            self._start_work(estimate, now_s)
        if not observation.engaged:
            self._paused = True
            self.wheels.reset()
            return self._standing_wish(estimate, observation)
        return self._engaged_wish(estimate, observation, fresh, standing)

    # ---- selection (the tablet's "Select the object") ------------------------------------
    def select_pallet(self, name: str) -> tuple[bool, str]:
        """The pallet to go to, by its name in the merged map; planned from where the
        vehicle stands. The core refuses it while engaged."""
        if self.site is None or self.site.result is None:
            return False, self.merge_problem
        if name not in self.names:
            return False, f"no pallet {name!r} in the merged map"
        self.target = name
        self._target_pallet = self.site.result.pallets[self.names.index(name)].pallet
        self._new_plan_wanted()
        self.replans = 0
        return True, f"{name} selected: planning the way"

    def _new_plan_wanted(self) -> None:
        self._plan_wanted = True
        self.plan, self.controller, self.plan_problem = None, None, ""
        self._driven = False

    # ---- scans and background work -----------------------------------------------------
    def _feed(
        self, scans: Mapping[str, MountedScan | None], now_s: float
    ) -> list[tuple[str, MountedScan]]:
        fresh = []
        for name, mounted in scans.items():
            if mounted is None or self._seen.get(name) is mounted or name not in self.setups:
                continue
            self._seen[name] = mounted
            angles = mounted.scan.angles_rad - DEVICE_FORWARD_RAD
            self.localizer.update(
                name, mounted.scan.ranges_m, angles, mounted.host_receive_time_s, now_s
            )
            fresh.append((name, mounted))
        return fresh

    def _view(self, name: str, mounted: MountedScan, pose: Pose2D) -> ScanView:
        setup = self.setups[name]
        ranges = mounted.scan.ranges_m
        corrected = np.where(ranges > 0.0, ranges - setup.range_offset_m, 0.0)
        return ScanView(
            name,
            corrected,
            mounted.scan.angles_rad - DEVICE_FORWARD_RAD,
            pose.compose(setup.mount),
        )

    def _start_work(self, estimate: LandmarkEstimate, now_s: float) -> None:
        """Standing localized with nothing pending: merge if not merged, plan if wanted."""
        pose = estimate.pose
        assert pose is not None
        if self.site is None or self.site.result is None:
            if self.worker is None or now_s < self._next_merge_s:
                return
            if set(self._seen) != set(self.setups):
                return
            views = tuple(self._view(name, m, pose) for name, m in self._seen.items())
            merge = partial(
                merge_from_scans,
                views,
                self.worker,
                self.marker,
                self.merge_params,
                self.config.pallets.kinds,
                self.worker_alternatives,
            )
            self._submit(now_s, "merge", merge)
            self._next_merge_s = now_s + MERGE_RETRY_S
            return
        if self._plan_wanted and self._target_pallet is not None:
            self._plan_wanted = False
            self._planned_from = pose
            entry = self._merged_target()
            merged = entry is not None and entry.pallet is self._target_pallet
            # The merged map's pallets, the target as it is now known (a re-plan's is
            # the detection, in place of the map's).
            pallets = [
                p.pallet for p in self.site.result.pallets if entry is None or p is not entry
            ]
            pallets.append(self._target_pallet)
            target = (
                PalletTarget.from_merged(entry)
                if entry is not None and merged
                else PalletTarget(self._target_pallet)
            )
            plan = partial(
                plan_pallet_approach,
                pose,
                target,
                pallets,
                self.shape,
                self.planning,
                self.obstacles,
            )
            self._submit(now_s, "plan", plan)

    def _merged_target(self) -> MergedPallet | None:
        if self.site is None or self.site.result is None or self.target not in self.names:
            return None
        return self.site.result.pallets[self.names.index(self.target)]

    def _submit(self, key: float, kind: str, work: Callable[[], object]) -> None:
        self._pending = (key, kind)
        self.jobs.submit(key, work)

    def _take_jobs(self, done: tuple[float, ...]) -> None:
        if self._pending is None or self._pending[0] not in done:
            return
        key, kind = self._pending
        self._pending = None
        outcome = self.jobs.result(key) or JobOutcome(error="its result is gone")
        if kind == "merge":
            self._merged(outcome)
        elif not self._plan_wanted:  # else a newer selection's plan is still to come
            self._planned(outcome)

    def _merged(self, outcome: JobOutcome) -> None:
        site = outcome.value
        if outcome.error or not isinstance(site, SiteMerge):
            self.merge_problem = f"the maps are not merged: {outcome.error or 'no result'}"
            return
        if site.result is None or self.worker is None:
            self.merge_problem = f"the maps are not merged: {site.refused}"
            return
        self.site = site
        self.names = merged_names(site.result, self.worker)
        self.merge_problem = ""

    def _planned(self, outcome: JobOutcome) -> None:
        plan = outcome.value
        if isinstance(plan, PalletPlan):
            self.plan = plan
            self.controller = PalletApproach(plan, self.approach_params)
            self.plan_problem = ""
            return
        why = plan.reason if isinstance(plan, PlanRefusal) else outcome.error or "no result"
        self.plan, self.controller = None, None
        self.plan_problem = f"no way to {self.target}: {why}"

    # ---- wishes ------------------------------------------------------------------------
    def _refusal(self, estimate: LandmarkEstimate) -> str:
        """Why the worker cannot start (or go on with) a guidance now; "" if they can."""
        if self.worker_problem:
            return self.worker_problem
        if estimate.status is not LandmarkStatus.OK or estimate.pose is None:
            return f"no pose from the posts ({estimate.status}): {estimate.reason}"
        if self.site is None or self.site.result is None:
            return self.merge_problem
        if self.target is None:
            return "no pallet selected: select one on the tablet"
        if (self._pending is not None and self._pending[1] == "plan") or self._plan_wanted:
            return f"planning the way to {self.target}"
        if self.controller is None:
            return self.plan_problem or f"no way to {self.target}"
        if self.controller.phase is PalletPhase.DONE:
            return f"at {self.target}: the forks at its openings; select the next pallet"
        if self.controller.phase is PalletPhase.REFUSED:
            return f"the approach to {self.target} stopped: {self.controller.refused}"
        return ""

    def _standing_wish(self, estimate: LandmarkEstimate, observation: Observation) -> AutopilotWish:
        if (
            self.controller is not None
            and not self._driven
            and self._planned_from is not None
            and estimate.pose is not None
            and self._pending is None
        ):
            moved = self._planned_from
            off_m = math.hypot(estimate.pose.x_m - moved.x_m, estimate.pose.y_m - moved.y_m)
            off_rad = abs(math.remainder(estimate.pose.yaw_rad - moved.yaw_rad, math.tau))
            if off_m > REPLAN_MOVED_M or off_rad > REPLAN_MOVED_RAD:
                self._new_plan_wanted()  # driven by hand since: planned again, standing
        reason = self._refusal(estimate)
        steer = observation.steer_tyre_rad or 0.0
        return self._wish(not reason, reason, estimate, 0.0, steer, None)

    def _engaged_wish(
        self,
        estimate: LandmarkEstimate,
        observation: Observation,
        fresh: list[tuple[str, MountedScan]],
        standing: bool,
    ) -> AutopilotWish:
        now_s = observation.now_s
        steer = observation.steer_tyre_rad or 0.0
        if self._pending is not None and self._pending[1] == "plan" and self.replans:
            return self._wish(True, "", estimate, 0.0, steer, None, "planning again")
        controller = self.controller
        if controller is None:
            why = self._refusal(estimate) or "no plan"
            return self._wish(False, why, estimate, 0.0, steer, None)
        if self._paused:
            controller.resume(now_s)
            self._paused = False
        usable = estimate.status in (LandmarkStatus.OK, LandmarkStatus.DEGRADED)
        speed = observation.speed_mps if observation.speed_mps is not None else math.nan
        order = controller.update(
            estimate.pose if usable else None,
            estimate.covariance if usable else None,
            speed,
            now_s,
            self._detection(controller, fresh),
        )
        self._driven = True
        if order.phase is PalletPhase.REFUSED:
            if not standing:
                return self._wish(True, "", estimate, 0.0, order.steer_rad, order, "stopping")
            again = controller.detected_pallet if controller.plan_again else None
            if again is not None and self.replans < MAX_REPLANS and self.site is not None:
                self.replans += 1
                self._target_pallet = again
                self._new_plan_wanted()
                if estimate.pose is not None and estimate.status is LandmarkStatus.OK:
                    self._start_work(estimate, now_s)
                return self._wish(True, "", estimate, 0.0, steer, order, "planning again")
            return self._wish(False, self._refusal(estimate), estimate, 0.0, steer, order)
        steer, share = self.wheels.update(order.steer_rad, observation.steer_tyre_rad, now_s)
        return self._wish(True, "", estimate, order.speed_mps * share, steer, order)

    def _detection(
        self, controller: PalletApproach, fresh: list[tuple[str, MountedScan]]
    ) -> Pallet | None:
        """The target in this cycle's newest scan, looking again or going in."""
        if controller.phase not in (PalletPhase.REDETECT, PalletPhase.FINAL) or not fresh:
            return None
        expected = controller.detected_pallet or controller.plan.target
        name, mounted = max(fresh, key=lambda named: named[1].host_receive_time_s)
        at_scan = self.localizer.estimate(mounted.host_receive_time_s)
        if at_scan.pose is None:
            return None
        found = None
        for pallet in scan_pallets(self._view(name, mounted, at_scan.pose), (expected.kind,)):
            near_m = math.hypot(pallet.x_m - expected.x_m, pallet.y_m - expected.y_m)
            if pallet.kind is expected.kind and near_m < DETECTION_GATE_M:
                found = pallet
        return found

    def _wish(
        self,
        ready: bool,
        reason: str,
        estimate: LandmarkEstimate,
        speed_mps: float,
        steer_rad: float,
        order: PalletOrder | None,
        doing: str = "",
    ) -> AutopilotWish:
        status = self._status(estimate, order, doing, reason)
        self._last = status
        pose_state = {
            LandmarkStatus.OK: PoseState.OK,
            LandmarkStatus.DEGRADED: PoseState.DEGRADED,
        }.get(estimate.status, PoseState.LOST)
        expected = None
        if order is not None and order.phase is PalletPhase.TO_VIEW and self.plan is not None:
            expected = self.plan.view_pose
        return AutopilotWish(
            ready=ready,
            reason=reason,
            # The kit's servo turns the rear wheels: positive turns the vehicle left (the
            # pot's sense); the PC104's rear row angle is physical, so the other way.
            steer_tyre_rad=steer_rad,
            rear_steer_rad=-steer_rad,
            pattern=MotionPattern.REAR_STEER,
            max_speed_mps=self.approach_params.cruise_speed_mps,
            speed_mps=speed_mps,
            status=status,
            pose=estimate.pose,
            pose_state=pose_state,
            expected_pose=expected,
        )

    # ---- what is shown -----------------------------------------------------------------
    def _status(
        self, estimate: LandmarkEstimate, order: PalletOrder | None, doing: str, reason: str
    ) -> dict[str, Any]:
        phase = doing or (
            str(order.phase)
            if order is not None
            else str(self.controller.phase)
            if self.controller is not None
            else "waiting"
        )
        status: dict[str, Any] = {
            "localization": estimate_document(estimate),
            "merged": self.site is not None and self.site.result is not None,
            "target": self.target,
            "phase": phase,
            "replans": self.replans,
        }
        if reason:
            status["refused"] = reason
        if order is not None:
            status["approach"] = order_document(order)
        return status

    def state_for_tablet(self) -> dict[str, Any]:
        """What the tablet draws: the merged map, the plan's path, the vehicle, the phase."""
        document: dict[str, Any] = {
            "target": self.target,
            "phase": self._last.get("phase", "waiting"),
            "reason": self._last.get("refused", ""),
        }
        if self.site is not None and self.site.result is not None:
            document["pallets"] = [
                pallet_document(name, entry)
                for name, entry in zip(self.names, self.site.result.pallets, strict=True)
            ]
        if self.plan is not None:
            document["path"] = path_document(self.plan)
        pose = self._last.get("localization", {}).get("pose")
        if pose is not None:
            document["vehicle"] = pose
        return document
