"""Pallets in a worker's 3D point cloud, through its proximity points (Kinouchi et al.
2.2 (2)(i), after Tazaki et al. 2020).

**Proximity points** (`proximity`): per azimuth bin around a viewpoint, the point
within a height band (0.05 to 0.13 m above the floor) nearest the viewpoint: the
cloud as a 2D scan of the nearest obstacles, in which a pallet is an outline; less its
glimpses through holes up to ``max_hole_m`` wide (a fork opening in a sparse cloud).

**Clusters.** Successive proximity points (in azimuth, across at most a hole of
``max_hole_m``, wrapping round the full turn) are one object when closer than Borges &
Aldon's adaptive breakpoint distance (`perception.segments`): a jump in range or a gap
that a surface seen at more than 90° − λ to its normal would not leave. The points
beyond each end, within ``occlusion_window_m``, go to the fit with the cluster, which
judges against the fitted face whether the end is a true one
(`pallet_faces.continuation_hidden`): a point in front of the face's continuation, or
on it (the face cut off where it turns grazing, or past a hole), may hide more of it,
and its length is then only a lower bound. So may what stands above the band between
it and the viewpoint (a box on a pallet in front), from in front of the face's line:
its shadow on the band is empty in the viewpoint's own view, not a true end.

**Fusion.** Each viewpoint's clusters are fitted (`pallet_fit`), and the detections of
one pallet from several viewpoints (same kind, centres within a gate, postures within a
gate modulo the kind's symmetry) are merged by their information-weighted mean: a face
seen end-on from one side fixes what a single face from the other leaves loose. The
viewpoints' detections are taken as independent; two viewpoints that pick the very
same cloud points are not, and their fused covariance is then too small.

Caveats. The nearest of many noisy points in a bin is biased towards the viewpoint
(about 2σ of the cloud's noise for twenty points a bin): a pallet is found that much
nearer, which the covariance carries (``selection_bias_sigmas``). A map merged from
viewpoints that disagree shows every surface more than once (``registration_sigma_m``):
a consumer terminal's drift of a few cm makes a JIS side look as long as a EUR length,
and what is not sure is refused as ambiguous. Two pallets stored closer than a hole
are one object, refused. A walking person, smeared over several viewpoints, can look
like a short straight face: rarely, a loosely fitted pallet (large covariance) where
none is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

from appliance.mapping.pallet_fit import (
    ALL_KINDS,
    PalletFitParams,
    PalletRejection,
    PalletRejectReason,
    fit_pallet,
)
from appliance.mapping.pallet_fusion import fuse_pallets
from appliance.mapping.pallets import FloatArray, Pallet, PalletKind, PalletMap
from appliance.mapping.proximity import (
    DEFAULT_BAND_M,
    DEFAULT_STEP_RAD,
    IntArray,
    ProximityScan,
    as_rows,
    band_xy,
    check_step,
    drop_glimpses,
    hole_bins,
    proximity_points,
    proximity_scan,
)
from appliance.perception.segments import breakpoint_distance_m

__all__ = [
    "CloudPalletParams",
    "CloudPallets",
    "ClusterRejection",
    "ScanCluster",
    "cluster_scan",
    "detect_pallets",
    "proximity_points",
]


@dataclass(frozen=True)
class CloudPalletParams:
    """Detection settings (the band is explained in `proximity`).

    ``azimuth_step_rad`` 0.25°: 13 mm at 3 m, about a handheld LiDAR's point spacing
    there, so most bins hold points and a 0.8 m face at 8 m still gets 20. Ranges from
    0.5 m (the operator's own feet) to 15 m (beyond, the bins thin out). A hole of
    ``max_hole_m`` 5 cm (a sparse patch, a fork opening whose deck edge caught no point)
    may sit inside one object; two pallets stored closer than that are one object, and
    refused (no pallet is that long). The points beyond a cluster's end are looked for
    within ``occlusion_window_m`` 10 cm (twice a hole: past a hole, the face goes on).

    ``cloud_sigma_m`` 10 mm is the noise of a consumer terminal's map, in every
    direction (a map's points carry its registration's errors, not only their range's):
    the fit is given it along the rays and across them (conservative for a face seen
    head-on, right for one seen obliquely). The nearest of a bin's points is pulled
    towards the viewpoint by about ``selection_bias_sigmas`` of it (2: the expected
    minimum of ten to thirty normal draws is 1.5σ to 2σ below their mean), a systematic
    error of each face that the fit's ``offset_sigma_m`` carries.
    ``registration_sigma_m`` 2 cm: how far the viewpoints' clouds disagree in a map
    merged from them (a consumer terminal's tracking drifts by a few cm between
    viewpoints; set it to the terminal's, 0 for one consistent scan): the union shows
    each face doubled that far apart, thicker and longer (a JIS side read as a EUR
    length), and the fit is told so (its ``smear_sigma_m``). Per-viewpoint clouds would
    not be smeared, but are no better: a terminal's ray grid leaves rings of the band
    unsampled, and an end in one of them looks like a true end.

    Fusion gates: 0.3 m, under half a pallet's width, so two pallets never merge; 10°,
    far beyond two good fits' disagreement.
    """

    floor_z_m: float = 0.0
    height_band_m: tuple[float, float] = DEFAULT_BAND_M
    azimuth_step_rad: float = DEFAULT_STEP_RAD
    min_range_m: float = 0.5
    max_range_m: float = 15.0
    max_hole_m: float = 0.05
    breakpoint_lambda_rad: float = math.radians(10.0)
    occlusion_window_m: float = 0.1
    min_cluster_points: int = 6
    cloud_sigma_m: float = 0.01
    selection_bias_sigmas: float = 2.0
    registration_sigma_m: float = 0.02
    kinds: tuple[PalletKind, ...] = ALL_KINDS
    fit: PalletFitParams = field(default_factory=PalletFitParams)
    fuse_gate_m: float = 0.3
    fuse_gate_rad: float = math.radians(10.0)

    def __post_init__(self) -> None:
        low, high = self.height_band_m
        if not (math.isfinite(low) and math.isfinite(high) and low < high):
            raise ValueError(f"height_band_m must be finite (low, high), got {self.height_band_m}")
        check_step(self.azimuth_step_rad)
        if not 0.0 < self.breakpoint_lambda_rad <= math.pi / 2.0:
            raise ValueError("breakpoint_lambda_rad must be in (0, π/2]")
        if not (0.0 <= self.min_range_m < self.max_range_m and math.isfinite(self.floor_z_m)):
            raise ValueError("need 0 <= min_range_m < max_range_m and a finite floor_z_m")
        if self.min_cluster_points < 0:
            raise ValueError("min_cluster_points must be >= 0")
        for name in (
            "max_hole_m",
            "occlusion_window_m",
            "cloud_sigma_m",
            "selection_bias_sigmas",
            "registration_sigma_m",
            "fuse_gate_m",
            "fuse_gate_rad",
        ):
            value = getattr(self, name)
            if not (value >= 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if not (self.cloud_sigma_m > 0.0 and self.kinds):
            raise ValueError("cloud_sigma_m must be > 0 and kinds not empty")

    @property
    def fit_params(self) -> PalletFitParams:
        """The fit's settings for a cloud's points (a union of viewpoints' clouds):
        their noise in every direction (the surface term), the viewpoints' disagreement
        (the smear), the proximity points' pull and that disagreement in the offsets."""
        bias_m = self.selection_bias_sigmas * self.cloud_sigma_m
        fit = self.fit
        return replace(
            fit,
            surface_sigma_m=math.hypot(fit.surface_sigma_m, self.cloud_sigma_m),
            smear_sigma_m=math.hypot(fit.smear_sigma_m, self.registration_sigma_m),
            offset_sigma_m=math.hypot(fit.offset_sigma_m, bias_m, self.registration_sigma_m),
        )


@dataclass(frozen=True)
class ClusterRejection:
    """A cluster that gave no pallet, for the report: where it was and why."""

    viewpoint: int
    n_points: int
    centre_xy_m: tuple[float, float]
    reason: PalletRejectReason
    detail: str = ""


@dataclass(frozen=True)
class CloudPallets:
    """What a cloud yielded: the fused pallet map, each viewpoint's detections before
    fusion, the clusters that were not pallets, and how many were too small to try."""

    pallet_map: PalletMap
    detections: tuple[tuple[int, Pallet], ...]  # (viewpoint index, pallet)
    rejections: tuple[ClusterRejection, ...]
    small_clusters: int = 0


@dataclass(frozen=True, eq=False)
class ScanCluster:
    """One object of a proximity scan: indices into it (azimuth order), and the points
    past each end, (k, 2) each: the band's and the overhead's nearest points in the bins
    within ``occlusion_window_m`` past it (none when those bins are empty). The fit
    judges from them whether that end is a true one. ``closed``: the object goes all
    round the viewpoint (a room's walls), and has no ends."""

    indices: IntArray
    start_beyond_xy_m: FloatArray
    end_beyond_xy_m: FloatArray
    start_overhead_xy_m: FloatArray
    end_overhead_xy_m: FloatArray
    closed: bool = False


def cluster_scan(
    scan: ProximityScan, params: CloudPalletParams, overhead: ProximityScan | None = None
) -> list[ScanCluster]:
    """The proximity scan cut into objects at every gap a surface would not leave.
    ``overhead`` is the proximity scan of what is above the band, up to the viewpoint:
    a box there casts a shadow on the band behind it, in which a face may go on unseen
    (a viewpoint's own scan has no points in it, a bare end)."""
    count = int(scan.bins.shape[0])
    if count == 0:
        return []
    following = np.roll(np.arange(count), -1)
    bin_gap = (scan.bins[following] - scan.bins) % scan.bin_count
    step = scan.xy_m[following] - scan.xy_m
    limit = breakpoint_distance_m(
        scan.range_m,
        (bin_gap * scan.step_rad).astype(np.float64),
        params.breakpoint_lambda_rad,
        params.cloud_sigma_m,
    )
    holes = hole_bins(scan.range_m, scan.step_rad, params.max_hole_m)
    joined = (bin_gap >= 1) & (bin_gap - 1 <= holes)
    joined &= np.hypot(step[:, 0], step[:, 1]) <= limit
    ends = np.flatnonzero(~joined)  # a cluster ends where a point is not joined to the next
    if ends.shape[0] == 0:  # one object all round
        nothing = np.zeros((0, 2))
        return [ScanCluster(np.arange(count), nothing, nothing, nothing, nothing, True)]
    clusters = []
    window = params.occlusion_window_m
    for k, end in enumerate(ends.tolist()):
        start = (int(ends[k - 1]) + 1) % count  # after the end of the one before
        indices = np.arange(start, start + (end - start) % count + 1) % count
        before = _beyond(scan, indices, start, -1, window, overhead)
        after = _beyond(scan, indices, end, +1, window, overhead)
        clusters.append(ScanCluster(indices, before[0], after[0], before[1], after[1]))
    return clusters


def _beyond(
    scan: ProximityScan,
    members: IntArray,
    end: int,
    direction: int,
    window_m: float,
    overhead: ProximityScan | None,
) -> tuple[FloatArray, FloatArray]:
    """The band's points (never the cluster's own) and the overhead's past ``end``
    (``direction`` −1: before it, +1: after it), in the bins that span ``window_m`` at
    the end's range."""
    reach = float(hole_bins(scan.range_m[end : end + 1], scan.step_rad, window_m)[0])
    end_bin = scan.bins[end]
    away = (scan.bins - end_bin) * direction % scan.bin_count
    inside = (away >= 1) & (away <= reach)
    inside[members] = False
    if overhead is None:
        return scan.xy_m[inside], np.zeros((0, 2))
    above = (overhead.bins - end_bin) * direction % overhead.bin_count
    return scan.xy_m[inside], overhead.xy_m[(above >= 1) & (above <= reach)]


_BAD = PalletRejectReason.BAD_INPUT


def detect_pallets(
    xyz_m: npt.ArrayLike,
    origins_xyz_m: npt.ArrayLike,
    params: CloudPalletParams | None = None,
    *,
    frame: str = "",
) -> CloudPallets:
    """Pallets in a cloud (N, 3) seen from its viewpoints (V, 3) (a cloud without any
    is given the worker map's origin by the caller). Never raises on the arrays: points
    that are not finite are ignored, a viewpoint that is not finite is reported."""
    settings = params if params is not None else CloudPalletParams()
    cloud = as_rows(xyz_m, 3)
    origins = as_rows(origins_xyz_m, 3)
    rejections: list[ClusterRejection] = []
    low, high = (settings.floor_z_m + z for z in settings.height_band_m)
    band = band_xy(cloud, low, high)
    detections: list[tuple[int, Pallet]] = []
    small = 0
    for viewpoint, origin in enumerate(origins):
        if not np.isfinite(origin).all():
            rejections.append(ClusterRejection(viewpoint, 0, (0.0, 0.0), _BAD, "viewpoint"))
            continue
        # What is above the band, up to the viewpoint, may shadow the band behind it.
        above = band_xy(cloud, high, float(origin[2]))
        scans = [
            proximity_scan(
                points,
                origin[:2],
                settings.azimuth_step_rad,
                settings.min_range_m,
                settings.max_range_m,
            )
            for points in (band, above)
        ]
        scan = drop_glimpses(
            scans[0], settings.max_hole_m, settings.breakpoint_lambda_rad, settings.cloud_sigma_m
        )
        small += _fit_clusters(scan, scans[1], viewpoint, origin, settings, detections, rejections)
    fused = fuse_pallets(
        [pallet for _, pallet in detections], settings.fuse_gate_m, settings.fuse_gate_rad
    )
    source = f"cloud of {cloud.shape[0]} points, {origins.shape[0]} viewpoint(s)"
    return CloudPallets(
        PalletMap(fused, frame, source), tuple(detections), tuple(rejections), small
    )


def _fit_clusters(
    scan: ProximityScan,
    overhead: ProximityScan,
    viewpoint: int,
    origin: FloatArray,
    settings: CloudPalletParams,
    detections: list[tuple[int, Pallet]],
    rejections: list[ClusterRejection],
) -> int:
    """Every cluster of one viewpoint's scan fitted: pallets to ``detections``, the rest
    to ``rejections``; how many were too small to try."""
    fit_params = settings.fit_params
    small = 0
    for cluster in cluster_scan(scan, settings, overhead):
        points = scan.xy_m[cluster.indices]
        if points.shape[0] < settings.min_cluster_points:
            small += 1
            continue
        result = fit_pallet(
            points,
            (float(origin[0]), float(origin[1])),
            settings.kinds,
            settings.cloud_sigma_m,
            start_occluded=cluster.closed,
            end_occluded=cluster.closed,
            beyond_xy_m=(cluster.start_beyond_xy_m, cluster.end_beyond_xy_m),
            overhead_xy_m=(cluster.start_overhead_xy_m, cluster.end_overhead_xy_m),
            params=fit_params,
        )
        if isinstance(result, PalletRejection):
            x, y = points.mean(axis=0).tolist()
            rejection = ClusterRejection(
                viewpoint, points.shape[0], (x, y), result.reason, result.detail
            )
            rejections.append(rejection)
        else:
            detections.append((viewpoint, result))
    return small
