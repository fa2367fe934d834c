"""Cost of the LMS111 error model: one scan, ideal against realistic, from a moving vehicle.

Figures: median, p99, min and max time of one `render_scan` of the built-in launcher site,
1081 beams (25 Hz / 0.25°) and 541 beams (50 Hz / 0.5°), for the ideal scanner, the
thin-ray model of noise and a fixed offset the simulator used before (``statistical
only``), and a drawn realistic scanner (noise, systematic error, mount error, remission
limit, footprints cast near edges and on posts). The left scanner of the ``sim`` vehicle
approaches the launcher as in Qian et al. (from about 12.6 m out, 1 m/s, turning
slightly), so every scan is taken from a new pose and no `RayCache` could help.

The budget it is measured against: a docking simulation with two 1081-beam scanners at
25 Hz running 20 times faster than real time renders 1000 scans per second of wall time,
all of its other work included; the last lines give the share of that second the
rendering alone takes at the median.
"""

from __future__ import annotations

import math
import time

import numpy as np

from appliance.config import load_config
from appliance.sim import (
    ScannerErrors,
    draw_scanner_errors,
    ideal_scanner,
    load_site,
    render_scan,
    statistical_only,
)
from appliance.sim.site import Site
from benchmarks.stats import summarize
from drivers.geometry import Pose2D
from drivers.lms111.mounted import mount_pose

SCANS = 2000
SCAN_PERIOD_S = 0.04  # 25 Hz
DOCKING_SCANS_PER_S = 2 * 25 * 20  # two scanners at 25 Hz, 20x real time


def _approach(t_s: float) -> Pose2D:
    """Qian et al.'s start, about 12.6 m before the board, then 1 m/s straight in."""
    along_m = t_s % 10.0
    return Pose2D(-12.6 + along_m, 0.4 - 0.03 * along_m, math.radians(3.0 - 0.3 * along_m))


def _time_scans(
    site: Site, mount: Pose2D, errors: ScannerErrors, step_rad: float, scans: int
) -> list[float]:
    rng = np.random.default_rng(0)
    durations_ms = []
    for i in range(scans):
        t_s = i * SCAN_PERIOD_S
        vehicle = _approach(t_s)
        started = time.perf_counter()
        render_scan(site, t_s, vehicle, mount, rng=rng, errors=errors, step_rad=step_rad)
        durations_ms.append((time.perf_counter() - started) * 1e3)
    return durations_ms


def main() -> None:
    site = load_site("launcher")
    mount = mount_pose(load_config("sim").geometry.scanner_left_mount)
    models = {
        "ideal": ideal_scanner(),
        "statistical only": statistical_only(0.01),
        "realistic": draw_scanner_errors(1, 0, realistic=True),
    }
    layouts = {"1081 beams (0.25°)": math.radians(0.25), "541 beams (0.5°)": math.radians(0.5)}
    for errors in models.values():  # warm-up: imports, scratch buffers, cached angles
        for step_rad in layouts.values():
            _time_scans(site, mount, errors, step_rad, 50)
    medians_ms: dict[str, float] = {}
    for layout, step_rad in layouts.items():
        for name, errors in models.items():
            durations_ms = _time_scans(site, mount, errors, step_rad, SCANS)
            medians_ms[f"{name}, {layout}"] = float(np.median(durations_ms))
            print(summarize(f"{name}, {layout}, moving", durations_ms, "ms"))
    for name in models:
        median_ms = medians_ms[f"{name}, 1081 beams (0.25°)"]
        share = DOCKING_SCANS_PER_S * median_ms / 1e3
        print(
            f"{name}: {DOCKING_SCANS_PER_S} scans of 1081 beams (docking, 20x real time) "
            f"take {share:.0%} of a second of one core"
        )


if __name__ == "__main__":
    main()
