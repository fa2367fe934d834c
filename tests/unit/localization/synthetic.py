"""A synthetic approach to the launcher for the filter's tests, without the ray caster.

Measurements are drawn from the truth with exactly the noise the filter is told, so the
filter's consistency (NEES) can be tested apart from perception: if the filter is
inconsistent here, it is the filter; with real scans it could be either.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from appliance.localization.board_motion import BoardEnd, BoardSighting
from appliance.localization.compound import compound, wrap_angle_rad
from appliance.localization.launcher_ekf import (
    LauncherEkf,
    board_measurement,
    cylinder_measurement,
)
from appliance.localization.launcher_map import LauncherMap
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]

# The flat-bed's scanners relative to O_f, their midpoint (profile: x 5.8, y ±1.5, ±45°).
SENSORS = {
    "left": Pose2D(0.0, 1.5, math.radians(45.0)),
    "right": Pose2D(0.0, -1.5, math.radians(-45.0)),
}
LINE_COV = np.diag([0.002**2, math.radians(0.05) ** 2])
CYL_COV = np.diag([0.008**2, math.radians(0.15) ** 2])
END_SIGMA_M = 0.02
FOV_HALF_RAD = math.radians(135.0)


def _noisy_end(point: FloatArray, rng: np.random.Generator) -> BoardEnd:
    x_m, y_m = point + rng.normal(0.0, END_SIGMA_M, 2)
    return BoardEnd(float(x_m), float(y_m), END_SIGMA_M)


@dataclass(frozen=True)
class Sample:
    t_s: float
    sensor: str
    truth: FloatArray
    board: BoardSighting
    cylinders: tuple[tuple[FloatArray, tuple[float, float]], ...]


def board_ends(truth: FloatArray, launcher: LauncherMap) -> tuple[FloatArray, FloatArray]:
    """The board's two ends seen from O_f at ``truth`` (low end first along the line)."""
    c, s = math.cos(truth[2]), math.sin(truth[2])
    ends = []
    for y in (-launcher.half_width_m, launcher.half_width_m):
        dx, dy = 0.0 - truth[0], y - truth[1]
        ends.append(np.array([c * dx + s * dy, -s * dx + c * dy]))
    z, _ = board_measurement(truth)
    direction = np.array([-math.sin(z[1]), math.cos(z[1])])
    ends.sort(key=lambda p: float(direction @ p))
    return ends[0], ends[1]


def approach(
    rng: np.random.Generator,
    launcher: LauncherMap,
    start: tuple[float, float, float] = (-10.0, 0.6, math.radians(3.0)),
    speed_mps: float = 0.3,
    yaw_rate_radps: float = math.radians(-0.2),
    lateral_mps: float = -0.04,
    duration_s: float = 20.0,
    period_s: float = 0.04,
) -> list[Sample]:
    """Scans alternating between the two scanners every half period, with noise; the
    truth's motion is disturbed by the process noise the filter assumes (its own Q), as a
    consistency test requires."""
    process_noise = LauncherEkf().process_noise
    samples: list[Sample] = []
    truth = np.array(start, dtype=float)
    t_s = 0.0
    step_s = period_s / 2.0
    index = 0
    while t_s < duration_s:
        sensor = "left" if index % 2 == 0 else "right"
        z_board, _ = board_measurement(truth)
        z_board = z_board + rng.multivariate_normal(np.zeros(2), LINE_COV)
        low, high = board_ends(truth, launcher)
        ends = [_noisy_end(p, rng) for p in (low, high)]
        board = BoardSighting(t_s, float(z_board[0]), float(z_board[1]), LINE_COV, *ends)
        cylinders = []
        for landmark in launcher.cylinders:
            xy = (landmark.x_m, landmark.y_m)
            z, _ = cylinder_measurement(truth, xy, SENSORS[sensor])
            if abs(z[1]) < FOV_HALF_RAD:
                noisy = z + rng.multivariate_normal(np.zeros(2), CYL_COV)
                cylinders.append((noisy, xy))
        samples.append(Sample(t_s, sensor, truth.copy(), board, tuple(cylinders)))
        delta = np.array([speed_mps, lateral_mps, yaw_rate_radps]) * step_s
        delta = delta + rng.multivariate_normal(np.zeros(3), process_noise(delta, step_s))
        truth = compound(truth, delta)
        truth[2] = wrap_angle_rad(float(truth[2]))
        t_s += step_s
        index += 1
    return samples
