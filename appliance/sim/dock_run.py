"""One docking approach, faster than real time: `dbw sim dock` and the docking benchmark.

The same perception, localizer and docking controller the daemon runs, stepped on a
simulated clock against the simulated world: each scanner renders its scans (at its rate,
the two staggered by half a period, from its true mount, with its drawn errors), the
localizer takes each scan a latency after its instant, stamped with that instant (as the
daemon receives a real scanner's: `dock_scans`), the controller runs at the control rate,
and the PC104's speed PID (the twin's own) turns its wish into throttle and brake on the
simulated flat-bed. No sockets, no event loop: so a hundred approaches take minutes, and
a run is a pure function of its parameters and seed (with or without the worker that
renders the scans on another core).

What is judged is the truth, not the estimate: the teeth's lateral offsets in their
troughs, the heading, the gap, and whether a tooth reached a trough misaligned (contact).
"""

from __future__ import annotations

import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from appliance.config.models import VehicleConfig
from appliance.guidance.docking import (
    DockingController,
    DockingParams,
    docking_errors,
    teeth_inside,
)
from appliance.localization.ekf_floats import inverse_3x3
from appliance.localization.launcher_localizer import (
    LauncherLocalizer,
    LocalizationStatus,
    LocalizerParams,
    ScannerSetup,
)
from appliance.perception.features import FeatureParams
from appliance.perception.types import ScannerModel
from appliance.sim.dock_scans import ScanRenderer, open_scans
from appliance.sim.scanner_errors import ScannerErrors, draw_scanner_errors, noise_seed
from appliance.sim.scanner_model import RayCache, beam_angles_rad
from appliance.sim.site_file import load_site
from appliance.sim.twins.pc104_core import PidSpeedController
from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from drivers.geometry import Pose2D
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, mount_pose
from drivers.pc104.messages import MotionPattern

# What the feature extraction assumes of the ideal scanner: no footprint to widen an arc.
THIN_RAY = ScannerModel(footprint_exit_m=0.0, footprint_divergence_rad=0.0)


@dataclass(frozen=True)
class DockRunParams:
    # Where the vehicle's front end starts, in the launcher frame (about 10 m out).
    start_gap_m: float = 10.0
    start_y_m: float = 0.0
    start_heading_deg: float = 0.0
    seed: int = 1
    ideal_scanner: bool = False
    # True: the localizer knows each scanner's true mount and range offset (a perfect
    # `dbw calibrate scanners`); False: only the configured mounts.
    calibrated: bool = True
    calibrated_range_sigma_m: float = 0.003
    calibrated_yaw_sigma_rad: float = math.radians(0.03)
    control_hz: float = 50.0
    world_hz: float = 100.0
    timeout_s: float = 300.0
    lost_abort_s: float = 3.0  # the vehicle stops at once; the run gives up after this
    # A scanner that stops sending at this time (a cable pulled mid-approach).
    silence_scanner: str | None = None
    silence_at_s: float = math.inf
    site: str = "launcher"
    docking: DockingParams = field(default_factory=DockingParams)
    # From the instant a scan is rendered at to its delivery to the localizer (None:
    # half the scan period, the end of the sweep and the transfer; see `dock_scans`).
    scan_latency_s: float | None = None
    # Render the scans in a forked worker on another core (the same run, sooner).
    render_worker: bool = False


@dataclass(frozen=True)
class DockResult:
    success: bool
    reason: str
    teeth_lateral_m: tuple[float, float]
    heading_error_deg: float
    gap_m: float
    pattern_switches: int
    attempts: int
    contact_misaligned: bool
    sim_time_s: float
    wall_time_s: float
    estimate_error_m: float  # the localizer's position error at the end (truth vs estimate)
    rejected: dict[str, int]
    final_speed_mps: float = 0.0  # the truth's: a run that ends stopped ends at 0
    # The estimate's NEES against the truth, averaged over the control cycles it was
    # used in: over the whole approach and within ``NEAR_GAP_M`` of the board (3 for a
    # covariance that is right; NaN when there was none).
    mean_nees: float = math.nan
    mean_nees_near: float = math.nan

    @property
    def real_time_factor(self) -> float:
        return self.sim_time_s / self.wall_time_s if self.wall_time_s > 0 else math.inf


# Where the gate's certainty check and the teeth's tolerance bite: the NEES there is
# reported on its own.
NEAR_GAP_M = 2.0


def _nees(estimate: Pose2D, covariance: np.ndarray, truth: Pose2D) -> float:
    """``eᵀ P⁻¹ e`` for the error of (x, y, ψ), the heading's wrapped; by the cofactor
    inverse in floats (``np.linalg.solve``'s to rounding: it is asked every control
    cycle), NaN for a singular covariance (left out of the means)."""
    error = (
        estimate.x_m - truth.x_m,
        estimate.y_m - truth.y_m,
        math.remainder(estimate.yaw_rad - truth.yaw_rad, math.tau),
    )
    inverse = inverse_3x3(covariance.tolist())
    if inverse is None:
        return math.nan
    return sum(error[i] * inverse[i][j] * error[j] for i in range(3) for j in range(3))


def scan_latency_s(config: VehicleConfig, params: DockRunParams) -> float:
    """From a scan's instant to its delivery: as given, else half the scan period."""
    if params.scan_latency_s is not None:
        return params.scan_latency_s
    return 0.5 / config.devices.lms111_left.scan_frequency_hz


def _truth_at(history: deque[tuple[float, Pose2D]], t_s: float | None) -> Pose2D | None:
    """The truth at ``t_s``, a time the loop stood at (scans are taken at world steps),
    or None when it is older than the history."""
    for when, truth in reversed(history):
        if when == t_s:
            return truth
    return None


def run_dock(config: VehicleConfig, params: DockRunParams) -> DockResult:
    started = time.perf_counter()
    site = load_site(params.site)
    dock = params.docking
    vehicle = VehicleParams.from_config(config)
    mounts = {
        "left": mount_pose(config.geometry.scanner_left_mount),
        "right": mount_pose(config.geometry.scanner_right_mount),
    }
    errors: dict[str, ScannerErrors] = {
        name: draw_scanner_errors(params.seed, index, not params.ideal_scanner)
        for index, name in enumerate(mounts)
    }
    rngs = {
        name: np.random.default_rng(noise_seed(params.seed, index))
        for index, name in enumerate(mounts)
    }
    if params.calibrated:
        setups = {
            name: ScannerSetup(
                errors[name].true_mount(mount),
                errors[name].range_offset_m,
                params.calibrated_range_sigma_m,
                params.calibrated_yaw_sigma_rad,
            )
            for name, mount in mounts.items()
        }
    else:
        setups = {name: ScannerSetup(mount) for name, mount in mounts.items()}
    features = FeatureParams(scanner=THIN_RAY) if params.ideal_scanner else FeatureParams()
    localizer = LauncherLocalizer(setups, LocalizerParams(features=features))
    controller = DockingController(dock)
    pid = PidSpeedController()
    endpoint = config.devices.lms111_left
    scan_period_s = 1.0 / endpoint.scan_frequency_hz
    latency_s = scan_latency_s(config, params)
    step_rad = math.radians(endpoint.angular_resolution_deg)
    renderer = ScanRenderer(
        site, mounts, errors, rngs, {name: RayCache() for name in mounts}, step_rad
    )
    device_angles = beam_angles_rad(step_rad=step_rad)
    sensor_angles = device_angles - DEVICE_FORWARD_RAD

    heading = math.radians(params.start_heading_deg)
    front = Pose2D(-dock.standoff_m - params.start_gap_m, params.start_y_m, heading)
    centre = front.compose(Pose2D(-dock.front_end_forward_m, 0.0, 0.0))
    state = VehicleState(x_m=centre.x_m, y_m=centre.y_m, yaw_rad=centre.yaw_rad)

    world_dt = 1.0 / params.world_hz
    control_dt = 1.0 / params.control_hz
    next_scan = {"left": 0.0, "right": scan_period_s / 2.0}
    next_control = 0.0
    wish = VehicleCommand()
    contact = False
    t_s = 0.0
    reason = "timeout"
    lost_since_s: float | None = None
    nees_sums, nees_counts = [0.0, 0.0], [0, 0]  # [far, near]

    def platform(s: VehicleState) -> Pose2D:
        return Pose2D(s.x_m, s.y_m, s.platform_yaw_rad)

    # The truth where the loop stands: set again after every world step.
    truth = platform(state)
    gap = docking_errors(truth, dock)[0]
    # Scans rendered and not yet delivered, oldest first: (delivery time, scanner, taken).
    in_flight: deque[tuple[float, str, float]] = deque()
    # The truth of the last second, by time: an estimate is judged against the truth at
    # the time of its last scan, which reached it a latency later.
    history: deque[tuple[float, Pose2D]] = deque(maxlen=max(1, round(params.world_hz)))
    scans = open_scans(renderer, params.render_worker)
    try:
        while t_s < params.timeout_s:
            history.append((t_s, truth))
            # Asked for first: a worker renders while the localizer takes the older scans.
            for name in mounts:
                silenced = name == params.silence_scanner and t_s >= params.silence_at_s
                if t_s + 1e-9 >= next_scan[name] and not silenced:
                    scans.submit(name, t_s, truth)
                    in_flight.append((t_s + latency_s, name, t_s))
                    next_scan[name] += scan_period_s
            while in_flight and t_s + 1e-9 >= in_flight[0][0]:
                _, name, taken_s = in_flight.popleft()
                localizer.update(name, scans.take(), sensor_angles, taken_s, t_s)
            if t_s + 1e-9 >= next_control:
                next_control += control_dt
                estimate = localizer.estimate(t_s)
                if estimate.status is not LocalizationStatus.OK or estimate.centre_pose is None:
                    command_speed, pattern, front_rad, rear_rad = 0.0, MotionPattern.STOP, 0.0, 0.0
                    lost_since_s = t_s if lost_since_s is None else lost_since_s
                    if t_s - lost_since_s > params.lost_abort_s:
                        reason = f"localization {estimate.status}: {estimate.reason}"
                        break
                else:
                    lost_since_s = None
                    then = _truth_at(history, estimate.t_s)
                    if (
                        estimate.centre_covariance is not None
                        and then is not None
                        and math.isfinite(
                            nees := _nees(estimate.centre_pose, estimate.centre_covariance, then)
                        )
                    ):
                        near = gap <= NEAR_GAP_M
                        nees_sums[near] += nees
                        nees_counts[near] += 1
                    order = controller.update(estimate.centre_pose, estimate.centre_covariance, t_s)
                    command_speed, pattern = order.speed_mps, order.pattern
                    front_rad, rear_rad = order.front_steer_rad, order.rear_steer_rad
                    if order.refused:
                        reason = order.refused
                        break
                    if order.phase.value == "docked" and abs(state.speed_mps) < 1e-3:
                        reason = "docked"
                        break
                throttle, brake, reverse = pid.update(command_speed, state.speed_mps, control_dt)
                wish = VehicleCommand(
                    pattern=pattern,
                    front_steer_rad=front_rad,
                    rear_steer_rad=-rear_rad,  # the sim counts counter-steer positive
                    throttle_pct=throttle,
                    brake_pct=brake,
                    reverse=reverse,
                )
            state = step(state, wish, world_dt, vehicle)
            t_s += world_dt
            truth = platform(state)
            gap, _, _, _ = docking_errors(truth, dock)
            if gap <= dock.tooth_insertion_m and not teeth_inside(truth, dock):
                contact = True
    finally:
        scans.close()

    truth = platform(state)
    gap, _, heading_err, teeth = docking_errors(truth, dock)
    final = localizer.estimate(t_s)
    estimate_error = (
        math.dist(final.centre_pose[:2], truth[:2]) if final.centre_pose is not None else math.nan
    )
    success = reason == "docked" and teeth_inside(truth, dock) and not contact
    return DockResult(
        success=success,
        reason=reason,
        teeth_lateral_m=teeth,
        heading_error_deg=math.degrees(heading_err),
        gap_m=gap,
        pattern_switches=controller.switches,
        attempts=controller.attempts,
        contact_misaligned=contact,
        sim_time_s=t_s,
        wall_time_s=time.perf_counter() - started,
        estimate_error_m=estimate_error,
        rejected=dict(final.rejected),
        final_speed_mps=state.speed_mps,
        mean_nees=sum(nees_sums) / sum(nees_counts) if sum(nees_counts) else math.nan,
        mean_nees_near=nees_sums[1] / nees_counts[1] if nees_counts[1] else math.nan,
    )
