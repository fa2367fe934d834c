"""The `pallet` source's work that does not fit in a control cycle, as pure functions.

Each takes frozen values and returns one (`appliance.core.jobs` runs them on a thread in
the daemon and inline in replay and simulation): the vehicle's own pallets from the
scans it stood still for, merged with the worker's map (Kinouchi et al. 2.2: the
vehicle's map is the reference, the worker's is fitted to it through the pallets both
saw); and the plan to a pallet (``pallet_plan``). Also what the merged map is called
and drawn as: the names a worker taps on the tablet.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from appliance.guidance.pallet_approach_params import PalletOrder
from appliance.guidance.pallet_plan import PalletPlan
from appliance.localization.landmark_localizer import LandmarkEstimate
from appliance.mapping.merge import MergedPallet, MergeParams, MergeRefusal, MergeResult, merge_maps
from appliance.mapping.pallet_fit import ALL_KINDS
from appliance.mapping.pallet_fusion import fuse_pallets
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap
from appliance.mapping.scan_pallets import ScanPalletParams, detect_scan_pallets
from drivers.geometry import Pose2D

FloatArray = np.ndarray
# Detections of one pallet from both scanners are one pallet within these gates.
FUSE_GATE_M = 0.3
FUSE_GATE_RAD = math.radians(10.0)


@dataclass(frozen=True, eq=False)
class ScanView:
    """One scan as the merge needs it: ranges corrected for the scanner's offset, beam
    angles in the scanner's frame, and the scanner's pose in the site at the scan."""

    sensor: str
    ranges_m: FloatArray
    angles_rad: FloatArray
    scanner_pose: Pose2D


@dataclass(frozen=True, eq=False)
class SiteMerge:
    """The merge's outcome: the vehicle's own pallets and the merged map, or why not."""

    vehicle: PalletMap
    result: MergeResult | None
    refused: str = ""


def scan_pallets(view: ScanView, kinds: Sequence[PalletKind] = ALL_KINDS) -> tuple[Pallet, ...]:
    """The pallets of one scan, of the footprints ``kinds``. Looking for a known pallet,
    give its kind alone: one face seen square on (1.1 m: a 1100x1100's side or a
    1200x800's long one, within the noise) is then no longer ambiguous."""
    params = ScanPalletParams(kinds=tuple(kinds))
    return detect_scan_pallets(view.ranges_m, view.angles_rad, view.scanner_pose, params).pallets


def merge_from_scans(
    views: Sequence[ScanView],
    worker: PalletMap,
    marker: Pose2D,
    params: MergeParams,
    kinds: Sequence[PalletKind] = ALL_KINDS,
    alternatives: Sequence[Pallet] = (),
) -> SiteMerge:
    """The pallets of ``views`` (both scanners', fused) as the vehicle's map, and the
    worker's merged into it from the floor marker's T0."""
    seen = [pallet for view in views for pallet in scan_pallets(view, kinds)]
    vehicle = PalletMap(fuse_pallets(seen, FUSE_GATE_M, FUSE_GATE_RAD), "vehicle")
    if not vehicle.pallets:
        return SiteMerge(vehicle, None, "the vehicle sees no pallet to merge the maps through")
    merged = merge_maps(vehicle, worker, marker, params, alternatives)
    if isinstance(merged, MergeRefusal):
        return SiteMerge(vehicle, None, merged.reason)
    return SiteMerge(vehicle, merged, "")


def merged_names(merged: MergeResult, worker: PalletMap) -> tuple[str, ...]:
    """A name per merged pallet, as the worker knows it where the worker saw it (the
    terminal's), else ``vehicle-N``; unique (a repeat gets ``#2``, ``#3``)."""
    names: list[str] = []
    for i, entry in enumerate(merged.pallets):
        name = ""
        if entry.worker_index is not None and entry.worker_index < len(worker.pallets):
            name = worker.pallets[entry.worker_index].name
        if not name:
            name = f"vehicle-{i + 1}" if not entry.from_worker else f"worker-{i + 1}"
        base, n = name, 2
        while name in names:
            name, n = f"{base}#{n}", n + 1
        names.append(name)
    return tuple(names)


def pallet_document(name: str, entry: MergedPallet) -> dict[str, Any]:
    """One pallet as the tablet draws it (and `dbw status` lists it)."""
    pallet = entry.pallet
    document: dict[str, Any] = {
        "name": name,
        "kind": pallet.kind.value,
        "x_m": round(pallet.x_m, 4),
        "y_m": round(pallet.y_m, 4),
        "yaw_deg": round(math.degrees(pallet.yaw_rad), 3),
        "length_m": pallet.kind.length_m,
        "width_m": pallet.kind.width_m,
        "from": "worker" if entry.from_worker else "vehicle",
    }
    area = entry.reference_area
    if area is not None:
        document["reference_area"] = {
            "x_m": round(area.centre_x_m, 4),
            "y_m": round(area.centre_y_m, 4),
            "radius_m": round(area.radius_m, 4),
        }
    return document


def path_document(plan: PalletPlan, points: int = 200) -> list[list[float]]:
    """The plan's centre path, thinned to about ``points`` for the page."""
    centres = plan.centres_xy_m()
    step = max(1, math.ceil(len(centres) / points))
    kept = centres[::step]
    if len(centres) and (len(centres) - 1) % step:
        kept = np.vstack([kept, centres[-1:]])
    return [[round(float(x), 3), round(float(y), 3)] for x, y in kept]


def _finite(value: float, scale: float, digits: int) -> float | None:
    return round(scale * value, digits) if math.isfinite(value) else None


def pose_document(pose: Pose2D) -> dict[str, float]:
    return {
        "x_m": round(pose.x_m, 4),
        "y_m": round(pose.y_m, 4),
        "yaw_deg": round(math.degrees(pose.yaw_rad), 3),
    }


def estimate_document(estimate: LandmarkEstimate) -> dict[str, Any]:
    """The pose on the posts for `dbw status` (and the tablet's vehicle)."""
    document: dict[str, Any] = {
        "status": str(estimate.status),
        "reason": estimate.reason,
        "landmarks": list(estimate.landmarks),
    }
    if estimate.pose is not None:
        document["pose"] = pose_document(estimate.pose)
    return document


def order_document(order: PalletOrder) -> dict[str, Any]:
    """The approach's errors and what it waits for, for `dbw status`."""
    return {
        "lateral_mm": _finite(order.lateral_error_m, 1000.0, 2),
        "heading_deg": _finite(order.heading_error_rad, 180.0 / math.pi, 3),
        "distance_m": _finite(order.distance_m, 1.0, 3),
        "detections": order.detections,
        "waiting": order.waiting,
        "rejected": order.rejected,
    }
