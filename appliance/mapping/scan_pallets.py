"""Pallets in the vehicle's own 2D scans (Kinouchi et al. 2.2 (2)(i): the vehicle map's side).

A 2D scan is already what a worker's cloud is turned into before its pallets are looked
for: the nearest point along every direction from one viewpoint, in one plane (the
scanner's; an underbody scanner's plane cuts a pallet's blocks). So a scan is made into a
`ProximityScan` (a bin per beam) and goes through the same clustering and the same fit
as the cloud (`cloud_pallets.cluster_scan`, `pallet_fit.fit_pallet`), with the scanner's
own noise instead of the cloud's. Where the points are is the caller's choice of frame:
the scanner's mount gives vehicle-frame pallets (the final approach tracks these: no
localization error in them), the localizer's pose composed with the mount gives the
site's (the vehicle's pallet map for the merge).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from appliance.mapping.cloud_pallets import CloudPalletParams, cluster_scan
from appliance.mapping.pallet_fit import ALL_KINDS, PalletRejection, PalletRejectReason, fit_pallet
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap
from appliance.mapping.proximity import ProximityScan
from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]


@dataclass(frozen=True)
class ScanPalletParams:
    kinds: tuple[PalletKind, ...] = ALL_KINDS
    # The LMS111's range noise (1 sigma) at the ranges a pallet is approached from.
    range_sigma_m: float = 0.012
    min_range_m: float = 0.1
    max_range_m: float = 15.0
    # The clustering and the fit: the cloud's, without a cloud's smear (one scan is one
    # viewpoint at one instant) and with the scanner's noise.
    cloud: CloudPalletParams = field(
        default_factory=lambda: CloudPalletParams(
            registration_sigma_m=0.0, selection_bias_sigmas=0.0
        )
    )

    def __post_init__(self) -> None:
        if not (self.range_sigma_m > 0.0 and 0.0 <= self.min_range_m < self.max_range_m):
            raise ValueError("need range_sigma_m > 0 and 0 <= min_range_m < max_range_m")
        if not self.kinds:
            raise ValueError("kinds must name at least one pallet footprint")

    @property
    def clustering(self) -> CloudPalletParams:
        return replace(self.cloud, cloud_sigma_m=self.range_sigma_m, kinds=self.kinds)


@dataclass(frozen=True)
class ScanRejection:
    n_points: int
    centre_xy_m: tuple[float, float]
    reason: PalletRejectReason
    detail: str = ""


@dataclass(frozen=True)
class ScanPallets:
    pallets: tuple[Pallet, ...]
    rejections: tuple[ScanRejection, ...]

    def pallet_map(self, frame: str = "", source: str = "") -> PalletMap:
        return PalletMap(self.pallets, frame, source)


def scan_proximity(
    ranges_m: npt.ArrayLike,
    angles_rad: npt.ArrayLike,
    scanner: Pose2D,
    params: ScanPalletParams,
) -> ProximityScan | None:
    """The scan as a proximity scan in the frame ``scanner`` is given in: a bin per beam
    step of absolute azimuth, echoes only (0 and out-of-range readings dropped); None
    for a scan whose beams are not evenly stepped."""
    ranges = np.asarray(ranges_m, dtype=np.float64).ravel()
    angles = np.asarray(angles_rad, dtype=np.float64).ravel()
    if ranges.shape != angles.shape or ranges.shape[0] < 2 or not np.isfinite(angles).all():
        return None
    step = float(np.median(np.diff(angles)))
    if not (step > 0.0 and np.allclose(np.diff(angles), step, rtol=1e-6, atol=1e-9)):
        return None
    bin_count = round(2.0 * math.pi / step)
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(ranges) & (ranges >= params.min_range_m)
        valid &= ranges <= params.max_range_m
    world = angles[valid] + scanner.yaw_rad
    distance = ranges[valid]
    xy = np.column_stack(
        (scanner.x_m + distance * np.cos(world), scanner.y_m + distance * np.sin(world))
    )
    bins = np.floor((np.remainder(world + math.pi, 2.0 * math.pi)) / step).astype(np.int64)
    bins %= bin_count
    order = np.argsort(bins, kind="stable")
    bins, xy, distance = bins[order], xy[order], distance[order]
    keep = np.ones(bins.shape[0], dtype=bool)
    keep[1:] = bins[1:] != bins[:-1]  # two beams in one bin (rounding): the first
    return ProximityScan(bins[keep], xy[keep], distance[keep], bin_count, step)


def detect_scan_pallets(
    ranges_m: npt.ArrayLike,
    angles_rad: npt.ArrayLike,
    scanner: Pose2D,
    params: ScanPalletParams | None = None,
) -> ScanPallets:
    """The pallets one scan shows. ``angles_rad`` are the beams' in the scanner's frame
    (x out of its window), ``scanner`` its pose in the output frame. Never raises on the
    arrays: a malformed scan gives nothing, a cluster that is no pallet a rejection."""
    settings = params or ScanPalletParams()
    scan = scan_proximity(ranges_m, angles_rad, scanner, settings)
    if scan is None or scan.bins.shape[0] == 0:
        return ScanPallets((), ())
    clustering = settings.clustering
    fit_params = clustering.fit_params
    pallets: list[Pallet] = []
    rejections: list[ScanRejection] = []
    for cluster in cluster_scan(scan, clustering):
        points = scan.xy_m[cluster.indices]
        if points.shape[0] < clustering.min_cluster_points:
            continue
        result = fit_pallet(
            points,
            (scanner.x_m, scanner.y_m),
            settings.kinds,
            settings.range_sigma_m,
            start_occluded=cluster.closed,
            end_occluded=cluster.closed,
            beyond_xy_m=(cluster.start_beyond_xy_m, cluster.end_beyond_xy_m),
            params=fit_params,
        )
        if isinstance(result, PalletRejection):
            x, y = points.mean(axis=0).tolist()
            rejections.append(ScanRejection(points.shape[0], (x, y), result.reason, result.detail))
        else:
            pallets.append(result)
    return ScanPallets(tuple(pallets), tuple(rejections))
