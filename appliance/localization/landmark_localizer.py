"""Scans and odometry in, the vehicle's pose among surveyed reflector posts out.

Kinouchi et al.'s forklift needs its self-location in the storage area (the paper
presumes it known): here it is estimated from the same machinery as the flat-bed's on
the launcher: cylinders of one known radius extracted from both scanners' scans
(``perception.features``), the launcher's EKF reused as it is (``LauncherEkf``, with
the vehicle's centre as its state and each scanner's mount as its sensor pose), gating,
inflation after a run of rejections. What differs is what moves the prediction and what
starts it:

- **Odometry.** The vehicle reports its speed and steering angle; the rear axle steers
  (``rear_steer_odometry``: the body velocity at the centre, the simulator's kinematic
  bicycle with the front wheels straight, and the samples a scan is predicted through).
- **The first pose** comes from the map with no prior (``landmark_initial``): both
  scanners' cylinders within ``initial_pair_s``, the earlier scan's carried to the
  later's time by the odometry between them, matched by pairwise distances. Or it is
  given (`reset` with a pose hint, from the operator or the simulator): then it is not
  used (INITIALIZING) before a landmark has confirmed it.
- **Lost and found.** With no landmark accepted for ``relocalize_after_s`` the whole
  scan is searched again and a unique match restarts the filter.

The estimate says how good it is, as the launcher localizer's does: a status (OK,
DEGRADED, INITIALIZING, LOST) with a reason, for the safety layer to stop on. Only
INITIALIZING is new: "no pose yet" is a different thing to tell an operator than "lost
the pose".
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
import numpy.typing as npt

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.landmark_initial import (
    Detection,
    LandmarkMap,
    LandmarkMatch,
    MatchParams,
    carried,
    circle_detection,
    match_landmarks,
    merge_detections,
)
from appliance.localization.launcher_ekf import EkfParams, LauncherEkf, cylinder_terms
from appliance.localization.localizer_params import ScannerSetup
from appliance.localization.rear_steer_odometry import (
    OdometryHistory,
    OdometryParams,
    predict_through,
    rear_steer_motion,
)
from appliance.perception.features import DiscRoi, FeatureParams, extract_features
from appliance.perception.types import CircleFeature, ScanFeatures
from drivers.geometry import Pose2D

__all__ = [
    "LandmarkEstimate",
    "LandmarkLocalizer",
    "LandmarkLocalizerParams",
    "LandmarkMap",
    "LandmarkStatus",
    "OdometryParams",
]

FloatArray = npt.NDArray[np.float64]


class LandmarkStatus(StrEnum):
    OK = "ok"
    DEGRADED = "degraded"  # usable with care: automatic motion may not start or go on
    INITIALIZING = "initializing"  # no pose yet (or a given one not yet confirmed)
    LOST = "lost"  # had a pose and lost it: automatic motion stops


@dataclass(frozen=True)
class LandmarkLocalizerParams:
    """The ROI of a landmark is ``roi_m`` plus ``roi_sigmas`` of its predicted position's
    σ (the pose's, with the heading's at the landmark's range), at most ``max_roi_m``;
    only for landmarks within ``max_landmark_range_m`` of the scanner (the LMS111's
    20 m). The posts' radius in ``features`` is replaced by the map's."""

    features: FeatureParams = field(default_factory=FeatureParams)
    ekf: EkfParams = field(default_factory=EkfParams)
    odometry: OdometryParams = field(default_factory=OdometryParams)
    match: MatchParams = field(default_factory=MatchParams)
    scan_max_age_s: float = 0.12
    initial_pair_s: float = 0.1
    roi_m: float = 0.5
    roi_sigmas: float = 3.0
    max_roi_m: float = 1.5
    max_landmark_range_m: float = 20.5
    # A pose given by `reset` without a covariance: an operator's "about here".
    hint_sigma_m: float = 0.3
    hint_sigma_heading_rad: float = math.radians(5.0)
    # Status. A forklift at a walking pace drives 1 m blind on odometry for a few cm.
    lost_after_s: float = 1.0
    lost_sigma_m: float = 0.15
    degraded_sigma_m: float = 0.05
    degraded_heading_sigma_rad: float = math.radians(0.5)
    scanner_silent_after_s: float = 0.3
    odometry_silent_after_s: float = 0.2
    relocalize_after_s: float = 2.0
    # `estimate` predicts the last scan's pose to ``now_s`` by odometry, at most this far.
    max_extrapolation_s: float = 0.25
    # The statistical σ of a post's range and bearing the systematic term weighs with
    # (`systematic_covariance`): an LMS111's fit of a post a few metres out.
    weighting_range_sigma_m: float = 0.006
    weighting_bearing_sigma_rad: float = 0.002


@dataclass(frozen=True)
class LandmarkEstimate:
    """The vehicle centre's pose in the site frame at ``t_s`` (the last scan's pose
    carried to the asked time by odometry), its covariance over (x, y, yaw), the last
    scan it includes, and the landmarks accepted within ``lost_after_s``."""

    status: LandmarkStatus
    reason: str
    t_s: float | None
    pose: Pose2D | None
    covariance: FloatArray | None
    measured_t_s: float | None
    landmarks: tuple[str, ...]
    accepted: Mapping[str, int]
    rejected: Mapping[str, int]


def systematic_covariance(
    state: tuple[float, float, float],
    sightings: Mapping[str, list[tuple[float, float]]],
    scanners: Mapping[str, ScannerSetup],
    weighting: tuple[float, float],
) -> FloatArray:
    """The pose's covariance from the scanners' systematic errors, which no number of
    scans averages away (a "consider" covariance): the filter adds each scanner's
    systematic variances to every measurement as if they were new each time, and its
    covariance shrinks below what a mount's tenths of a degree leave (a mean NEES of 17
    on the pallets site, uncalibrated, against 2.4 calibrated).

    The least-squares pose from the landmarks each scanner has seen (``sightings``: their
    site coordinates) moves by ``G_s b_s`` for scanner s's range offset and yaw error
    ``b_s``: ``G_s = J⁻¹ Σ_{k∈s} H_kᵀ W``, ``J = Σ_k H_kᵀ W H_k``, ``W`` the
    ``weighting`` (range, bearing) σ's inverse squares. So ``Σ_s G_s diag(σ_r², σ_ψ²) G_sᵀ``.
    Zero when the landmarks seen do not fix the pose (J singular)."""
    w_range, w_bearing = weighting[0] ** -2, weighting[1] ** -2
    jacobians: dict[str, list[FloatArray]] = {}
    information = np.zeros((3, 3))
    for name, landmarks in sightings.items():
        mount = scanners[name].mount
        for xy in landmarks:
            _, h = cylinder_terms(state, xy, mount)
            h_array = np.array(h)
            jacobians.setdefault(name, []).append(h_array)
            information += w_range * np.outer(h_array[0], h_array[0])
            information += w_bearing * np.outer(h_array[1], h_array[1])
    if np.linalg.matrix_rank(information) < 3:
        return np.zeros((3, 3))
    inverse = np.linalg.inv(information)
    covariance = np.zeros((3, 3))
    for name, hs in jacobians.items():
        setup = scanners[name]
        weighted = sum((h.T * (w_range, w_bearing) for h in hs), np.zeros((3, 2)))
        gain = inverse @ weighted
        bias = np.diag([setup.systematic_range_sigma_m**2, setup.systematic_yaw_sigma_rad**2])
        covariance += gain @ bias @ gain.T
    result: FloatArray = 0.5 * (covariance + covariance.T)
    return result


def circle_polar(
    circle: CircleFeature, sensor: Pose2D, systematic: tuple[float, float]
) -> tuple[FloatArray, FloatArray]:
    """A circle's centre (vehicle frame) as range and bearing from the scanner, with its
    covariance ``J C Jᵀ`` plus the scanner's systematic range and bearing variances."""
    dx, dy = circle.cx_m - sensor.x_m, circle.cy_m - sensor.y_m
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    jac = np.array([[dx / r, dy / r], [-dy / q, dx / q]])
    covariance = jac @ np.asarray(circle.covariance) @ jac.T + np.diag(systematic)
    z = np.array([r, wrap_angle_rad(math.atan2(dy, dx) - sensor.yaw_rad)])
    return z, covariance


class LandmarkLocalizer:
    """`update` per scan, `odometry` per motion report, `estimate` per control cycle."""

    def __init__(
        self,
        scanner_mounts: Mapping[str, Pose2D | ScannerSetup],
        landmark_map: LandmarkMap,
        params: LandmarkLocalizerParams | None = None,
    ) -> None:
        if not scanner_mounts:
            raise ValueError("the localizer needs at least one scanner")
        params = params or LandmarkLocalizerParams()
        circles = replace(params.features.circles, radius_m=landmark_map.radius_m)
        self.params = replace(params, features=replace(params.features, circles=circles))
        # A bare mount is an uncalibrated scanner: ScannerSetup's systematic defaults.
        self.scanners = {
            name: s if isinstance(s, ScannerSetup) else ScannerSetup(Pose2D(*s))
            for name, s in scanner_mounts.items()
        }
        self.landmark_map = landmark_map
        self._landmarks_xy = list(landmark_map.xy)
        self._index = {lm.name: i for i, lm in enumerate(landmark_map.landmarks)}
        self.ekf = LauncherEkf(self.params.ekf)
        self._odometry = OdometryHistory(self.params.odometry)
        self.reset()

    def reset(
        self, pose_hint: Pose2D | None = None, covariance: npt.ArrayLike | None = None
    ) -> None:
        """Forget everything. With ``pose_hint`` (the vehicle centre in the site frame),
        start from it at the next scan rather than from the map, with ``covariance`` or
        the params' hint sigmas; it is used once a landmark has confirmed it."""
        p = self.params
        self.ekf.reset()
        self._odometry.reset()
        self._hint: tuple[Pose2D, FloatArray] | None = None
        if pose_hint is not None:
            if covariance is None:
                covariance = np.diag(
                    [p.hint_sigma_m**2, p.hint_sigma_m**2, p.hint_sigma_heading_rad**2]
                )
            cov = np.asarray(covariance, dtype=float)
            if cov.shape != (3, 3):
                raise ValueError(f"a pose hint's covariance is 3x3, not {cov.shape}")
            self._hint = (Pose2D(*pose_hint), cov)
        self._confirmed = False
        self._pending: dict[str, tuple[float, tuple[Detection, ...]]] = {}
        self._last_scan_s: dict[str, float] = {}
        self._last_accept_s: float | None = None
        # The last landmark accepted or the filter's (re)start: the whole scan is searched
        # again when this is ``relocalize_after_s`` old (a given pose never confirmed, too).
        self._anchor_s = -math.inf
        self._landmark_seen_s: dict[str, float] = {}
        self._seen_by: dict[tuple[str, str], float] = {}  # (scanner, landmark): last accepted
        self.stale_scans = 0
        self.out_of_order_scans = 0
        self.relocalizations = 0
        self.feature_rejections: Counter[str] = Counter()
        self.init_reason = "no scan yet"
        self.last_match: LandmarkMatch | None = None
        self.last_features: dict[str, ScanFeatures] = {}

    def odometry(
        self,
        t_s: float,
        speed_mps: float,
        steer_rad: float,
        wheelbase_m: float,
        *,
        characteristic_speed_mps: float = math.inf,
    ) -> None:
        """The vehicle's speed (at its centre) and steering angle (positive turns left)
        at ``t_s``; a sample older than the last one is dropped."""
        motion = rear_steer_motion(
            speed_mps, steer_rad, wheelbase_m, self.params.odometry, characteristic_speed_mps
        )
        self._odometry.add(t_s, motion)

    def update(
        self,
        sensor: str,
        ranges_m: FloatArray,
        angles_rad: FloatArray,
        t_s: float,
        now_s: float,
    ) -> None:
        """One scan, ``angles_rad`` in the scanner's frame (x out of its window)."""
        setup = self.scanners.get(sensor)
        if setup is None:
            raise KeyError(f"unknown scanner {sensor!r}")
        if now_s - t_s > self.params.scan_max_age_s:
            self.stale_scans += 1
            return
        self._last_scan_s[sensor] = max(t_s, self._last_scan_s.get(sensor, t_s))
        if self._hint is not None:
            pose, covariance = self._hint
            self._hint = None
            self.ekf.reset(pose, covariance, t_s)
            self._anchor_s = t_s
            self.init_reason = "the given pose is not confirmed by a landmark yet"
        if not self.ekf.initialized:
            features = self._whole_scan(sensor, setup, ranges_m, angles_rad)
            self._try_match(sensor, setup, features, t_s)
            return
        if not predict_through(self.ekf, self._odometry, t_s):
            self.out_of_order_scans += 1
            return
        self._odometry.forget_before(t_s - self.params.initial_pair_s)
        self._track(sensor, setup, ranges_m, angles_rad, t_s)
        # Still nothing accepted for long (or a given pose never confirmed): the map is
        # searched too, with the whole scan. Only the match may use that: the filter
        # keeps to its regions of interest, so clutter that passes the cylinder test
        # (the column, beyond 7 m) is not offered to a covariance rejections inflated.
        if t_s - self._anchor_s > self.params.relocalize_after_s:
            whole = self._whole_scan(sensor, setup, ranges_m, angles_rad)
            if self._try_match(sensor, setup, whole, t_s):
                self.relocalizations += 1

    def _track(
        self,
        sensor: str,
        setup: ScannerSetup,
        ranges_m: FloatArray,
        angles_rad: FloatArray,
        t_s: float,
    ) -> None:
        """The filter's update with the cylinders in the regions of interest."""
        features = extract_features(
            ranges_m, angles_rad, setup.mount, self.params.features,
            self._rois(setup.mount), range_offset_m=setup.range_offset_m,
        )  # fmt: skip
        self.last_features[sensor] = features
        self.feature_rejections.update(features.rejections)
        systematic = (setup.systematic_range_sigma_m**2, setup.systematic_yaw_sigma_rad**2)
        for circle in features.circles:
            z, r_cov = circle_polar(circle, setup.mount, systematic)
            index, outcome = self.ekf.update_nearest_cylinder(
                z, r_cov, self._landmarks_xy, setup.mount
            )
            if outcome.accepted:
                self._last_accept_s = self._anchor_s = t_s
                self._confirmed = True
                name = self.landmark_map.landmarks[index].name
                self._landmark_seen_s[name] = t_s
                self._seen_by[sensor, name] = t_s

    # ---- without a pose --------------------------------------------------------------
    def _whole_scan(
        self, sensor: str, setup: ScannerSetup, ranges_m: FloatArray, angles_rad: FloatArray
    ) -> ScanFeatures:
        features = extract_features(
            ranges_m, angles_rad, setup.mount, self.params.features,
            range_offset_m=setup.range_offset_m,
        )  # fmt: skip
        self.last_features[sensor] = features
        return features

    def _try_match(
        self, sensor: str, setup: ScannerSetup, features: ScanFeatures, t_s: float
    ) -> bool:
        """Match this scan's cylinders and every other scanner's latest (carried to
        ``t_s`` by odometry) to the map; on success the filter starts there."""
        p = self.params
        systematic = (setup.systematic_range_sigma_m**2, setup.systematic_yaw_sigma_rad**2)
        detections = tuple(
            circle_detection(c, sensor, setup.mount, systematic) for c in features.circles
        )
        self._pending[sensor] = (t_s, detections)
        fresh = {n: v for n, v in self._pending.items() if abs(t_s - v[0]) <= p.initial_pair_s}
        if len(fresh) < len(self.scanners):
            missing = sorted(set(self.scanners) - set(fresh))
            self.init_reason = f"waiting for scanner {', '.join(missing)}"
            return False
        seen: list[Detection] = []
        for then_s, found in fresh.values():
            if then_s == t_s:
                seen.extend(found)
            else:
                moved = self._odometry.relative(then_s, t_s)
                seen.extend(carried(d, moved) for d in found)
        merged = merge_detections(seen, p.match.merge_distance_m)
        match = match_landmarks(merged, self.landmark_map, p.match)
        if not isinstance(match, LandmarkMatch):
            self.init_reason = match.reason
            return False
        self.last_match = match
        self.ekf.reset(match.pose, match.covariance, t_s)
        self._last_accept_s = self._anchor_s = t_s
        self._confirmed = True
        for _, name in match.pairs:
            self._landmark_seen_s[name] = t_s
        self._pending.clear()
        self.init_reason = ""
        return True

    # ---- with a pose -----------------------------------------------------------------
    def _rois(self, sensor: Pose2D) -> list[DiscRoi]:
        """Discs around the landmarks as the predicted pose puts them, in the vehicle frame."""
        p = self.params
        x, y, yaw = self.ekf.state_floats
        (pxx, pxy, _), (_, pyy, _), (_, _, pyaw) = self.ekf.covariance.tolist()
        largest = 0.5 * (pxx + pyy) + math.hypot(0.5 * (pxx - pyy), pxy)
        c, s = math.cos(yaw), math.sin(yaw)
        rois = []
        for lx, ly in self._landmarks_xy:
            dx, dy = lx - x, ly - y
            vx, vy = c * dx + s * dy, -s * dx + c * dy
            range_m = math.hypot(vx - sensor.x_m, vy - sensor.y_m)
            if range_m > p.max_landmark_range_m:
                continue
            sigma = math.sqrt(max(largest, 0.0) + range_m * range_m * max(pyaw, 0.0))
            rois.append(DiscRoi(vx, vy, min(p.max_roi_m, p.roi_m + p.roi_sigmas * sigma)))
        return rois

    # ---- what the rest of the vehicle reads ------------------------------------------
    def estimate(self, now_s: float) -> LandmarkEstimate:
        p = self.params
        counts = (dict(self.ekf.accepted), dict(self.ekf.rejected))
        recent = tuple(
            sorted(n for n, t in self._landmark_seen_s.items() if now_s - t <= p.lost_after_s)
        )
        if not self.ekf.initialized or self.ekf.t_s is None:
            return LandmarkEstimate(
                LandmarkStatus.INITIALIZING, self.init_reason or "no pose", None, None, None,
                None, recent, *counts,
            )  # fmt: skip
        measured_s = self.ekf.t_s
        until_s = min(max(now_s, measured_s), measured_s + p.max_extrapolation_s)
        ahead = LauncherEkf(p.ekf)
        ahead.reset(self.ekf.pose, self.ekf.covariance, measured_s)
        predict_through(ahead, self._odometry, until_s)
        sightings: dict[str, list[tuple[float, float]]] = {}
        for (sensor, name), seen_s in self._seen_by.items():
            if now_s - seen_s <= p.lost_after_s:
                landmark = self.landmark_map.landmarks[self._index[name]]
                sightings.setdefault(sensor, []).append((landmark.x_m, landmark.y_m))
        weighting = (p.weighting_range_sigma_m, p.weighting_bearing_sigma_rad)
        systematic = systematic_covariance(ahead.state_floats, sightings, self.scanners, weighting)
        pose, cov = ahead.pose, ahead.covariance + systematic
        status, reason = self._status(now_s, cov)
        return LandmarkEstimate(status, reason, until_s, pose, cov, measured_s, recent, *counts)

    def _status(self, now_s: float, cov: FloatArray) -> tuple[LandmarkStatus, str]:
        p = self.params
        (pxx, pxy, _), (_, pyy, _), (_, _, pyaw) = cov.tolist()
        # The larger eigenvalue of the position's 2x2 covariance, in closed form.
        largest = 0.5 * (pxx + pyy) + math.hypot(0.5 * (pxx - pyy), pxy)
        sigma_m = math.sqrt(max(largest, 0.0))
        sigma_yaw = math.sqrt(max(pyaw, 0.0))
        silent = [
            name
            for name in sorted(self.scanners)
            if now_s - self._last_scan_s.get(name, -math.inf) > p.scanner_silent_after_s
        ]
        odometry_s = self._odometry.last_s
        if not self._confirmed:
            return LandmarkStatus.INITIALIZING, self.init_reason
        if len(silent) == len(self.scanners):
            return LandmarkStatus.LOST, f"scanner {', '.join(silent)} silent"
        unseen_s = now_s - (self._last_accept_s if self._last_accept_s is not None else -math.inf)
        if unseen_s > p.lost_after_s:
            return LandmarkStatus.LOST, f"no landmark accepted for {unseen_s:.2f} s"
        if sigma_m > p.lost_sigma_m:
            return LandmarkStatus.LOST, f"position sigma {sigma_m * 100:.1f} cm"
        if sigma_m > p.degraded_sigma_m or sigma_yaw > p.degraded_heading_sigma_rad:
            return (
                LandmarkStatus.DEGRADED,
                f"sigma {sigma_m * 1000:.0f} mm, {math.degrees(sigma_yaw):.2f} deg",
            )
        if silent:
            return LandmarkStatus.DEGRADED, f"scanner {', '.join(silent)} silent"
        if odometry_s is None or now_s - odometry_s > p.odometry_silent_after_s:
            return LandmarkStatus.DEGRADED, "no odometry"
        return LandmarkStatus.OK, ""
