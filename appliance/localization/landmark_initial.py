"""The first pose among surveyed landmarks, with no prior: detected cylinders matched to
the map by their pairwise distances.

A storage area's reflector posts are all alike (one radius), so a single post says
nothing about where the vehicle is; two say it up to the map's pairs of the same
distance apart; every other post that then falls on a landmark is evidence. So: every
pair of detections against every pair of landmarks as far apart (within a tolerance for
the scanners' systematic error), each such correspondence a pose by the two-point closed
form (both orders), each pose scored by how many detections land on distinct landmarks,
refined by a weighted least-squares fit on its supporters and scored again.

Refusal is the safe default, with a reason a person can act on: fewer than
``min_support`` detections agreeing on one pose (a person's legs, a pallet's corner or a
stray pipe of the posts' size that passes the cylinder test makes at most a pair with a
real post, never the third witness), or two poses far apart that the same number of
detections support (a map symmetric from where the vehicle stands). The map's pairwise
distance table is built once and searched by bisection.
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.launcher_map import CylinderLandmark
from appliance.perception.types import CircleFeature
from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class LandmarkMap:
    """Surveyed cylinders of one radius in the site frame, with their pairwise distances.

    One radius because the feature extraction tests every arc against one known radius
    (``CircleParams.radius_m``): a map that mixed sizes would have landmarks the
    extraction refuses as clutter, which is how the site's 0.2 m steel column is kept out.
    """

    landmarks: tuple[CylinderLandmark, ...]
    radius_tolerance_m: float = 1e-6
    # (distance, index a, index b) with a < b, sorted by distance: the initial match's table.
    pairs: tuple[tuple[float, int, int], ...] = field(init=False, repr=False, compare=False)
    _distances: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        landmarks = tuple(self.landmarks)
        object.__setattr__(self, "landmarks", landmarks)
        if not landmarks:
            raise ValueError("a landmark map needs at least one landmark")
        names = [lm.name for lm in landmarks]
        if len(set(names)) != len(names):
            raise ValueError(f"landmark names must be unique: {sorted(names)}")
        radius = landmarks[0].radius_m
        if not radius > 0.0:
            raise ValueError(f"the landmarks' radius must be > 0, got {radius}")
        odd = [lm.name for lm in landmarks if abs(lm.radius_m - radius) > self.radius_tolerance_m]
        if odd:
            raise ValueError(
                f"all landmarks must have one radius ({radius} m, {landmarks[0].name}); "
                f"not so: {', '.join(odd)}"
            )
        pairs = []
        for a in range(len(landmarks)):
            for b in range(a + 1, len(landmarks)):
                la, lb = landmarks[a], landmarks[b]
                distance = math.hypot(lb.x_m - la.x_m, lb.y_m - la.y_m)
                if distance < 2.0 * radius:
                    raise ValueError(f"landmarks {la.name} and {lb.name} overlap")
                pairs.append((distance, a, b))
        pairs.sort()
        object.__setattr__(self, "pairs", tuple(pairs))
        object.__setattr__(self, "_distances", tuple(d for d, _, _ in pairs))

    @property
    def radius_m(self) -> float:
        return self.landmarks[0].radius_m

    @property
    def xy(self) -> tuple[tuple[float, float], ...]:
        return tuple((lm.x_m, lm.y_m) for lm in self.landmarks)

    def pairs_near(self, distance_m: float, tolerance_m: float) -> Sequence[tuple[int, int]]:
        """The landmark pairs (a < b) whose distance is within ``tolerance_m`` of ``distance_m``."""
        low = bisect.bisect_left(self._distances, distance_m - tolerance_m)
        high = bisect.bisect_right(self._distances, distance_m + tolerance_m)
        return [(a, b) for _, a, b in self.pairs[low:high]]


@dataclass(frozen=True)
class Detection:
    """A cylinder's centre as seen, in the vehicle frame, with its 2x2 covariance (the
    fit's and the scanner's systematic error, which is what lets far posts disagree with
    the map by centimetres)."""

    x_m: float
    y_m: float
    covariance: FloatArray
    sensor: str = ""


@dataclass(frozen=True)
class MatchParams:
    """``pair_tolerance_*``: a detected pair's distance may differ from the map's by the
    scanners' systematic errors: ±30 mm in range each, and a mount's tenths of a degree
    that move a post 15 m out by 8 cm (0.5 %). ``min_pair_distance_m``: a shorter base
    fixes the heading too poorly to score the rest. ``support_radius_m``: a detection
    counts for a hypothesis when it falls this near a landmark (the same errors, and the
    two-point pose's heading error carried to the far posts), less than half the closest
    two landmarks. ``merge_distance_m``: both scanners see the posts ahead; two
    detections this close are one post. ``distinct_*``: two hypotheses nearer than this
    are the same pose. ``sigma_floor_*``: what the least-squares covariance misses, the
    systematic errors being common to all of one scanner's detections."""

    pair_tolerance_m: float = 0.12
    pair_tolerance_fraction: float = 0.005
    min_pair_distance_m: float = 1.0
    support_radius_m: float = 0.3
    min_support: int = 3
    merge_distance_m: float = 0.3
    distinct_position_m: float = 0.5
    distinct_heading_rad: float = math.radians(5.0)
    max_detections: int = 40
    sigma_floor_m: float = 0.02
    sigma_floor_heading_rad: float = math.radians(0.3)

    def __post_init__(self) -> None:
        if self.min_support < 3:
            raise ValueError(
                f"min_support must be >= 3 (two points fit any pair), not {self.min_support}"
            )
        if not 0.0 < self.merge_distance_m <= self.support_radius_m:
            raise ValueError("merge_distance_m must be in (0, support_radius_m]")


@dataclass(frozen=True)
class LandmarkMatch:
    """The vehicle's pose in the site frame, its covariance, and which detection (index
    in the merged detections) fell on which landmark."""

    pose: Pose2D
    covariance: FloatArray
    pairs: tuple[tuple[int, str], ...]
    rms_m: float

    @property
    def support(self) -> int:
        return len(self.pairs)


@dataclass(frozen=True)
class MatchRefusal:
    reason: str


def circle_detection(
    circle: CircleFeature, sensor_name: str, sensor: Pose2D, systematic: tuple[float, float]
) -> Detection:
    """A circle (vehicle frame) as a `Detection`, the scanner's systematic range variance
    along its beam and its yaw variance across it added to the fit's covariance."""
    dx, dy = circle.cx_m - sensor.x_m, circle.cy_m - sensor.y_m
    r = math.hypot(dx, dy)
    u = np.array([dx / r, dy / r])
    w = np.array([-u[1], u[0]])
    covariance = (
        np.asarray(circle.covariance)
        + systematic[0] * np.outer(u, u)
        + r * r * systematic[1] * np.outer(w, w)
    )
    return Detection(circle.cx_m, circle.cy_m, covariance, sensor_name)


def carried(detection: Detection, moved: Pose2D) -> Detection:
    """A detection in the vehicle frame of an earlier scan, in the frame of a later one,
    the vehicle having ``moved`` (the later frame's pose in the earlier one) in between:
    at a walking pace the two scanners' scans, half a period apart, are 2 cm apart."""
    c, s = math.cos(moved.yaw_rad), math.sin(moved.yaw_rad)
    dx, dy = detection.x_m - moved.x_m, detection.y_m - moved.y_m
    back = np.array([[c, s], [-s, c]])
    covariance = back @ detection.covariance @ back.T
    return Detection(c * dx + s * dy, -s * dx + c * dy, covariance, detection.sensor)


def merge_detections(detections: Sequence[Detection], merge_distance_m: float) -> list[Detection]:
    """One detection per post: those closer than ``merge_distance_m`` (both scanners on
    one post) fused by their information, in the order first seen."""
    merged: list[Detection] = []
    for detection in detections:
        for index, kept in enumerate(merged):
            if math.hypot(detection.x_m - kept.x_m, detection.y_m - kept.y_m) < merge_distance_m:
                merged[index] = _fused(kept, detection)
                break
        else:
            merged.append(detection)
    return merged


def _fused(a: Detection, b: Detection) -> Detection:
    info_a, info_b = np.linalg.inv(a.covariance), np.linalg.inv(b.covariance)
    covariance = np.linalg.inv(info_a + info_b)
    xy = covariance @ (info_a @ (a.x_m, a.y_m) + info_b @ (b.x_m, b.y_m))
    sensor = a.sensor if a.sensor == b.sensor else f"{a.sensor}+{b.sensor}"
    return Detection(float(xy[0]), float(xy[1]), 0.5 * (covariance + covariance.T), sensor)


def two_point_pose(
    seen: tuple[tuple[float, float], tuple[float, float]],
    mapped: tuple[tuple[float, float], tuple[float, float]],
) -> Pose2D:
    """The pose that puts the two points ``seen`` (vehicle frame) on ``mapped`` (site
    frame), the heading from the two directions and the position from the midpoints
    (each of the pair's errors counts once, not the first point's twice)."""
    (p0, p1), (q0, q1) = seen, mapped
    yaw = math.atan2(q1[1] - q0[1], q1[0] - q0[0]) - math.atan2(p1[1] - p0[1], p1[0] - p0[0])
    c, s = math.cos(yaw), math.sin(yaw)
    px, py = 0.5 * (p0[0] + p1[0]), 0.5 * (p0[1] + p1[1])
    qx, qy = 0.5 * (q0[0] + q1[0]), 0.5 * (q0[1] + q1[1])
    return Pose2D(qx - (c * px - s * py), qy - (s * px + c * py), wrap_angle_rad(yaw))


def _supporters(
    pose: Pose2D, seen: FloatArray, mapped: FloatArray, radius_m: float
) -> list[tuple[int, int, float]]:
    """(detection, landmark, distance) of the detections that ``pose`` puts within
    ``radius_m`` of a landmark, each detection and each landmark used once, nearest first."""
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    wx = pose.x_m + c * seen[:, 0] - s * seen[:, 1]
    wy = pose.y_m + s * seen[:, 0] + c * seen[:, 1]
    distance = np.hypot(wx[:, None] - mapped[None, :, 0], wy[:, None] - mapped[None, :, 1])
    near = np.argwhere(distance <= radius_m)
    candidates = sorted((float(distance[k, m]), int(k), int(m)) for k, m in near)
    used_k: set[int] = set()
    used_m: set[int] = set()
    found = []
    for d, k, m in candidates:
        if k not in used_k and m not in used_m:
            used_k.add(k)
            used_m.add(m)
            found.append((k, m, d))
    return found


def fit_pose(
    detections: Sequence[Detection], mapped_xy: Sequence[tuple[float, float]]
) -> tuple[Pose2D, FloatArray, float]:
    """The pose that best puts each detection on its landmark: the weighted closed-form
    rigid fit (Procrustes, weights by each detection's variance), its Gauss–Newton
    covariance (each residual's covariance rotated into the site frame) and rms residual."""
    seen = np.array([(d.x_m, d.y_m) for d in detections])
    mapped = np.asarray(mapped_xy, dtype=float)
    weights = np.array([2.0 / float(np.trace(d.covariance)) for d in detections])
    total = float(weights.sum())
    seen_mean = weights @ seen / total
    mapped_mean = weights @ mapped / total
    a, b = seen - seen_mean, mapped - mapped_mean
    h = (a * weights[:, None]).T @ b
    yaw = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s], [s, c]])
    xy = mapped_mean - rot @ seen_mean
    residuals = seen @ rot.T + xy - mapped
    rms = math.sqrt(float(np.mean(np.sum(residuals * residuals, axis=1))))
    information = np.zeros((3, 3))
    for detection, (px, py) in zip(detections, seen, strict=True):
        jac = np.array([[1.0, 0.0, -s * px - c * py], [0.0, 1.0, c * px - s * py]])
        in_site = rot @ detection.covariance @ rot.T
        information += jac.T @ np.linalg.solve(in_site, jac)
    covariance = np.linalg.inv(information)
    pose = Pose2D(float(xy[0]), float(xy[1]), wrap_angle_rad(yaw))
    return pose, 0.5 * (covariance + covariance.T), rms


@dataclass
class _Hypothesis:
    pose: Pose2D
    covariance: FloatArray
    pairs: tuple[tuple[int, int], ...]
    rms_m: float


def _hypotheses(
    detections: Sequence[Detection], landmark_map: LandmarkMap, params: MatchParams
) -> list[_Hypothesis]:
    """Every pair correspondence's pose, refined on its supporters; one per supporter set."""
    seen = np.array([(d.x_m, d.y_m) for d in detections])
    mapped = np.array(landmark_map.xy)
    found: dict[frozenset[tuple[int, int]], _Hypothesis] = {}
    n = len(detections)
    for i in range(n):
        for j in range(i + 1, n):
            p_i, p_j = (
                (float(seen[i, 0]), float(seen[i, 1])),
                (float(seen[j, 0]), float(seen[j, 1])),
            )
            distance = math.dist(p_i, p_j)
            if distance < params.min_pair_distance_m:
                continue
            tolerance = params.pair_tolerance_m + params.pair_tolerance_fraction * distance
            for a, b in landmark_map.pairs_near(distance, tolerance):
                q_a = (float(mapped[a, 0]), float(mapped[a, 1]))
                q_b = (float(mapped[b, 0]), float(mapped[b, 1]))
                for q0, q1 in ((q_a, q_b), (q_b, q_a)):
                    guess = two_point_pose((p_i, p_j), (q0, q1))
                    support = _supporters(guess, seen, mapped, params.support_radius_m)
                    if len(support) < 2:
                        continue
                    key = frozenset((k, m) for k, m, _ in support)
                    if key in found:
                        continue
                    found[key] = _refined(support, detections, seen, mapped, params)
    return list(found.values())


def _refined(
    support: list[tuple[int, int, float]],
    detections: Sequence[Detection],
    seen: FloatArray,
    mapped: FloatArray,
    params: MatchParams,
) -> _Hypothesis:
    """The hypothesis fitted on its supporters, then scored again from the fitted pose
    (a far post the two-point heading missed may now fall on its landmark); kept only
    if the new set is at least as large."""
    pairs = sorted((k, m) for k, m, _ in support)
    for _ in range(2):
        pose, covariance, rms = fit_pose(
            [detections[k] for k, _ in pairs], [tuple(mapped[m]) for _, m in pairs]
        )
        again = sorted(
            (k, m) for k, m, _ in _supporters(pose, seen, mapped, params.support_radius_m)
        )
        if len(again) <= len(pairs) or again == pairs:
            break
        pairs = again
    return _Hypothesis(pose, covariance, tuple(pairs), rms)


def _distinct(a: Pose2D, b: Pose2D, params: MatchParams) -> bool:
    return (
        math.hypot(a.x_m - b.x_m, a.y_m - b.y_m) > params.distinct_position_m
        or abs(wrap_angle_rad(a.yaw_rad - b.yaw_rad)) > params.distinct_heading_rad
    )


def match_landmarks(
    detections: Sequence[Detection],
    landmark_map: LandmarkMap,
    params: MatchParams | None = None,
) -> LandmarkMatch | MatchRefusal:
    """The vehicle's pose from cylinders seen in the vehicle frame, or why not.

    ``detections`` should be merged (`merge_detections`) when several scanners saw them:
    a post seen twice would otherwise count as two witnesses.
    """
    params = params or MatchParams()
    n = len(detections)
    if n < params.min_support:
        return MatchRefusal(f"{n} cylinder(s) seen, {params.min_support} needed")
    if n > params.max_detections:
        return MatchRefusal(f"{n} cylinders seen: more than {params.max_detections}, clutter")
    hypotheses = _hypotheses(detections, landmark_map, params)
    if not hypotheses:
        return MatchRefusal(f"{n} cylinders seen, no two as far apart as two landmarks")
    best_support = max(len(h.pairs) for h in hypotheses)
    if best_support < params.min_support:
        return MatchRefusal(
            f"{n} cylinders seen, at most {best_support} fit the map together, "
            f"{params.min_support} needed"
        )
    top = sorted((h for h in hypotheses if len(h.pairs) == best_support), key=lambda h: h.rms_m)
    best = top[0]
    rivals = [h for h in top[1:] if _distinct(h.pose, best.pose, params)]
    if rivals:
        return MatchRefusal(
            f"ambiguous: {len(rivals) + 1} poses {_distance_apart(best, rivals)} apart "
            f"fit {best_support} cylinders each"
        )
    floor = np.diag(
        [params.sigma_floor_m**2, params.sigma_floor_m**2, params.sigma_floor_heading_rad**2]
    )
    names = tuple((k, landmark_map.landmarks[m].name) for k, m in best.pairs)
    return LandmarkMatch(best.pose, best.covariance + floor, names, best.rms_m)


def _distance_apart(best: _Hypothesis, rivals: Sequence[_Hypothesis]) -> str:
    far = max(math.hypot(h.pose.x_m - best.pose.x_m, h.pose.y_m - best.pose.y_m) for h in rivals)
    return f"up to {far:.1f} m"
