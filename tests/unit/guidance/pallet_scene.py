"""The `pallets` site and the `forklift-sim` vehicle for the pallet guidance's tests, and
a closed loop: the approach controller driving the simulated vehicle.

The map is the site's truth, as the vehicle's own scans would have it (2 cm), except
the target, which comes from the worker's map: moved by ``map_error`` and 5 cm unsure,
as Kinouchi et al.'s terminal would leave it. The detections are what the vehicle's
scanners would report: the true pallet relative to the true vehicle, with a few mm and
a tenth of a degree of noise, a half turn of its symmetry at random, put into the
site frame with the vehicle's *estimate* (so an error of the estimate is in them as it
would be), and only while both scanners have the face in their fields. What is judged
is the truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

from appliance.config import load_config
from appliance.config.models import VehicleConfig
from appliance.core import pallet_parts
from appliance.guidance.pallet_approach import (
    PalletApproach,
    PalletApproachParams,
    PalletOrder,
    PalletPhase,
)
from appliance.guidance.pallet_final import face_errors
from appliance.guidance.pallet_geometry import (
    Obstacle,
    ScannerField,
    VehicleShape,
    box_corners,
    face_in_view,
    nearest_entry_face,
)
from appliance.guidance.pallet_plan import (
    PalletPlan,
    PalletPlanParams,
    PalletTarget,
    PlanRefusal,
    plan_pallet_approach,
)
from appliance.mapping.merge import reference_area
from appliance.mapping.pallets import Pallet, inverse_pose
from appliance.sim import pallet_run
from appliance.sim.site_file import load_site
from appliance.sim.twins.pc104_core import PidSpeedController
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.geometry import Pose2D
from drivers.lms111.mounted import mount_pose
from drivers.pc104.messages import MotionPattern

START = Pose2D(-2.0, -1.5, 0.0)
ROW_B = ("row_b.r0c0", "row_b.r0c1", "row_b.r0c2")
# A fork is about 12 cm wide: the outline of both, centre to centre plus one.
FORK_WIDTH_M = 0.15
SEEN_SIGMA_M = 0.02
WORKER_SIGMA_M = 0.05


@cache
def config() -> VehicleConfig:
    return load_config("forklift-sim")


def vehicle_shape() -> VehicleShape:
    c = config()
    return VehicleShape(
        length_m=c.geometry.length_m,
        width_m=c.geometry.width_m,
        front_m=c.forks.tips_forward_m,
        wheelbase_m=c.geometry.wheelbase_m,
        max_steer_rad=math.radians(c.limits.max_steer_angle_deg),
        tips_forward_m=c.forks.tips_forward_m,
        forks_offset_y_m=c.forks.offset_y_m,
        scanners=(
            ScannerField(mount_pose(c.geometry.scanner_left_mount)),
            ScannerField(mount_pose(c.geometry.scanner_right_mount)),
        ),
        heel_forward_m=c.forks.heel_forward_m,
        forks_width_m=c.forks.spread_m + FORK_WIDTH_M,
    )


def approach_params() -> PalletApproachParams:
    """As the `pallet` source builds them from the vehicle file."""
    return pallet_parts.approach_params(config())


def plan_params() -> PalletPlanParams:
    return PalletPlanParams(approach_standoff_m=config().pallets.approach_standoff_m)


@cache
def true_pallets() -> tuple[Pallet, ...]:
    """The site's pallets, exactly."""
    site = load_site("pallets")
    return tuple(pallet_run.true_pallet(site, solid.name) for solid in site.pallets)


def true_pallet(name: str) -> Pallet:
    return next(p for p in true_pallets() if p.name == name)


@cache
def static_obstacles() -> tuple[Obstacle, ...]:
    """The yard's walls and the posts, grown by the plan's clearance."""
    return pallet_parts.site_obstacles(config(), plan_params().clearance_m)


def worker_map(
    target_name: str, map_error: tuple[float, float, float]
) -> tuple[PalletTarget, tuple[Pallet, ...]]:
    """The merged map: the vehicle's pallets (true, 2 cm) and the target from the
    worker's map, off by ``map_error`` (m, m, rad), with its reference area."""
    seen = np.diag([SEEN_SIGMA_M**2, SEEN_SIGMA_M**2, math.radians(0.5) ** 2])
    worker = np.diag([WORKER_SIGMA_M**2, WORKER_SIGMA_M**2, math.radians(2.0) ** 2])
    pallets = []
    target: Pallet | None = None
    for p in true_pallets():
        if p.name == target_name:
            dx, dy, dyaw = map_error
            target = Pallet(p.x_m + dx, p.y_m + dy, p.yaw_rad + dyaw, worker, p.kind, p.name)
            pallets.append(target)
        else:
            pallets.append(Pallet(p.x_m, p.y_m, p.yaw_rad, seen, p.kind, p.name))
    assert target is not None
    return PalletTarget(target, reference_area(target, 3.0)), tuple(pallets)


@cache
def site_plan(
    target_name: str,
    map_error: tuple[float, float, float] = (0.0, 0.0, 0.0),
    start: Pose2D = START,
) -> PalletPlan | PlanRefusal:
    target, pallets = worker_map(target_name, map_error)
    return plan_pallet_approach(
        start, target, pallets, vehicle_shape(), plan_params(), static_obstacles()
    )


@dataclass(frozen=True)
class LoopResult:
    order: PalletOrder
    # The truth at the end, against the true pallet's face the plan chose.
    tips_lateral_m: float
    heading_rad: float
    tips_past_face_m: float  # > 0: the tips went into the openings by this much
    sim_time_s: float
    truth: tuple[Pose2D, ...]  # the vehicle centre every control cycle
    phases: tuple[PalletPhase, ...]
    max_path_deviation_m: float


def closed_loop(
    plan: PalletPlan,
    target_name: str,
    estimate_error: tuple[float, float, float] = (0.0, 0.0, 0.0),
    seed: int = 0,
    detection_noise: tuple[float, float] = (0.003, math.radians(0.1)),
    timeout_s: float = 250.0,
) -> LoopResult:
    """The approach on the simulated forklift: world at 100 Hz, control at 50 Hz, the
    scanners' detections at 25 Hz; the speed wish through the PC104's speed PID."""
    rng = np.random.default_rng(seed)
    truth_pallet = true_pallet(target_name)
    shape = vehicle_shape()
    params = approach_params()
    vehicle = VehicleParams.from_config(config())
    controller = PalletApproach(plan, params)
    pid = PidSpeedController()
    dx, dy, dyaw = estimate_error
    start = Pose2D(plan.guide_xy_m[0, 0], plan.guide_xy_m[0, 1], float(plan.headings_rad[0]))
    centre = shape.centre_of(start)
    # The plan was made from the estimate: the truth is off it by the error.
    state = VehicleState(x_m=centre.x_m - dx, y_m=centre.y_m - dy, yaw_rad=centre.yaw_rad - dyaw)
    covariance = np.diag([0.01**2, 0.01**2, math.radians(0.2) ** 2])
    world_dt, command = 0.01, VehicleCommand()
    truth_log: list[Pose2D] = []
    phases: list[PalletPhase] = []
    deviation = 0.0
    order = PalletOrder(PalletPhase.TO_VIEW, 0.0, 0.0)
    t_s = 0.0
    for k in range(int(timeout_s / world_dt)):
        t_s = k * world_dt
        if k % 2 == 0:
            truth = Pose2D(state.x_m, state.y_m, state.yaw_rad)
            estimate = Pose2D(truth.x_m + dx, truth.y_m + dy, truth.yaw_rad + dyaw)
            detection = None
            looking = controller.phase in (PalletPhase.REDETECT, PalletPhase.FINAL)
            face = nearest_entry_face(truth_pallet, plan.face.entry_yaw_rad)
            if looking and k % 4 == 0 and face_in_view(shape, truth, face) == "":
                relative = inverse_pose(truth).compose(truth_pallet.pose)
                flip = math.pi if rng.random() < 0.5 else 0.0
                noisy = Pose2D(
                    relative.x_m + rng.normal(0.0, detection_noise[0]),
                    relative.y_m + rng.normal(0.0, detection_noise[0]),
                    relative.yaw_rad + rng.normal(0.0, detection_noise[1]) + flip,
                )
                seen = estimate.compose(noisy)
                detection = Pallet(
                    seen.x_m, seen.y_m, seen.yaw_rad, np.eye(3) * 1e-5, truth_pallet.kind
                )
            order = controller.update(estimate, covariance, state.speed_mps, t_s, detection)
            if order.phase is PalletPhase.TO_VIEW:
                deviation = max(deviation, abs(order.lateral_error_m))
            truth_log.append(truth)
            phases.append(order.phase)
            throttle, brake, reverse = pid.update(order.speed_mps, state.speed_mps, 2 * world_dt)
            command = VehicleCommand(
                MotionPattern.REAR_STEER, 0.0, order.steer_rad, throttle, brake, reverse
            )
            finished = order.phase in (PalletPhase.DONE, PalletPhase.REFUSED)
            if finished and abs(state.speed_mps) < 1e-6:
                break
        state = step(state, command, world_dt, vehicle)
    truth = Pose2D(state.x_m, state.y_m, state.yaw_rad)
    face = nearest_entry_face(truth_pallet, plan.face.entry_yaw_rad)
    errors = face_errors(
        truth, face, shape.guide_forward_m, shape.tips_forward_m, shape.forks_offset_y_m
    )
    return LoopResult(
        order,
        errors.tips_lateral_m,
        errors.heading_rad,
        errors.tips_along_m,
        t_s,
        tuple(truth_log),
        tuple(phases),
        deviation,
    )


def outline_polygons(shape: VehicleShape, centres: list[Pose2D]) -> list[np.ndarray]:
    """The outline's boxes at each centre pose, (N, 4, 2) each."""
    guides = np.array([list(shape.guide_of(c)) for c in centres])
    return [box_corners(box, guides) for box in shape.parts_local_m()]
