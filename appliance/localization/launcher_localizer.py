"""Scans in, the vehicle's pose on the launcher out: features, initial pose, EKF, status.

One small class the daemon, the docking simulation and replay all step the same way:
``update(sensor, ranges_m, angles_rad, t_s, now_s)`` per scan, ``estimate(now_s)`` per
control cycle. With no pose yet it looks for the whole front board in both scanners
(``initial_pose``); from then on it searches only around the predicted landmarks
(regions of interest, 3.2.3 b), predicts with the board's motion, and updates with every
cylinder each scanner sees (eq. 5, with that scanner's own offset) and with the board.

The estimate says how good it is, as SICK's own localization reports it: a status
(``ok``, ``degraded``, ``lost``) and a quality from 0 to 100, for the safety layer to stop
automatic motion on. A scan older than ``scan_max_age_s`` is never used.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from appliance.localization.board_motion import (
    BoardEnd,
    BoardMotion,
    BoardSighting,
)
from appliance.localization.compound import wrap_angle_rad
from appliance.localization.ekf_floats import sandwich
from appliance.localization.initial_pose import (
    InitialPose,
    InitialPoseParams,
    board_end_sigma_m,
    initial_pose,
)
from appliance.localization.launcher_ekf import (
    BodyMotion,
    LauncherEkf,
    cylinder_terms,
)
from appliance.localization.launcher_map import CylinderLandmark
from appliance.localization.localizer_params import (
    LocalizationEstimate,
    LocalizationStatus,
    LocalizerParams,
    ScannerSetup,
)
from appliance.perception.features import DiscRoi, LineRoi, extract_features
from appliance.perception.types import CircleFeature, LineFeature, ScanFeatures
from drivers.geometry import Pose2D

# Re-exported: the localizer's own API is these with the class below.
__all__ = [
    "LauncherLocalizer",
    "LocalizationEstimate",
    "LocalizationStatus",
    "LocalizerParams",
    "ScannerSetup",
]

FloatArray = NDArray[np.float64]


def _polar(
    circle: CircleFeature, sensor: Pose2D, extra: tuple[float, float] = (0.0, 0.0)
) -> tuple[FloatArray, FloatArray]:
    """A circle's centre as range and bearing from the scanner, with covariance (``J C
    Jᵀ`` written out in floats: numpy's 2x2 products cost more than their arithmetic),
    plus ``extra`` on its diagonal (a scanner's systematic variances)."""
    dx, dy = circle.cx_m - sensor.x_m, circle.cy_m - sensor.y_m
    q = dx * dx + dy * dy
    r = math.sqrt(q)
    z = np.array([r, wrap_angle_rad(math.atan2(dy, dx) - sensor.yaw_rad)])
    (j00, j01), (j10, j11) = (dx / r, dy / r), (-dy / q, dx / q)
    (c00, c01), (c10, c11) = circle.covariance.tolist()
    t00, t01 = j00 * c00 + j01 * c10, j00 * c01 + j01 * c11
    t10, t11 = j10 * c00 + j11 * c10, j10 * c01 + j11 * c11
    cross = t00 * j10 + t01 * j11
    covariance = np.array(
        [
            [t00 * j00 + t01 * j01 + extra[0], cross],
            [t10 * j00 + t11 * j01, t10 * j10 + t11 * j11 + extra[1]],
        ]
    )
    return z, covariance


class _Verdicts:
    """One landmark's verdicts (time, accepted, NIS) over the disagreement window, with the
    counts ``estimate`` reads kept as they come and go (it asks at every control cycle).

    The NIS that goes into the mean is capped at the gate: a sighting kept out says it
    was beyond the gate, not by how much. Uncapped, one outlier (a mixed echo, a person
    passing the cylinder) with a NIS of a few hundred tipped a 2 s mean of about 60
    sightings over its limit for a cycle, and the daemon stopped 0.34 m from the troughs
    ("cylinder_left disagrees with the map", in the in-process docking test and in HIL).
    Many sightings kept out still tip it, at the gate's value each, and count as failures."""

    def __init__(self) -> None:
        self.entries: deque[tuple[float, bool, float]] = deque()
        self.failed = 0  # not accepted
        self.missed = 0  # not accepted because not found (NIS nan)
        self.finite_nis: deque[float] = deque()  # the finite NIS values, oldest first

    def add(self, t_s: float, accepted: bool, nis: float, window_s: float, cap: float) -> None:
        self._count((t_s, accepted, nis), 1)
        self.entries.append((t_s, accepted, nis))
        if math.isfinite(nis):
            self.finite_nis.append(min(nis, cap))
        while self.entries and t_s - self.entries[0][0] > window_s:
            oldest = self.entries.popleft()
            self._count(oldest, -1)
            if math.isfinite(oldest[2]):
                self.finite_nis.popleft()

    def _count(self, entry: tuple[float, bool, float], sign: int) -> None:
        _, accepted, nis = entry
        if not accepted:
            self.failed += sign
            self.missed += sign * math.isnan(nis)


class LauncherLocalizer:
    def __init__(
        self, scanners: Mapping[str, ScannerSetup], params: LocalizerParams | None = None
    ) -> None:
        if not scanners:
            raise ValueError("the localizer needs at least one scanner")
        self.params = params or LocalizerParams()
        self.scanners = dict(scanners)
        # O_f: midway between the scanners (Fig. 7); each scanner's pose in the O_f frame.
        xs = [s.mount.x_m for s in scanners.values()]
        ys = [s.mount.y_m for s in scanners.values()]
        self.origin_in_vehicle = Pose2D(sum(xs) / len(xs), sum(ys) / len(ys), 0.0)
        self.sensors = {
            name: Pose2D(
                s.mount.x_m - self.origin_in_vehicle.x_m,
                s.mount.y_m - self.origin_in_vehicle.y_m,
                s.mount.yaw_rad,
            )
            for name, s in scanners.items()
        }
        self._initial = self._initial_params()
        # The map's cylinders (a property that builds them anew at every read), once.
        self._cylinders = self.params.launcher.cylinders
        self._landmarks_xy = [(lm.x_m, lm.y_m) for lm in self._cylinders]
        self.ekf = LauncherEkf(self.params.ekf)
        self.motion = BoardMotion(self.params.board_motion)
        self.reset()

    def reset(self) -> None:
        self.ekf.reset()
        self.motion.reset()
        self.stale_scans = 0
        self.feature_rejections: Counter[str] = Counter()
        self._pending: dict[str, tuple[float, ScanFeatures]] = {}
        self._last_accept_s: float | None = None
        self._last_cylinder_s: float | None = None
        self._last_scan_s: dict[str, float] = {}
        self._verdicts: dict[str, _Verdicts] = {}
        self.init_reason = "no scan yet"
        self.last_features: dict[str, ScanFeatures] = {}

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
        if not self.ekf.initialized:
            self._initialize(sensor, ranges_m, angles_rad, t_s)
            return
        self._track(sensor, setup, ranges_m, angles_rad, t_s)

    # ---- without a pose --------------------------------------------------------------
    def _initialize(
        self, sensor: str, ranges_m: FloatArray, angles_rad: FloatArray, t_s: float
    ) -> None:
        p = self.params
        setup = self.scanners[sensor]
        features = extract_features(
            ranges_m, angles_rad, self.sensors[sensor], p.features,
            range_offset_m=setup.range_offset_m,
        )  # fmt: skip
        self.last_features[sensor] = features
        self._pending[sensor] = (t_s, features)
        fresh = {n: f for n, (t, f) in self._pending.items() if t_s - t <= p.initial_pair_s}
        if len(fresh) < len(self.scanners):
            self.init_reason = "waiting for every scanner"
            return
        found = initial_pose(fresh, self.sensors, p.launcher, self._initial)
        if not isinstance(found, InitialPose):
            self.init_reason = found.reason
            return
        self.ekf.reset(found.pose, found.covariance, t_s)
        self._last_accept_s = t_s
        self.init_reason = ""

    def _initial_params(self) -> InitialPoseParams:
        """The first pose's parameters with the worst scanner's systematic error."""
        return replace(
            self.params.initial,
            systematic_range_sigma_m=max(
                s.systematic_range_sigma_m for s in self.scanners.values()
            ),
            systematic_yaw_sigma_rad=max(
                s.systematic_yaw_sigma_rad for s in self.scanners.values()
            ),
        )

    # ---- with a pose -----------------------------------------------------------------
    def _rois(
        self, state: tuple[float, float, float], cylinders: tuple[CylinderLandmark, ...]
    ) -> list[DiscRoi | LineRoi]:
        p = self.params
        x, y, yaw = state
        c, s = math.cos(yaw), math.sin(yaw)

        def to_of(x_m: float, y_m: float) -> tuple[float, float]:
            dx, dy = x_m - x, y_m - y
            return c * dx + s * dy, -s * dx + c * dy

        half = p.launcher.half_width_m
        (x0, y0), (x1, y1) = to_of(0.0, -half), to_of(0.0, half)
        rois: list[DiscRoi | LineRoi] = [LineRoi(x0, y0, x1, y1, p.board_roi_m)]
        for landmark in cylinders:
            cx, cy = to_of(landmark.x_m, landmark.y_m)
            rois.append(DiscRoi(cx, cy, p.cylinder_roi_m))
        return rois

    def _track(
        self,
        sensor: str,
        setup: ScannerSetup,
        ranges_m: FloatArray,
        angles_rad: FloatArray,
        t_s: float,
    ) -> None:
        p = self.params
        motion = self.motion.motion(t_s) or BodyMotion.still()
        if not self.ekf.predict(t_s, motion):
            return
        pose_in_of = self.sensors[sensor]
        cylinders = self._cylinders
        features = extract_features(
            ranges_m, angles_rad, pose_in_of, p.features,
            self._rois(self.ekf.state_floats, cylinders), range_offset_m=setup.range_offset_m,
        )  # fmt: skip
        self.last_features[sensor] = features
        self.feature_rejections.update(features.rejections)
        systematic = (setup.systematic_range_sigma_m**2, setup.systematic_yaw_sigma_rad**2)
        # Per landmark, this scan's best: one detection accepted is the landmark seen,
        # whatever else near it (a post, a person) was kept out.
        seen: dict[str, tuple[bool, float]] = {}
        landmarks_xy = self._landmarks_xy
        for circle in features.circles:
            z, r_cov = _polar(circle, pose_in_of, systematic)
            index, outcome = self.ekf.update_nearest_cylinder(z, r_cov, landmarks_xy, pose_in_of)
            best = cylinders[index]
            accepted, nis = seen.get(best.name, (False, math.inf))
            seen[best.name] = (accepted or outcome.accepted, min(nis, outcome.nis))
            if outcome.accepted:
                self._last_accept_s = self._last_cylinder_s = t_s
        for landmark in cylinders:
            if landmark.name not in seen and self._in_view(landmark, pose_in_of):
                seen[landmark.name] = (False, math.nan)  # predicted in view, not found
        for name, (accepted, nis) in seen.items():
            verdicts = self._verdicts.setdefault(name, _Verdicts())
            verdicts.add(t_s, accepted, nis, p.disagreement_window_s, self.ekf.gate_2d)
        board = self._board_line(features.lines)
        if board is not None:
            z = np.array([board.r_m, board.alpha_rad])
            r_cov = board.covariance + np.diag(systematic)
            if self.ekf.update_board(z, r_cov).accepted:
                self._last_accept_s = t_s
            self.motion.update(sensor, self._sighting(board, pose_in_of, t_s))

    def _board_line(self, lines: tuple[LineFeature, ...]) -> LineFeature | None:
        """The line that is the front board, as predicted; the longest if it is split."""
        p = self.params
        x, _, yaw = self.ekf.state_floats
        expected_r, expected_alpha = -x, wrap_angle_rad(-yaw)
        matches = [
            line
            for line in lines
            if abs(wrap_angle_rad(line.alpha_rad - expected_alpha)) <= p.board_match_heading_rad
            and abs(line.r_m - expected_r) <= p.board_match_range_m
        ]
        return max(matches, key=lambda line: line.n_points, default=None)

    def _sighting(self, line: LineFeature, sensor: Pose2D, t_s: float) -> BoardSighting:
        initial = self.params.initial
        normal = (math.cos(line.alpha_rad), math.sin(line.alpha_rad))
        ends: list[tuple[float, BoardEnd | None]] = []
        sides = ((line.start_xy_m, line.start_occluded), (line.end_xy_m, line.end_occluded))
        for xy, occluded in sides:
            sigma = board_end_sigma_m(xy, sensor, normal, initial)
            along = -normal[1] * xy[0] + normal[0] * xy[1]  # along the tangent (−n_y, n_x)
            ends.append((along, None if occluded else BoardEnd(*xy, sigma)))
        ends.sort(key=lambda pair: pair[0])
        return BoardSighting(
            t_s, line.r_m, line.alpha_rad, np.asarray(line.covariance), ends[0][1], ends[1][1]
        )

    # ---- what the rest of the vehicle reads ------------------------------------------
    def _in_view(self, landmark: CylinderLandmark, sensor: Pose2D) -> bool:
        """Whether the predicted landmark is well inside this scanner's field and range."""
        (range_m, bearing_rad), _ = cylinder_terms(
            self.ekf.state_floats, (landmark.x_m, landmark.y_m), sensor
        )
        p = self.params
        return (
            p.in_view_min_range_m <= range_m <= p.in_view_max_range_m
            and abs(bearing_rad) <= p.in_view_half_angle_rad
        )

    def _disagreeing_landmarks(self) -> list[str]:
        """Landmarks seen often and mostly rejected, or whose innovations are persistently
        far larger than their covariance says (mean NIS against its expected 2): the map
        is not the launcher, and a pose that fits the landmarks that agree with each other
        proves nothing. One cylinder kept out now and then is a person walking past."""
        p = self.params
        found = []
        for name, verdicts in sorted(self._verdicts.items()):
            count = len(verdicts.entries)
            if count < p.disagreement_min_sightings:
                continue
            nis = verdicts.finite_nis
            mean_nis = sum(nis) / len(nis) if nis else 0.0
            if verdicts.failed > p.disagreement_fraction * count:
                found.append(
                    f"{name} not seen where the map puts it"
                    if verdicts.missed > verdicts.failed / 2
                    else f"{name} disagrees with the map"
                )
            elif mean_nis > p.disagreement_mean_nis:
                found.append(f"{name} disagrees with the map")
        return found

    def _silent_scanners(self, now_s: float) -> list[str]:
        limit = self.params.scanner_silent_after_s
        return [
            name
            for name in sorted(self.scanners)
            if now_s - self._last_scan_s.get(name, -math.inf) > limit
        ]

    def estimate(self, now_s: float) -> LocalizationEstimate:
        p = self.params
        counts = (dict(self.ekf.accepted), dict(self.ekf.rejected))
        if not self.ekf.initialized or self._last_accept_s is None:
            return LocalizationEstimate(
                LocalizationStatus.LOST, self.init_reason or "no pose", 0, None, None, None,
                None, None, {}, *counts,
            )  # fmt: skip
        state, cov = self.ekf.state, self.ekf.covariance
        (pxx, pxy, _), (_, pyy, _), (_, _, pyaw) = cov.tolist()
        # The larger eigenvalue of the position's 2x2 covariance, in closed form.
        largest = 0.5 * (pxx + pyy) + math.hypot(0.5 * (pxx - pyy), pxy)
        sigma_m = math.sqrt(max(largest, 0.0))
        sigma_yaw = math.sqrt(max(pyaw, 0.0))
        silent_s = now_s - self._last_accept_s
        if silent_s > p.lost_after_s:
            status, reason = LocalizationStatus.LOST, f"no landmark accepted for {silent_s:.2f} s"
        elif sigma_m > p.lost_sigma_m:
            status, reason = LocalizationStatus.LOST, f"position sigma {sigma_m * 100:.1f} cm"
        elif sigma_m > p.degraded_sigma_m or sigma_yaw > p.degraded_heading_sigma_rad:
            status = LocalizationStatus.DEGRADED
            reason = f"sigma {sigma_m * 1000:.0f} mm, {math.degrees(sigma_yaw):.2f} deg"
        elif disagreeing := self._disagreeing_landmarks():
            status = LocalizationStatus.DEGRADED
            reason = "; ".join(disagreeing)
        elif silent := self._silent_scanners(now_s):
            status, reason = LocalizationStatus.DEGRADED, f"scanner {', '.join(silent)} silent"
        elif self._last_cylinder_s is None or (
            now_s - self._last_cylinder_s > p.cylinder_degraded_after_s
        ):
            status, reason = LocalizationStatus.DEGRADED, "no cylinder in view"
        else:
            status, reason = LocalizationStatus.OK, ""
        quality = 0
        if status is not LocalizationStatus.LOST:
            quality = round(100.0 * max(0.0, min(1.0, 1.0 - sigma_m / p.lost_sigma_m)))
        # The vehicle's centre: O_f ⊕ (−origin), its covariance through the compounding's
        # Jacobian (``compound``, ``compound_jacobians``), written out in floats.
        x, y, yaw = self.ekf.state_floats
        bx, by = -self.origin_in_vehicle.x_m, -self.origin_in_vehicle.y_m
        c, s = math.cos(yaw), math.sin(yaw)
        centre = (x + c * bx - s * by, y + s * bx + c * by, wrap_angle_rad(yaw + 0.0))
        lever = ((1.0, 0.0, -s * bx - c * by), (0.0, 1.0, c * bx - s * by), (0.0, 0.0, 1.0))
        centre_cov = np.array(sandwich(lever, cov.tolist()))
        return LocalizationEstimate(
            status,
            reason,
            quality,
            self.ekf.t_s,
            Pose2D(*map(float, state)),
            cov,
            Pose2D(*centre),
            centre_cov,
            dict(self.ekf.last_nis),
            *counts,
        )
