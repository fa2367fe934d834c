"""Cost of rendering one simulated LMS111 scan: two scanners at 50 Hz must be cheap.

Figures: the median and p99 time of one 1081-beam scan (0.25°, 270°) of the built-in
launcher site (what the twins render every 20 ms, twice), of the 541-beam variant, and
of a denser scene of 50 segments and 10 circles (the target: well under 2 ms).
"""

from __future__ import annotations

import math
import time

import numpy as np

from appliance.sim import Circle, Segment, Site, load_site, render_scan
from benchmarks.stats import summarize

VEHICLE = (-10.0, 0.3, math.radians(2.0))  # about where Qian et al.'s approach starts
LEFT_MOUNT = (0.0, 1.1, math.radians(45.0))


def _time_scans(site: Site, scans: int, step_rad: float) -> list[float]:
    rng = np.random.default_rng(0)
    durations_ms = []
    for i in range(scans):
        t_s = i * 0.02
        started = time.perf_counter()
        render_scan(site, t_s, VEHICLE, LEFT_MOUNT, rng=rng, step_rad=step_rad)
        durations_ms.append((time.perf_counter() - started) * 1e3)
    return durations_ms


def _dense_site(segments: int = 50, circles: int = 10) -> Site:
    """The launcher site padded with random walls and posts up to the stated counts."""
    base = load_site("launcher")
    rng = np.random.default_rng(1)
    walls = rng.uniform(-20.0, 10.0, size=(segments - len(base.segments), 4))
    posts = rng.uniform(-20.0, 10.0, size=(circles - len(base.circles) - len(base.movers), 2))
    extra_segments = tuple(
        Segment(float(x0), float(y0), float(x1), float(y1), 0.5, f"wall_{i}")
        for i, (x0, y0, x1, y1) in enumerate(walls)
    )
    extra_circles = tuple(
        Circle(float(x), float(y), 0.2, 0.3, f"post_{i}") for i, (x, y) in enumerate(posts)
    )
    return base.merged(Site(extra_segments, extra_circles), name="dense")


def main() -> None:
    launcher = load_site("launcher")
    dense = _dense_site()
    _time_scans(launcher, 50, math.radians(0.25))  # warm-up: imports, scratch buffers
    _time_scans(dense, 50, math.radians(0.25))
    print(
        summarize(
            "launcher site, 1081 beams (7 segments, 5 circles)",
            _time_scans(launcher, 2000, math.radians(0.25)),
            "ms",
        )
    )
    print(
        summarize("launcher site, 541 beams", _time_scans(launcher, 2000, math.radians(0.5)), "ms")
    )
    shapes = dense.shapes_at(0.0)
    print(
        summarize(
            f"dense site, 1081 beams ({len(shapes.segments)} segments, "
            f"{len(shapes.circles)} circles)",
            _time_scans(dense, 2000, math.radians(0.25)),
            "ms",
        )
    )


if __name__ == "__main__":
    main()
