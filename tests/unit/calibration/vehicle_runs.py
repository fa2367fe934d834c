"""The calibration maneuvers driven on the simulated vehicle, with a known truth.

The truth is what the fits must recover: a counter-steer ratio k, a nonlinear steering
linkage (wheel to front tyre, an arcsine of a sine like Stanley et al.'s eq. 4, 1:18 at the
centre and 1.2 deg off that constant ratio at the lock), the sideslip gain's V_char. The
vehicle is ``appliance.sim.vehicle.step``; the GNSS/INS is the GNSS twin's error model
(white position and heading noise, 0.3 m threshold-switching jumps every 20 s in a new
direction) applied to the antenna 3 m ahead of the geometric centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from appliance.sim.vehicle import VehicleCommand, VehicleParams, VehicleState, step
from calibration.k_ratio import SteadyTurn
from calibration.palm_tree_samples import PalmTreeSamples
from drivers.pc104.messages import MotionPattern

TRUE_K = 0.63
V_CHAR_MPS = 10.0
WHEELBASE_M = 3.6
ANTENNA_FORWARD_M = 3.0
LINKAGE_GAIN = 2.0
LINKAGE_RATIO = 18.0 * LINKAGE_GAIN  # 1:18 at the centre
HALF_TURNS_RAD = tuple(math.pi * n for n in range(-3, 4))  # full left to full right
DT_S = 0.02
EPOCH_STEPS = 5  # 10 Hz GNSS

VEHICLE = VehicleParams(
    wheelbase_m=WHEELBASE_M,
    track_width_m=2.3,
    counter_steer_ratio_k=TRUE_K,
    characteristic_speed_mps=V_CHAR_MPS,
    max_steer_angle_rad=math.radians(32.0),
    max_steer_rate_rad_per_s=math.radians(25.0),
)


def true_tyre_rad(wheel_rad: float | np.ndarray) -> np.ndarray:
    return np.asarray(np.arcsin(LINKAGE_GAIN * np.sin(np.asarray(wheel_rad) / LINKAGE_RATIO)))


def true_wheel_rad(tyre_rad: float) -> float:
    return LINKAGE_RATIO * math.asin(math.sin(tyre_rad) / LINKAGE_GAIN)


@dataclass(frozen=True)
class GnssErrors:
    position_sigma_m: float = 0.02
    heading_sigma_rad: float = math.radians(0.2)
    speed_sigma_mps: float = 0.02
    wheel_sigma_rad: float = 0.003
    jump_m: float = 0.3
    jump_period_s: float = 20.0


class Recorder:
    """Epochs of the antenna's pose as the noisy receiver reports them."""

    def __init__(self, errors: GnssErrors, seed: int) -> None:
        self.errors = errors
        self.rng = np.random.default_rng(seed)
        self.rows: list[tuple[float, ...]] = []
        self.truth: list[VehicleState] = []
        self._jump_angle: dict[int, float] = {}

    def _jump(self, t_s: float) -> tuple[float, float]:
        period = math.floor(t_s / self.errors.jump_period_s)
        if self.errors.jump_m == 0.0 or period % 2 == 0:
            return 0.0, 0.0
        angle = self._jump_angle.setdefault(period, float(self.rng.uniform(0, math.tau)))
        return self.errors.jump_m * math.cos(angle), self.errors.jump_m * math.sin(angle)

    def record(self, state: VehicleState, antenna_speed_mps: float) -> None:
        e, rng = self.errors, self.rng
        jx, jy = self._jump(state.t_s)
        x = state.x_m + ANTENNA_FORWARD_M * math.cos(state.yaw_rad) + jx
        y = state.y_m + ANTENNA_FORWARD_M * math.sin(state.yaw_rad) + jy
        self.rows.append(
            (
                state.t_s,
                x + rng.normal(0, e.position_sigma_m),
                y + rng.normal(0, e.position_sigma_m),
                state.yaw_rad + rng.normal(0, e.heading_sigma_rad),
                abs(antenna_speed_mps + rng.normal(0, e.speed_sigma_mps)),
                true_wheel_rad(state.front_steer_rad) + rng.normal(0, e.wheel_sigma_rad),
                e.position_sigma_m,
            )
        )
        self.truth.append(state)

    def samples(self) -> PalmTreeSamples:
        columns = np.array(self.rows).T
        return PalmTreeSamples(*columns)


class Driver:
    """Steps the vehicle and records every fifth step; the maneuvers' building blocks."""

    def __init__(self, errors: GnssErrors, seed: int) -> None:
        self.state = VehicleState()
        self.recorder = Recorder(errors, seed)
        self._steps = 0
        self.front_rad = 0.0

    def _step(self, throttle_pct: float, brake_pct: float, reverse: bool) -> None:
        before = self.state
        command = VehicleCommand(
            MotionPattern.COUNTER_STEER, self.front_rad, 0.0, throttle_pct, brake_pct, reverse
        )
        self.state = step(before, command, DT_S, VEHICLE)
        self._steps += 1
        if self._steps % EPOCH_STEPS == 0:
            ax = ANTENNA_FORWARD_M * (math.cos(self.state.yaw_rad) - math.cos(before.yaw_rad))
            ay = ANTENNA_FORWARD_M * (math.sin(self.state.yaw_rad) - math.sin(before.yaw_rad))
            dx = self.state.x_m - before.x_m + ax
            dy = self.state.y_m - before.y_m + ay
            self.recorder.record(self.state, math.hypot(dx, dy) / DT_S)

    def hold(self, seconds: float) -> None:
        for _ in range(round(seconds / DT_S)):
            self._step(0.0, 100.0, False)

    def drive(self, speed_mps: float, metres: float, max_turn_rad: float = math.inf) -> None:
        """Drive ``metres`` (or until the heading turned ``max_turn_rad``), then stop."""
        reverse = speed_mps < 0
        start_odo, start_yaw = self.state.odometer_m, self.state.yaw_rad
        while self.state.odometer_m - start_odo < metres:
            turned = abs(math.remainder(self.state.yaw_rad - start_yaw, math.tau))
            if turned >= max_turn_rad:
                break
            error = abs(speed_mps) - abs(self.state.speed_mps)
            throttle = 100.0 * min(1.0, max(0.0, 0.05 * abs(speed_mps) + 2.0 * error))
            self._step(throttle, 0.0, reverse)
        while abs(self.state.speed_mps) > 0.0:
            self._step(0.0, 100.0, reverse)


def palm_tree(
    errors: GnssErrors = GnssErrors(),
    seed: int = 1,
    speed_mps: float = 1.0,
    metres: float = 12.0,
    max_turn_rad: float = math.pi,
    wheels_rad: tuple[float, ...] = HALF_TURNS_RAD,
) -> Recorder:
    """Full left to full right at half turns: forward an arc, reverse back, half a turn."""
    driver = Driver(errors, seed)
    for wheel in wheels_rad:
        driver.front_rad = float(true_tyre_rad(wheel))
        driver.hold(3.0)
        start = driver.state.odometer_m
        driver.drive(speed_mps, metres, max_turn_rad)
        driver.hold(0.5)
        driver.drive(-speed_mps, driver.state.odometer_m - start)
        driver.hold(0.5)
    return driver.recorder


def steady_turn(
    wheel_rad: float, speed_mps: float, seconds: float, seed: int, errors: GnssErrors = GnssErrors()
) -> SteadyTurn:
    """A turn at a held wheel angle: settle for 8 s, then record ``seconds`` of it (heading
    with the receiver's noise, the vehicle's own speed with noise, the wheel angle)."""
    driver = Driver(GnssErrors(jump_m=0.0), seed)
    driver.front_rad = float(true_tyre_rad(wheel_rad))
    driver.hold(3.0)
    rng = np.random.default_rng(seed + 1000)
    rows: list[tuple[float, float, float, float]] = []
    settle_s = 8.0
    start_s = driver.state.t_s
    while driver.state.t_s - start_s < settle_s + seconds:
        error = speed_mps - driver.state.speed_mps
        throttle = 100.0 * min(1.0, max(0.0, 0.05 * speed_mps + 2.0 * error))
        for _ in range(EPOCH_STEPS):
            driver._step(throttle, 0.0, False)
        if driver.state.t_s - start_s >= settle_s:
            rows.append(
                (
                    driver.state.t_s,
                    driver.state.yaw_rad + rng.normal(0, errors.heading_sigma_rad),
                    driver.state.speed_mps + rng.normal(0, errors.speed_sigma_mps),
                    true_wheel_rad(driver.state.front_steer_rad)
                    + rng.normal(0, errors.wheel_sigma_rad),
                )
            )
    t, heading, speed, wheel = np.array(rows).T
    return SteadyTurn(t, heading, speed, wheel)
