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
from dataclasses import dataclass, field, replace

import numpy as np

from appliance.config.models import VehicleConfig
from appliance.core.jobs import InlineJobs
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.core.wish import AutopilotWish, Observation
from appliance.guidance.pallet_approach import PalletPhase
from appliance.guidance.pallet_final import face_errors
from appliance.guidance.pallet_geometry import nearest_entry_face
from appliance.guidance.pallet_plan import PalletPlan
from appliance.localization.localizer_params import ScannerSetup
from appliance.mapping.cloud_pallets import detect_pallets
from appliance.mapping.map_file import cloud_alternatives
from appliance.mapping.merge import MergeParams
from appliance.mapping.pallets import Pallet, PalletKind
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
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, MountedScan, mount_pose
from drivers.lms111.scan import scan_from_ranges
from drivers.pc104.messages import MotionPattern

MARKER = Pose2D(0.0, 0.0, 0.0)  # the floor marker: the worker map's origin, surveyed
# The source merges again every few seconds while the maps do not fit: a trial gives up.
MERGE_GIVE_UP_S = 15.0
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
    # The kit's steering servo between the wish and the wheels: its position loop
    # (`drivers.actuators.steering_model`, 8 /s) as a first-order lag, before the
    # vehicle model's own (the daemon's simulated forklift has both).
    servo_lag_s: float = 0.125
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


def _mounted(scanners: _Scanners, name: str, ranges: np.ndarray, t_s: float) -> MountedScan:
    """A rendered scan as the daemon's driver hands it over (millimetre telegram)."""
    scan = scan_from_ranges(
        ranges,
        start_angle_deg=math.degrees(scanners.angles[0] + DEVICE_FORWARD_RAD),
        angular_step_deg=math.degrees(scanners.step_rad),
    )
    return MountedScan(scan, name, scanners.mounts[name], t_s, round(t_s * 1e6))


def run_pallet(config: VehicleConfig, params: PalletRunParams) -> PalletResult:
    """The trial on the `pallet` autopilot source itself (`PalletAutopilot`, its jobs
    inline): the worker's map handed to it, the worker selecting the target once the
    maps are merged and holding the button from when the source is ready, the speed
    through the PC104 twin's PID and the steering straight to the wheels."""
    started = time.perf_counter()
    if params.worker_form not in ("cloud", "objects"):
        raise ValueError(f"worker_form must be 'cloud' or 'objects', not {params.worker_form!r}")
    trial = TRIALS[params.trial]
    site = load_site(config.simulation.site)
    rng = np.random.default_rng(params.seed)
    truth_target = true_pallet(site, trial.target)
    # The worker's map: a walk with the terminal, its pallets through proximity points.
    errors = WORSE if trial.worse_worker_map else CONSUMER
    alternatives: tuple[Pallet, ...] = ()
    if params.worker_form == "objects":
        listed = survey_objects(site, MARKER, errors, rng, viewpoints=walk_around(site))
        worker, worker_in_site = object_pallet_map(listed.objects), listed.t0_true
    else:
        cloud = survey(site, MARKER, walk_around(site), rng=rng, errors=errors)
        worker = detect_pallets(cloud.xyz_m, cloud.origins_m, frame="worker").pallet_map
        alternatives = cloud_alternatives(cloud.xyz_m, cloud.origins_m)
        worker_in_site = cloud.t0_true
    scanners = _Scanners(config, site, params.seed)
    marker = config.pallets.worker_marker.model_copy(
        update={"x_m": MARKER.x_m, "y_m": MARKER.y_m, "yaw_deg": math.degrees(MARKER.yaw_rad)}
    )
    run_config = config.model_copy(
        update={"pallets": config.pallets.model_copy(update={"worker_marker": marker})}
    )
    source = PalletAutopilot(
        run_config,
        jobs=InlineJobs(),
        scanners=scanners.setups,
        worker=worker,
        worker_alternatives=alternatives,
    )
    source.merge_params = params.merge
    jobs = source.jobs
    vehicle = VehicleParams.from_config(config)
    state = VehicleState(x_m=trial.start.x_m, y_m=trial.start.y_m, yaw_rad=trial.start.yaw_rad)
    speed_scale = 1.0 + float(rng.normal(0.0, params.speed_scale_sigma))
    steer_bias = float(rng.normal(0.0, params.steer_bias_sigma_rad))
    next_scan = {"left": 0.0, "right": scanners.period_s / 2.0}
    scans: dict[str, MountedScan | None] = {name: None for name in SCANNERS}
    pid = PidSpeedController()
    control_dt, world_dt = 1.0 / params.control_hz, 1.0 / params.world_hz
    t_s, next_control = 0.0, 0.0
    command = VehicleCommand()
    engaged = False
    servo_rad = 0.0
    wish: AutopilotWish | None = None
    first_plan: PalletPlan | None = None
    deadline = params.timeout_s
    while t_s < deadline:
        truth = Pose2D(state.x_m, state.y_m, state.yaw_rad)
        for name in SCANNERS:
            if t_s + 1e-9 >= next_scan[name]:
                scans[name] = _mounted(scanners, name, scanners.render(name, t_s, truth), t_s)
                next_scan[name] += scanners.period_s
        if t_s + 1e-9 >= next_control:
            next_control += control_dt
            observation = Observation(
                t_s,
                state.speed_mps * speed_scale,
                state.rear_steer_rad + steer_bias,
                dict(scans),
                engaged,
                jobs_done=jobs.done(),
            )
            wish = source.update(observation)
            if source.plan is not None and first_plan is None:
                first_plan = source.plan
            if source.target is None and source.names:
                # The worker taps the target: the merged pallet where the true one stands.
                entries = source.site.result.pallets if source.site and source.site.result else ()
                near = [
                    (
                        math.hypot(
                            e.pallet.x_m - truth_target.x_m, e.pallet.y_m - truth_target.y_m
                        ),
                        n,
                    )
                    for n, e in zip(source.names, entries, strict=True)
                ]
                off_m, name = min(near)
                if off_m > 0.5:
                    break
                source.select_pallet(name)
            standing = abs(state.speed_mps) < 1e-4
            phase = None if source.controller is None else source.controller.phase
            if engaged and not wish.ready:
                engaged = False  # a refusal engaged: the core would fault and stop
            elif not engaged and wish.ready and phase is PalletPhase.TO_VIEW:
                engaged = True  # the worker holds the button from when it may
            speed = wish.speed_mps if engaged and wish.speed_mps is not None else 0.0
            throttle, brake, reverse = pid.update(speed, state.speed_mps, control_dt)
            command = VehicleCommand(
                MotionPattern.REAR_STEER, 0.0, servo_rad, throttle, brake, reverse
            )
            ended = phase is PalletPhase.DONE or (not engaged and first_plan is not None)
            unmerged = source.site is None and t_s > MERGE_GIVE_UP_S
            if standing and (ended or unmerged or (source.plan_problem and not engaged)):
                break
        if wish is not None:
            servo_rad += (wish.steer_tyre_rad - servo_rad) * (
                1.0 - math.exp(-world_dt / params.servo_lag_s)
            )
            command = replace(command, rear_steer_rad=servo_rad)
        state = step(state, command, world_dt, vehicle)
        t_s += world_dt
    return _result(params, source, wish, state, truth_target, first_plan, worker_in_site,
                   config, t_s, deadline, started)  # fmt: skip


def _result(
    params: PalletRunParams,
    source: PalletAutopilot,
    wish: AutopilotWish | None,
    state: VehicleState,
    truth_target: Pallet,
    first_plan: PalletPlan | None,
    worker_in_site: Pose2D,
    config: VehicleConfig,
    t_s: float,
    deadline: float,
    started: float,
) -> PalletResult:
    counts: dict[str, float | int] = {"worker_pallets": len(source.worker or ())}
    site_merge = source.site
    if site_merge is None or site_merge.result is None:
        return _failure(source.merge_problem, params, started, **counts)
    counts["vehicle_pallets"] = len(site_merge.vehicle)
    fitted = site_merge.result.worker_in_vehicle
    merge_error = {
        "merge_error_m": math.dist(fitted[:2], worker_in_site[:2]),
        "merge_error_deg": math.degrees(
            abs(math.remainder(fitted.yaw_rad - worker_in_site.yaw_rad, math.tau))
        ),
    }
    if source.target is None:
        return _failure("the target is not in the merged map", params, started, **counts,
                        **merge_error)  # fmt: skip
    plan, controller = source.plan, source.controller
    if first_plan is None or plan is None or controller is None:
        return _failure(source.plan_problem or "no plan", params, started, **counts,
                        **merge_error)  # fmt: skip
    shape = source.shape
    truth = Pose2D(state.x_m, state.y_m, state.yaw_rad)
    face = nearest_entry_face(truth_target, plan.face.entry_yaw_rad)
    errors_at = face_errors(
        truth, face, shape.guide_forward_m, shape.tips_forward_m, shape.forks_offset_y_m
    )
    gap_m = config.pallets.final_gap_m
    translation = math.hypot(errors_at.tips_lateral_m, errors_at.tips_along_m + gap_m)
    success = controller.phase is PalletPhase.DONE
    reason = "at the pallet" if success else (controller.refused or (wish.reason if wish else ""))
    return PalletResult(
        success=success,
        reason=reason,
        phase="timeout" if t_s >= deadline else str(controller.phase),
        tips_lateral_m=errors_at.tips_lateral_m,
        heading_error_deg=math.degrees(errors_at.heading_rad),
        tips_along_m=errors_at.tips_along_m,
        translation_error_m=translation,
        sim_time_s=t_s,
        wall_time_s=time.perf_counter() - started,
        worker_pallets=int(counts["worker_pallets"]),
        vehicle_pallets=int(counts["vehicle_pallets"]),
        plan_length_m=first_plan.length_m,
        face=plan.face.index,
        trial=params.trial,
        seed=params.seed,
        **merge_error,
    )
