"""The last scans for the operator page: each scanner's latest scan in the vehicle frame,
thinned to a few hundred points (a browser draws them; the localizer has the full ones)."""

from __future__ import annotations

import math
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from appliance.topics import TopicRegistry
from drivers.lms111.mounted import MountedScan

MAX_POINTS: Final = 360
SCAN_TOPIC_PREFIX: Final = "scan."


def decimate(points: npt.NDArray[np.float64], max_points: int) -> npt.NDArray[np.float64]:
    """At most ``max_points`` rows, evenly strided, in beam order."""
    if max_points < 1:
        raise ValueError(f"max_points must be at least 1 (got {max_points})")
    stride = max(1, math.ceil(len(points) / max_points))
    return points[::stride]


def scan_entry(scan: MountedScan, age_s: float, max_points: int = MAX_POINTS) -> dict[str, Any]:
    points = decimate(scan.points_vehicle_m(), max_points)
    return {
        "sensor": scan.sensor,
        "age_s": round(age_s, 3) if math.isfinite(age_s) else None,
        "mount": {
            "x_m": round(scan.mount.x_m, 3),
            "y_m": round(scan.mount.y_m, 3),
            "yaw_deg": round(math.degrees(scan.mount.yaw_rad), 2),
        },
        "points_m": np.round(points, 3).tolist(),
    }


def scans_document(
    topics: TopicRegistry, now_s: float, max_points: int = MAX_POINTS
) -> dict[str, Any]:
    """``{"frame": "vehicle", "scans": {"left": {...}, ...}}`` from every ``scan.*`` topic."""
    scans: dict[str, Any] = {}
    for name, topic in topics.items():
        sample = topic.latest() if name.startswith(SCAN_TOPIC_PREFIX) else None
        if sample is not None and isinstance(sample.value, MountedScan):
            scans[name.removeprefix(SCAN_TOPIC_PREFIX)] = scan_entry(
                sample.value, sample.age_s(now_s), max_points
            )
    return {"frame": "vehicle", "scans": scans}
