"""One guidance to a pallet in the blind area, faster than real time: `dbw sim pallet`.

Kinouchi et al.'s whole flow on the simulated forklift in the `pallets` site: a worker
walks the storage area with a consumer 3D terminal (`worker_terminal`: the marker's
error, the drift); its pallets are found through the cloud's proximity points; the
vehicle finds its own pallets in its first scans (`scan_pallets`) where its
self-localization on the site's posts puts them; the two maps are merged from the
floor marker's T0; the worker's pallet behind the front row (the vehicle cannot see it)
is the target; the planner finds the entry face and the view pose; the approach drives
there, detects the pallet again in its own scans, and goes in along the detection. The
same perception, localizer, merge, planner and controller as the daemon's, stepped on a
simulated clock; the speed through the PC104 twin's PID. What is judged is the truth:
the fork tips against the true pallet's face.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from appliance.config.models import VehicleConfig
from appliance.core.pallet_parts import approach_params, plan_params, vehicle_shape
from appliance.guidance.pallet_approach import PalletApproach, PalletPhase
from appliance.guidance.pallet_final import face_errors
from appliance.guidance.pallet_geometry import (
    Obstacle,
    disc_obstacle,
    nearest_entry_face,
    wall_obstacle,
)
from appliance.guidance.pallet_plan import PalletTarget, PlanRefusal, plan_pallet_approach
from appliance.localization.landmark_initial import LandmarkMap
from appliance.localization.landmark_localizer import LandmarkLocalizer, LandmarkStatus
from appliance.localization.launcher_map import CylinderLandmark
from appliance.localization.localizer_params import ScannerSetup
from appliance.mapping.cloud_pallets import detect_pallets
from appliance.mapping.merge import MergeParams, MergeRefusal, merge_maps
from appliance.mapping.pallet_fusion import fuse_pallets
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap
from appliance.mapping.scan_pallets import detect_scan_pallets
from appliance.sim.scanner_errors import ScannerErrors, draw_scanner_errors, noise_seed
from appliance.sim.scanner_model import RayCache, beam_angles_rad, render_scan
from appliance.sim.site import Site
from appliance.sim.site_file import load_site
from appliance.sim.terminal_errors import CONSUMER, WORSE
from appliance.sim.twins.pc104_core import PidSpeedController
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from appliance.sim.worker_route import walk_around
from appliance.sim.worker_terminal import object_pallet_map, survey, survey_objects
from drivers.geometry import Pose2D
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, mount_pose
from drivers.pc104.messages import MotionPattern

MARKER = Pose2D(0.0, 0.0, 0.0)  # the floor marker: the worker map's origin, surveyed
SCANNERS = ("left", "right")


@dataclass(frozen=True)
class PalletTrial:
    """One of the paper's three trials: a target in the blind area, a start, a map."""

    target: str
    start: Pose2D
    worse_worker_map: bool = False


TRIALS: dict[int, PalletTrial] = {
    1: PalletTrial("row_b.r0c1", Pose2D(-2.0, -1.5, 0.0)),
    # The paper's n = 2: the worker's terminal at its worst (Fig. 9, centre).
    2: PalletTrial("row_b.r0c0", Pose2D(-2.0, -1.5, 0.0), worse_worker_map=True),
    3: PalletTrial("row_b.r0c2", Pose2D(-1.5, -2.5, math.radians(8.0))),
}


@dataclass(frozen=True)
class PalletRunParams:
    trial: int = 1
    seed: int = 1
    # The worker's map as the terminal hands it over: its 3D cloud (the paper's; pallets
    # found here through proximity points) or the pallets it found itself (an object list).
    worker_form: str = "cloud"
    control_hz: float = 50.0
    world_hz: float = 100.0
    timeout_s: float = 400.0
    # A pallet found again too far off the line the vehicle stands on to go in: plan
    # again from the detection (the paper: "re-plans the final straight approach"), at
    # most this many times.
    max_replans: int = 2
    # The forklift's own odometry: its speed off by a scale, its steering by a bias.
    speed_scale_sigma: float = 0.01
    steer_bias_sigma_rad: float = math.radians(0.2)
    merge: MergeParams = field(default_factory=MergeParams)


@dataclass(frozen=True)
class PalletResult:
    success: bool
    reason: str
    phase: str
    tips_lateral_m: float
    heading_error_deg: float
    tips_along_m: float  # the tips' distance past the face (0: at it)
    translation_error_m: float  # hypot(lateral, along - the configured final gap)
    sim_time_s: float
    wall_time_s: float
    worker_pallets: int
    vehicle_pallets: int
    merge_error_m: float  # the fitted worker frame against its truth
    merge_error_deg: float
    plan_length_m: float
    face: int | None
    trial: int
    seed: int

    @property
    def real_time_factor(self) -> float:
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf


def _failure(
    reason: str, params: PalletRunParams, started: float, **known: float | int
) -> PalletResult:
    nan = math.nan
    values: dict[str, float | int] = {
        "worker_pallets": 0,
        "vehicle_pallets": 0,
        "merge_error_m": nan,
        "merge_error_deg": nan,
        "plan_length_m": nan,
    }
    values.update(known)
    return PalletResult(
        False, reason, "not started", nan, nan, nan, nan, 0.0,
        time.perf_counter() - started, int(values["worker_pallets"]),
        int(values["vehicle_pallets"]), float(values["merge_error_m"]),
        float(values["merge_error_deg"]), float(values["plan_length_m"]), None,
        params.trial, params.seed,
    )  # fmt: skip


def site_obstacles(site: Site, clearance_m: float) -> tuple[Obstacle, ...]:
    """The yard's walls and the posts, which the merged map (pallets only) does not hold."""
    walls = tuple(
        wall_obstacle(s.x0_m, s.y0_m, s.x1_m, s.y1_m, clearance_m, s.name)
        for s in site.segments
        if s.name.startswith("yard")
    )
    posts = tuple(
        disc_obstacle(c.cx_m, c.cy_m, c.radius_m, clearance_m, c.name) for c in site.circles
    )
    return walls + posts


def true_pallet(site: Site, name: str) -> Pallet:
    """The site's pallet ``name`` exactly, as a standard pallet."""
    solid = next(p for p in site.pallets if p.name == name)
    kind = PalletKind.of_size(solid.length_m, solid.width_m)
    if kind is None:
        raise ValueError(f"{name} is {solid.length_m} x {solid.width_m} m: no standard pallet")
    return Pallet(*solid.pose, np.zeros((3, 3)), kind, name)


class _Scanners:
    """The two simulated LMS111 of one run: their drawn errors, and the setup the
    localizer and the detections use (a calibrated one: their true mounts and offsets,
    as `dbw calibrate scanners` measures them)."""

    def __init__(self, config: VehicleConfig, site: Site, seed: int) -> None:
        self.site = site
        endpoint = config.devices.lms111_left
        self.period_s = 1.0 / endpoint.scan_frequency_hz
        self.step_rad = math.radians(endpoint.angular_resolution_deg)
        self.angles = beam_angles_rad(step_rad=self.step_rad) - DEVICE_FORWARD_RAD
        mounts = {
            "left": mount_pose(config.geometry.scanner_left_mount),
            "right": mount_pose(config.geometry.scanner_right_mount),
        }
        self.mounts = mounts
        self.errors: dict[str, ScannerErrors] = {
            name: draw_scanner_errors(seed, i, True) for i, name in enumerate(SCANNERS)
        }
        self.rngs = {
            name: np.random.default_rng(noise_seed(seed, i)) for i, name in enumerate(SCANNERS)
        }
        self.caches = {name: RayCache() for name in SCANNERS}
        self.setups = {
            name: ScannerSetup(
                self.errors[name].true_mount(mounts[name]),
                self.errors[name].range_offset_m,
                0.003,
                math.radians(0.03),
            )
            for name in SCANNERS
        }

    def render(self, name: str, t_s: float, truth: Pose2D) -> np.ndarray:
        ranges, _ = render_scan(
            self.site, t_s, truth, self.mounts[name], rng=self.rngs[name],
            errors=self.errors[name], step_rad=self.step_rad, cache=self.caches[name],
        )  # fmt: skip
        return ranges

    def pallets(self, name: str, ranges: np.ndarray, pose: Pose2D) -> tuple[Pallet, ...]:
        """The pallets of one scan in the site frame, placed by ``pose`` (the estimate)."""
        setup = self.setups[name]
        corrected = np.where(ranges > 0.0, ranges - setup.range_offset_m, 0.0)
        return detect_scan_pallets(corrected, self.angles, pose.compose(setup.mount)).pallets


def run_pallet(config: VehicleConfig, params: PalletRunParams) -> PalletResult:
    started = time.perf_counter()
    if params.worker_form not in ("cloud", "objects"):
        raise ValueError(f"worker_form must be 'cloud' or 'objects', not {params.worker_form!r}")
    trial = TRIALS[params.trial]
    site = load_site(config.simulation.site)
    rng = np.random.default_rng(params.seed)
    truth_target = true_pallet(site, trial.target)
    # The worker's map: a walk with the terminal, its pallets through proximity points.
    errors = WORSE if trial.worse_worker_map else CONSUMER
    if params.worker_form == "objects":
        listed = survey_objects(site, MARKER, errors, rng, viewpoints=walk_around(site))
        worker, worker_in_site = object_pallet_map(listed.objects), listed.t0_true
    else:
        cloud = survey(site, MARKER, walk_around(site), rng=rng, errors=errors)
        worker = detect_pallets(cloud.xyz_m, cloud.origins_m, frame="worker").pallet_map
        worker_in_site = cloud.t0_true
    scanners = _Scanners(config, site, params.seed)
    landmarks = LandmarkMap(
        tuple(
            CylinderLandmark(c.name, c.cx_m, c.cy_m, c.radius_m)
            for c in site.circles
            if c.name.startswith("landmark")
        )
    )
    localizer = LandmarkLocalizer(scanners.setups, landmarks)
    vehicle = VehicleParams.from_config(config)
    state = VehicleState(x_m=trial.start.x_m, y_m=trial.start.y_m, yaw_rad=trial.start.yaw_rad)
    speed_scale = 1.0 + float(rng.normal(0.0, params.speed_scale_sigma))
    steer_bias = float(rng.normal(0.0, params.steer_bias_sigma_rad))
    wheelbase, v_char = config.geometry.wheelbase_m, config.geometry.characteristic_speed_mps
    next_scan = {"left": 0.0, "right": scanners.period_s / 2.0}
    latest: dict[str, np.ndarray] = {}
    t_s = 0.0

    def truth_of(s: VehicleState) -> Pose2D:
        return Pose2D(s.x_m, s.y_m, s.yaw_rad)

    def scan_due(now_s: float) -> list[str]:
        due = []
        for name in SCANNERS:
            if now_s + 1e-9 >= next_scan[name]:
                latest[name] = scanners.render(name, now_s, truth_of(state))
                localizer.update(name, latest[name], scanners.angles, now_s, now_s)
                next_scan[name] += scanners.period_s
                due.append(name)
        return due

    # Standing at the start: the first pose from the posts, and the vehicle's own map.
    while t_s < 3.0:
        localizer.odometry(t_s, 0.0, steer_bias, wheelbase, characteristic_speed_mps=v_char)
        scan_due(t_s)
        t_s += 1.0 / params.world_hz
    estimate = localizer.estimate(t_s)
    if estimate.status is not LandmarkStatus.OK or estimate.pose is None:
        return _failure(f"no first pose: {estimate.reason}", params, started)
    seen = [p for name in SCANNERS for p in scanners.pallets(name, latest[name], estimate.pose)]
    vehicle_map = PalletMap(fuse_pallets(seen, 0.3, math.radians(10.0)), "vehicle")
    counts = {"worker_pallets": len(worker), "vehicle_pallets": len(vehicle_map)}
    merged = merge_maps(vehicle_map, worker, MARKER, params.merge)
    if isinstance(merged, MergeRefusal):
        return _failure(f"maps not merged: {merged.reason}", params, started, **counts)
    fitted, truth_frame = merged.worker_in_vehicle, worker_in_site
    merge_error = {
        "merge_error_m": math.dist(fitted[:2], truth_frame[:2]),
        "merge_error_deg": math.degrees(
            abs(math.remainder(fitted.yaw_rad - truth_frame.yaw_rad, math.tau))
        ),
    }
    # The worker taps the target: the merged pallet where the true one stands.
    chosen = min(
        merged.pallets,
        key=lambda m: math.hypot(m.pallet.x_m - truth_target.x_m, m.pallet.y_m - truth_target.y_m),
    )
    if math.hypot(chosen.pallet.x_m - truth_target.x_m, chosen.pallet.y_m - truth_target.y_m) > 0.5:
        return _failure(
            "the target is not in the merged map", params, started, **counts, **merge_error
        )
    shape = vehicle_shape(config)
    planning = plan_params(config)
    plan = plan_pallet_approach(
        estimate.pose,
        PalletTarget.from_merged(chosen),
        [m.pallet for m in merged.pallets],
        shape,
        planning,
        site_obstacles(site, planning.clearance_m),
    )
    if isinstance(plan, PlanRefusal):
        return _failure(f"no plan: {plan.reason}", params, started, **counts, **merge_error)
    controller = PalletApproach(plan, approach_params(config))
    first_plan, replans = plan, 0
    obstacles = site_obstacles(site, planning.clearance_m)
    others = [m.pallet for m in merged.pallets if m is not chosen]
    pid = PidSpeedController()
    control_dt, world_dt = 1.0 / params.control_hz, 1.0 / params.world_hz
    next_control = t_s
    command = VehicleCommand()
    detection: Pallet | None = None
    order = None
    deadline = t_s + params.timeout_s
    while t_s < deadline:
        localizer.odometry(
            t_s, state.speed_mps * speed_scale, state.rear_steer_rad + steer_bias, wheelbase,
            characteristic_speed_mps=v_char,
        )  # fmt: skip
        due = scan_due(t_s)
        looking = controller.phase in (PalletPhase.REDETECT, PalletPhase.FINAL)
        if looking and due:
            estimate = localizer.estimate(t_s)
            if estimate.pose is not None:
                expected = controller.detected_pallet or chosen.pallet
                for name in due:
                    for found in scanners.pallets(name, latest[name], estimate.pose):
                        near = math.hypot(found.x_m - expected.x_m, found.y_m - expected.y_m)
                        if found.kind is expected.kind and near < 0.6:
                            detection = found
        if t_s + 1e-9 >= next_control:
            next_control += control_dt
            estimate = localizer.estimate(t_s)
            usable = estimate.status in (LandmarkStatus.OK, LandmarkStatus.DEGRADED)
            order = controller.update(
                estimate.pose if usable else None,
                estimate.covariance if usable else None,
                state.speed_mps * speed_scale,
                t_s,
                detection,
            )
            detection = None
            throttle, brake, reverse = pid.update(order.speed_mps, state.speed_mps, control_dt)
            command = VehicleCommand(
                MotionPattern.REAR_STEER, 0.0, order.steer_rad, throttle, brake, reverse
            )
            standing = abs(state.speed_mps) < 1e-4
            seen_again = controller.detected_pallet
            if (
                order.phase is PalletPhase.REFUSED
                and standing
                and seen_again is not None
                and replans < params.max_replans
                and estimate.pose is not None
            ):
                again = plan_pallet_approach(
                    estimate.pose, PalletTarget(seen_again), [*others, seen_again], shape,
                    planning, obstacles,
                )  # fmt: skip
                replans += 1  # tried: a refused plan is not tried again and again
                if not isinstance(again, PlanRefusal):
                    plan = again
                    controller = PalletApproach(plan, approach_params(config))
            elif order.phase in (PalletPhase.DONE, PalletPhase.REFUSED) and standing:
                break
        state = step(state, command, world_dt, vehicle)
        t_s += world_dt
    truth = truth_of(state)
    face = nearest_entry_face(truth_target, plan.face.entry_yaw_rad)
    errors_at = face_errors(
        truth, face, shape.guide_forward_m, shape.tips_forward_m, shape.forks_offset_y_m
    )
    gap_m = config.pallets.final_gap_m
    translation = math.hypot(errors_at.tips_lateral_m, errors_at.tips_along_m + gap_m)
    phase = "timeout" if order is None else str(order.phase)
    reason = "" if order is None else order.refused
    success = order is not None and order.phase is PalletPhase.DONE
    return PalletResult(
        success=success,
        reason=reason if not success else "at the pallet",
        phase=phase if t_s < deadline else "timeout",
        tips_lateral_m=errors_at.tips_lateral_m,
        heading_error_deg=math.degrees(errors_at.heading_rad),
        tips_along_m=errors_at.tips_along_m,
        translation_error_m=translation,
        sim_time_s=t_s,
        wall_time_s=time.perf_counter() - started,
        worker_pallets=len(worker),
        vehicle_pallets=len(vehicle_map),
        plan_length_m=first_plan.length_m,
        face=plan.face.index,
        trial=params.trial,
        seed=params.seed,
        **merge_error,
    )
