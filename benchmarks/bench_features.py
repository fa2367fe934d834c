"""Cost and accuracy of scan features: two LMS111 at 25-50 Hz feed them every scan.

Figures:

- the time from two 1081-beam scans (the flat-bed's left and right scanner, Qian et
  al.'s launcher about 10 m ahead) to their features, for the whole scans and with
  regions of interest around the two cylinders and the front board (what the estimator
  asks for once it has a pose, section 3.2.3 b); 20 different noisy scan pairs cycled;
- the error of a cylinder's centre with the vehicle 5 m before the board (both
  cylinders, both scanners: about 5 m to each), over many noisy renders: median and p95
  in millimetres, how often it was found, and the mean squared Mahalanobis error (2 for
  a covariance that is right).

Run: ``python -m benchmarks.bench_features``. Nothing here is asserted.
"""

from __future__ import annotations

import math
import time

import numpy as np

from appliance.perception.features import DiscRoi, LineRoi, Roi, extract_features
from appliance.sim import Site, beam_angles_rad, load_site, render_scan
from benchmarks.stats import summarize
from drivers.geometry import Pose2D

FRONT_M = 5.8  # the flat-bed's scanners: x 5.8 m, y ±1.5 m, yaw ±45° (profiles/flatbed.toml)
MOUNTS = (Pose2D(FRONT_M, 1.5, math.radians(45.0)), Pose2D(FRONT_M, -1.5, math.radians(-45.0)))
SENSOR_ANGLES = beam_angles_rad() - math.pi / 2.0  # 1081 beams, sensor frame
CYLINDERS = ((-0.5, 2.5), (-0.5, -2.5))  # the launcher frame (appliance/sim/sites)
REPETITIONS = 600


def _vehicle(distance_m: float) -> Pose2D:
    """The vehicle whose front end is ``distance_m`` before the front board."""
    return Pose2D(-distance_m - FRONT_M, 0.1, math.radians(1.0))


def _in_vehicle(vehicle: Pose2D, x_m: float, y_m: float) -> tuple[float, float]:
    dx, dy = x_m - vehicle.x_m, y_m - vehicle.y_m
    c, s = math.cos(vehicle.yaw_rad), math.sin(vehicle.yaw_rad)
    return c * dx + s * dy, -s * dx + c * dy


def _rois(vehicle: Pose2D) -> list[Roi]:
    rois: list[Roi] = [DiscRoi(*_in_vehicle(vehicle, x, y), 0.5) for x, y in CYLINDERS]
    ends = _in_vehicle(vehicle, 0.0, -1.5) + _in_vehicle(vehicle, 0.0, 1.5)
    rois.append(LineRoi(*ends, 0.25))
    return rois


def _time_pairs(site: Site, vehicle: Pose2D, rois: list[Roi] | None) -> list[float]:
    rng = np.random.default_rng(0)
    pairs = [
        [render_scan(site, 0.0, vehicle, mount, rng=rng)[0] for mount in MOUNTS] for _ in range(20)
    ]
    durations_ms = []
    for i in range(REPETITIONS):
        scans = pairs[i % len(pairs)]
        started = time.perf_counter()
        for ranges, mount in zip(scans, MOUNTS, strict=True):
            extract_features(ranges, SENSOR_ANGLES, mount, rois=rois)
        durations_ms.append((time.perf_counter() - started) * 1e3)
    return durations_ms


def _centre_errors(site: Site, vehicle: Pose2D, renders: int) -> tuple[list[float], float, float]:
    """Centre errors (mm) of both cylinders in both scanners, the fraction found, and
    the mean squared Mahalanobis error under the reported covariance."""
    rng = np.random.default_rng(1)
    errors_mm, mahalanobis, expected = [], [], 0
    for _ in range(renders):
        for mount in MOUNTS:
            features = extract_features(
                render_scan(site, 0.0, vehicle, mount, rng=rng)[0], SENSOR_ANGLES, mount
            )
            for x_m, y_m in CYLINDERS:
                expected += 1
                tx, ty = _in_vehicle(vehicle, x_m, y_m)
                for circle in features.circles:
                    error = np.array([circle.cx_m - tx, circle.cy_m - ty])
                    if math.hypot(*error) < 0.3:
                        errors_mm.append(1e3 * math.hypot(*error))
                        mahalanobis.append(float(error @ np.linalg.solve(circle.covariance, error)))
    return errors_mm, len(errors_mm) / max(expected, 1), float(np.mean(mahalanobis))


def main() -> None:
    launcher = load_site("launcher")
    far = _vehicle(10.0)
    _time_pairs(launcher, far, None)  # warm-up: imports, caches
    print(
        summarize(
            "two 1081-beam scans -> features, whole scans (10 m)",
            _time_pairs(launcher, far, None),
            "ms",
        )
    )
    print(
        summarize(
            "two 1081-beam scans -> features, regions of interest (10 m)",
            _time_pairs(launcher, far, _rois(far)),
            "ms",
        )
    )
    near = _vehicle(2.0)
    print(
        summarize(
            "two 1081-beam scans -> features, whole scans (2 m)",
            _time_pairs(launcher, near, None),
            "ms",
        )
    )
    print(
        summarize(
            "two 1081-beam scans -> features, regions of interest (2 m)",
            _time_pairs(launcher, near, _rois(near)),
            "ms",
        )
    )
    errors_mm, found, nees = _centre_errors(launcher, _vehicle(5.0), 300)
    p50, p95 = np.percentile(errors_mm, [50, 95])
    print(
        f"cylinder centre error at ~5 m: median {p50:.1f} mm, p95 {p95:.1f} mm, "
        f"max {max(errors_mm):.1f} mm (n={len(errors_mm)}, found {found:.1%}, "
        f"mean Mahalanobis² {nees:.2f}, 2 if the covariance is right)"
    )


if __name__ == "__main__":
    main()
