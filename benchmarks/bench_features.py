"""Cost and accuracy of scan features: two LMS111 at 25-50 Hz feed them every scan.

Figures:

- the time from two 1081-beam scans (the flat-bed's left and right scanner, Qian et
  al.'s launcher ahead) to their features, for the whole scans and with regions of
  interest around the two cylinders and the front board (what the estimator asks for
  once it has a pose, section 3.2.3 b); 20 different noisy scan pairs cycled. At 10 m
  and 2 m with the regions this benchmark always used (0.5 m discs, a 0.25 m board
  capsule), and near the launcher (the front end 2, 1 and 0.3 m from the board) with
  the localizer's (``LocalizerParams``: 0.6 m discs, 0.4 m capsule), which is what a
  docking run feeds it scan after scan;
- the whole path the localizer runs per pair of scans: `LauncherLocalizer.update` of the
  left and then the right scan (features in its own regions of interest, the prediction
  with the board's motion, the cylinder association and updates, the board update), with
  the localizer tracking (its first pose taken from the pair before timing starts), the
  two scans 20 ms apart as in a docking run, 20 noisy pairs cycled; at 10 m, 2 m and 1 m
  (from a standstill nearer than that the first pose cannot be had: the launcher is not in
  view). Each line ends with how many of the timed pairs left the estimate ``ok``;
- the error of a cylinder's centre with the vehicle 5 m before the board (both
  cylinders, both scanners: about 5 m to each), over many noisy renders: median and p95
  in millimetres, how often it was found, and the mean squared Mahalanobis error (2 for
  a covariance that is right).

Run: ``python -m benchmarks.bench_features`` (``--quick`` for fewer repetitions).
Nothing here is asserted.
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

from appliance.localization.launcher_localizer import (
    LauncherLocalizer,
    LocalizationStatus,
    ScannerSetup,
)
from appliance.perception.features import DiscRoi, LineRoi, Roi, extract_features
from appliance.sim import Site, beam_angles_rad, load_site, render_scan
from benchmarks.stats import summarize
from drivers.geometry import Pose2D

FRONT_M = 5.8  # the flat-bed's scanners: x 5.8 m, y ±1.5 m, yaw ±45° (profiles/flatbed.toml)
MOUNTS = (Pose2D(FRONT_M, 1.5, math.radians(45.0)), Pose2D(FRONT_M, -1.5, math.radians(-45.0)))
SENSOR_ANGLES = beam_angles_rad() - math.pi / 2.0  # 1081 beams, sensor frame
CYLINDERS = ((-0.5, 2.5), (-0.5, -2.5))  # the launcher frame (appliance/sim/sites)
REPETITIONS = 600
# (cylinder disc radius, board capsule half width): this benchmark's, the localizer's.
BENCH_ROIS = (0.5, 0.25)
LOCALIZER_ROIS = (0.6, 0.4)


def _vehicle(distance_m: float) -> Pose2D:
    """The vehicle whose front end is ``distance_m`` before the front board."""
    return Pose2D(-distance_m - FRONT_M, 0.1, math.radians(1.0))


def _in_vehicle(vehicle: Pose2D, x_m: float, y_m: float) -> tuple[float, float]:
    dx, dy = x_m - vehicle.x_m, y_m - vehicle.y_m
    c, s = math.cos(vehicle.yaw_rad), math.sin(vehicle.yaw_rad)
    return c * dx + s * dy, -s * dx + c * dy


def _rois(vehicle: Pose2D, sizes: tuple[float, float] = BENCH_ROIS) -> list[Roi]:
    disc_m, capsule_m = sizes
    rois: list[Roi] = [DiscRoi(*_in_vehicle(vehicle, x, y), disc_m) for x, y in CYLINDERS]
    ends = _in_vehicle(vehicle, 0.0, -1.5) + _in_vehicle(vehicle, 0.0, 1.5)
    rois.append(LineRoi(*ends, capsule_m))
    return rois


def _time_pairs(
    site: Site, vehicle: Pose2D, rois: list[Roi] | None, repetitions: int = REPETITIONS
) -> list[float]:
    rng = np.random.default_rng(0)
    pairs = [
        [render_scan(site, 0.0, vehicle, mount, rng=rng)[0] for mount in MOUNTS] for _ in range(20)
    ]
    durations_ms = []
    for i in range(repetitions):
        scans = pairs[i % len(pairs)]
        started = time.perf_counter()
        for ranges, mount in zip(scans, MOUNTS, strict=True):
            extract_features(ranges, SENSOR_ANGLES, mount, rois=rois)
        durations_ms.append((time.perf_counter() - started) * 1e3)
    return durations_ms


SCANNERS = ("left", "right")
PAIR_PERIOD_S = 0.04  # 25 Hz scanners
SCANNER_STAGGER_S = 0.02  # the right scan half a period after the left, as in `dbw sim dock`


def _time_localizer_pairs(
    site: Site, vehicle: Pose2D, repetitions: int = REPETITIONS
) -> tuple[list[float], int]:
    """Per pair of scans, the time of both `LauncherLocalizer.update` calls, and how many
    timed pairs left the estimate ``ok``."""
    rng = np.random.default_rng(0)
    pairs = [
        [render_scan(site, 0.0, vehicle, mount, rng=rng)[0] for mount in MOUNTS] for _ in range(20)
    ]
    localizer = LauncherLocalizer(
        {name: ScannerSetup(mount) for name, mount in zip(SCANNERS, MOUNTS, strict=True)}
    )

    def update_pair(i: int) -> None:
        t_s = i * PAIR_PERIOD_S
        for k, (name, ranges) in enumerate(zip(SCANNERS, pairs[i % len(pairs)], strict=True)):
            scan_t_s = t_s + k * SCANNER_STAGGER_S
            localizer.update(name, ranges, SENSOR_ANGLES, scan_t_s, scan_t_s)

    update_pair(0)  # the first pose: from here on the localizer tracks
    durations_ms, ok = [], 0
    for i in range(1, repetitions + 1):
        started = time.perf_counter()
        update_pair(i)
        durations_ms.append((time.perf_counter() - started) * 1e3)
        now_s = i * PAIR_PERIOD_S + SCANNER_STAGGER_S
        ok += localizer.estimate(now_s).status is LocalizationStatus.OK
    return durations_ms, ok


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


# (label, front end to board in m, regions: None for the whole scans, else their sizes)
CASES: tuple[tuple[str, float, tuple[float, float] | None], ...] = (
    ("whole scans (10 m)", 10.0, None),
    ("regions of interest (10 m)", 10.0, BENCH_ROIS),
    ("whole scans (2 m)", 2.0, None),
    ("regions of interest (2 m)", 2.0, BENCH_ROIS),
    ("localizer's regions (2 m)", 2.0, LOCALIZER_ROIS),
    ("localizer's regions (1 m)", 1.0, LOCALIZER_ROIS),
    ("localizer's regions (0.3 m)", 0.3, LOCALIZER_ROIS),
)


def main(argv: list[str] | None = None) -> None:
    quick = "--quick" in (sys.argv[1:] if argv is None else argv)
    repetitions = REPETITIONS // 4 if quick else REPETITIONS
    launcher = load_site("launcher")
    _time_pairs(launcher, _vehicle(10.0), None, repetitions // 2)  # warm-up: imports, caches
    for label, distance_m, sizes in CASES:
        vehicle = _vehicle(distance_m)
        rois = None if sizes is None else _rois(vehicle, sizes)
        durations_ms = _time_pairs(launcher, vehicle, rois, repetitions)
        print(summarize(f"two 1081-beam scans -> features, {label}", durations_ms, "ms"))
    for distance_m in (10.0, 2.0, 1.0):  # nearer, the first pose needs more of the board
        durations_ms, ok = _time_localizer_pairs(launcher, _vehicle(distance_m), repetitions)
        label = f"two 1081-beam scans -> features -> EKF (LauncherLocalizer), {distance_m:g} m"
        print(f"{summarize(label, durations_ms, 'ms')}, estimate ok after {ok}")
    errors_mm, found, nees = _centre_errors(launcher, _vehicle(5.0), 75 if quick else 300)
    p50, p95 = np.percentile(errors_mm, [50, 95])
    print(
        f"cylinder centre error at ~5 m: median {p50:.1f} mm, p95 {p95:.1f} mm, "
        f"max {max(errors_mm):.1f} mm (n={len(errors_mm)}, found {found:.1%}, "
        f"mean Mahalanobis² {nees:.2f}, 2 if the covariance is right)"
    )


if __name__ == "__main__":
    main()
