"""A pallet of known footprint fitted to the outline points of one cluster seen from a
known viewpoint: one visible face, or two meeting at a corner (an L).

**Faces** (`pallet_faces`): one straight face, or two at right angles fitted jointly as
a rectangle's sides, with the covariance of their orientation and offsets. Everything
is computed about the cluster's centroid so that no lever arm from a far map origin
enters the numbers.

**Placing the footprint** (`pallet_footprint`): the hidden faces behind the visible
ones, every kind and turn whose sides the faces' lengths allow, refused when they do
not agree on one pallet.

Pure, deterministic, and never raises: every input that is not a pallet (non-finite,
too few points, a post, a wall) comes back as a `PalletRejection` with a reason.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from appliance.mapping.pallet_faces import (
    FaceTests,
    PalletRejection,
    PalletRejectReason,
    continuation_hidden,
    find_faces,
)
from appliance.mapping.pallet_footprint import FootprintTests, place_corner, place_one_face
from appliance.mapping.pallets import FloatArray, Pallet, PalletKind
from appliance.perception.types import ScannerModel

__all__ = ["ALL_KINDS", "PalletFitParams", "PalletRejectReason", "PalletRejection", "fit_pallet"]

ALL_KINDS = (PalletKind.EUR, PalletKind.JIS)


@dataclass(frozen=True)
class PalletFitParams:
    """Acceptance settings.

    ``length_tolerance_m`` 25 mm: a side's length read from its farthest points,
    beyond what the noise explains (3σ of the end points along their faces is added,
    and a sampled face falls short by up to a spacing): chamfers, mixed points, ±3 mm
    of manufacture. With the noise's part it stays under half the 100 mm between a JIS
    side (1100) and a EUR length (1200) for a few mm of noise, so a face with true ends
    tells them apart; with a centimetre it does not, and the fit says ambiguous.
    ``right_angle_tolerance_rad`` 5°: boards are square to the blocks within a degree or
    two; the noise part is added (3σ of the two lines' angles). ``straight_gate_z`` 3.09
    is the 99.9 % χ² gate the scan lines use. ``surface_sigma_m`` 3 mm: a pallet's side
    is blocks, board edges and openings, flat to a few mm, not to the sensor's noise.
    ``end_sigma_m`` 10 mm: a chamfered or splintered board end, a mixed point.
    ``offset_sigma_m`` (0 here: pure noise propagation) is an error shared by all of a
    face's points, which their number does not average away: the proximity points'
    pull towards the viewpoint (`cloud_pallets` sets it), a scanner's range offset.
    ``smear_sigma_m`` (0 here) is how far copies of a face may lie apart in a cloud
    merged from viewpoints that disagree: faces are that much thicker, and longer (it
    widens the length test on the long side only: a smeared face is never shorter).
    A point beyond an end hides it when in front of the face's continuation, on it, or
    behind it by less than 3σ and ``occlusion_margin_m`` 10 mm; a point overhead, when
    in front of it by more than that.
    ``min_extent_m`` 0.25 m: a leg or a post is smaller, the shortest visible side of
    a pallet worth fitting is longer. ``same_pallet_m`` 20 mm / ``same_pallet_rad`` 1°:
    two hypotheses closer than this are one answer. Up to ``max_outlier_fraction`` a
    tenth of a face's points farther than ``outlier_gate_z`` 4σ from it are strays.
    """

    min_points: int = 6
    min_leg_points: int = 3
    min_extent_m: float = 0.25
    length_tolerance_m: float = 0.025
    right_angle_tolerance_rad: float = math.radians(5.0)
    straight_gate_z: float = 3.09
    surface_sigma_m: float = 0.003
    end_sigma_m: float = 0.01
    offset_sigma_m: float = 0.0
    smear_sigma_m: float = 0.0
    occlusion_margin_m: float = 0.01
    same_pallet_m: float = 0.02
    same_pallet_rad: float = math.radians(1.0)
    max_iterations: int = 20
    outlier_gate_z: float = 4.0
    max_outlier_fraction: float = 0.1

    def __post_init__(self) -> None:
        if self.min_points < 4 or self.min_leg_points < 2:
            raise ValueError("min_points must be >= 4 and min_leg_points >= 2")
        for name in (
            "min_extent_m",
            "length_tolerance_m",
            "right_angle_tolerance_rad",
            "same_pallet_rad",
        ):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"{name} must be >= 0")
        for name in (
            "surface_sigma_m",
            "end_sigma_m",
            "offset_sigma_m",
            "smear_sigma_m",
            "same_pallet_m",
            "occlusion_margin_m",
        ):
            if not (getattr(self, name) >= 0.0 and math.isfinite(getattr(self, name))):
                raise ValueError(f"{name} must be finite and >= 0")
        if not (self.outlier_gate_z > 0.0 and 0.0 <= self.max_outlier_fraction < 0.5):
            raise ValueError("outlier_gate_z must be > 0, max_outlier_fraction in [0, 0.5)")
        if not self.straight_gate_z > 0.0 or self.max_iterations < 1:
            raise ValueError("straight_gate_z must be > 0 and max_iterations >= 1")

    @property
    def footprint_tests(self) -> FootprintTests:
        return FootprintTests(
            self.length_tolerance_m,
            self.surface_sigma_m,
            self.smear_sigma_m,
            self.end_sigma_m,
            self.same_pallet_m,
            self.same_pallet_rad,
        )

    @property
    def face_tests(self) -> FaceTests:
        return FaceTests(
            self.min_leg_points,
            self.straight_gate_z,
            self.right_angle_tolerance_rad,
            self.max_iterations,
            self.outlier_gate_z,
            self.max_outlier_fraction,
        )


def fit_pallet(
    xy_m: npt.ArrayLike,
    viewpoint_xy_m: tuple[float, float],
    kinds: Sequence[PalletKind] = ALL_KINDS,
    range_sigma_m: float = 0.01,
    *,
    start_occluded: bool = False,
    end_occluded: bool = False,
    beyond_xy_m: tuple[npt.ArrayLike | None, npt.ArrayLike | None] = (None, None),
    overhead_xy_m: tuple[npt.ArrayLike | None, npt.ArrayLike | None] = (None, None),
    params: PalletFitParams | None = None,
) -> Pallet | PalletRejection:
    """The pallet whose visible faces the points are, or why there is none.

    ``xy_m`` (M, 2) are one cluster's points (any order), ``viewpoint_xy_m`` where they
    were seen from, ``range_sigma_m`` their noise along the ray. ``start_occluded`` /
    ``end_occluded`` say whether the cluster's first / last point in counter-clockwise
    order around the viewpoint may not be where the surface ends (something in front
    of the ray beyond it). ``beyond_xy_m`` are the points just past the first and the
    last, (k, 2) each (the next bins' or beams', None for none): the fit judges from
    them, against the fitted face's continuation, whether an end may be hidden, as a
    caller that cannot fit lines could not. ``overhead_xy_m`` likewise, of what is above
    the points' height band (a 3D cloud's): it hides an end only from in front of the
    face's line (it shadows the band behind it), not on it (the pallet's own deck or
    cargo, flush with its face). The pallet's covariance is over (x, y, yaw);
    its yaw is in ``[-symmetry/2, symmetry/2)``.
    """
    settings = params if params is not None else PalletFitParams()
    checked = _checked(xy_m, viewpoint_xy_m, kinds, range_sigma_m, settings)
    beyond, overhead = _pair(beyond_xy_m), _pair(overhead_xy_m)
    if isinstance(checked, PalletRejection):
        return checked
    if isinstance(beyond, PalletRejection) or isinstance(overhead, PalletRejection):
        return PalletRejection(PalletRejectReason.BAD_INPUT, "points past the ends: (k, 2)")
    xy, viewpoint, kind_list = checked
    with np.errstate(all="ignore"):
        try:
            return _fit(
                xy,
                viewpoint,
                kind_list,
                float(range_sigma_m),
                settings,
                (bool(start_occluded), bool(end_occluded)),
                beyond,
                overhead,
            )
        except np.linalg.LinAlgError:
            return PalletRejection(PalletRejectReason.DEGENERATE, "singular information")
        except ArithmeticError:  # Python floats overflow on points 1e200 m apart
            return PalletRejection(PalletRejectReason.NON_FINITE, "the fit overflowed")


def _checked(
    xy_m: npt.ArrayLike,
    viewpoint_xy_m: tuple[float, float],
    kinds: Sequence[PalletKind],
    range_sigma_m: float,
    params: PalletFitParams,
) -> tuple[FloatArray, FloatArray, tuple[PalletKind, ...]] | PalletRejection:
    try:
        xy = np.array(xy_m, dtype=np.float64)
        viewpoint = np.array(viewpoint_xy_m, dtype=np.float64).reshape(-1)
        sigma = float(range_sigma_m)
        kind_list = tuple(PalletKind(k) for k in kinds)
    except (TypeError, ValueError, OverflowError) as error:
        return PalletRejection(PalletRejectReason.BAD_INPUT, str(error)[:80])
    if xy.ndim != 2 or xy.shape[1] != 2 or viewpoint.shape != (2,) or not kind_list:
        return PalletRejection(PalletRejectReason.BAD_INPUT, f"points of shape {xy.shape}")
    # Up to a kilometre of noise: anything more is not a sensor, and its square overflows.
    if not (np.isfinite(viewpoint).all() and 0.0 < sigma <= 1e3):
        return PalletRejection(PalletRejectReason.BAD_INPUT, "viewpoint or sigma")
    if xy.shape[0] < params.min_points:
        return PalletRejection(PalletRejectReason.TOO_FEW_POINTS, f"{xy.shape[0]} points")
    if not np.isfinite(xy).all():
        return PalletRejection(PalletRejectReason.NON_FINITE, "points not finite")
    return xy, viewpoint, kind_list


def _pair(values: object) -> tuple[FloatArray | None, FloatArray | None] | PalletRejection:
    """Points past each end, as two (k, 2) arrays or None; anything else is bad input."""
    try:
        pair = list(values)  # type: ignore[call-overload]
    except TypeError:
        return PalletRejection(PalletRejectReason.BAD_INPUT)
    if len(pair) != 2:
        return PalletRejection(PalletRejectReason.BAD_INPUT)
    points = [_points(pair[0]), _points(pair[1])]
    if isinstance(points[0], PalletRejection) or isinstance(points[1], PalletRejection):
        return PalletRejection(PalletRejectReason.BAD_INPUT)
    return points[0], points[1]


def _points(value: object) -> FloatArray | PalletRejection | None:
    if value is None:
        return None
    try:
        points = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return PalletRejection(PalletRejectReason.BAD_INPUT)
    if points.size == 0:
        return None
    if points.shape == (2,):  # one point
        points = points[None, :]
    if points.ndim != 2 or points.shape[1] != 2 or not np.isfinite(points).all():
        return PalletRejection(PalletRejectReason.BAD_INPUT)
    return points


def _moved(points: FloatArray | None, origin: FloatArray) -> FloatArray | None:
    return None if points is None else points - origin


def _fit(
    xy: FloatArray,
    viewpoint: FloatArray,
    kinds: tuple[PalletKind, ...],
    sigma: float,
    params: PalletFitParams,
    occluded: tuple[bool, bool],
    beyond: tuple[FloatArray | None, FloatArray | None],
    overhead: tuple[FloatArray | None, FloatArray | None],
) -> Pallet | PalletRejection:
    origin = xy.mean(axis=0)
    q, view = xy - origin, viewpoint - origin
    rays = q - view
    distance = np.hypot(rays[:, 0], rays[:, 1])
    if not (np.isfinite(q).all() and np.isfinite(distance).all() and np.isfinite(view).all()):
        return PalletRejection(PalletRejectReason.NON_FINITE, "overflow")
    if not distance.min() > 0.0 or not math.hypot(*view.tolist()) > 0.0:
        return PalletRejection(PalletRejectReason.DEGENERATE, "a point at the viewpoint")
    towards = -view  # viewpoint to centroid: azimuths measured from it never wrap
    azimuth = np.arctan2(towards[0] * rays[:, 1] - towards[1] * rays[:, 0], rays @ towards)
    order = np.argsort(azimuth, kind="stable")
    q, rays = q[order], rays[order] / distance[order, None]
    extent = float(np.hypot(*(q.max(axis=0) - q.min(axis=0)).tolist()))
    if extent < params.min_extent_m:
        return PalletRejection(PalletRejectReason.TOO_SHORT, f"{extent:.3f} m across")
    surface_m = math.hypot(params.surface_sigma_m, params.smear_sigma_m)
    scanner = ScannerModel(sigma_m=sigma, floor_sigma_m=surface_m)
    faces = find_faces(q, rays, view, scanner, params.face_tests)
    if isinstance(faces, PalletRejection):
        return faces
    # A systematic error common to a face's points (not averaged away by their number).
    offsets = np.full(faces.covariance.shape[0], params.offset_sigma_m**2)
    offsets[0] = 0.0
    faces = faces._replace(covariance=faces.covariance + np.diag(offsets))
    margin = params.occlusion_margin_m
    hidden = [
        flag
        or continuation_hidden(faces, view, _moved(near, origin), at_end, scanner, margin)
        or continuation_hidden(faces, view, _moved(high, origin), at_end, scanner, -margin)
        for flag, near, high, at_end in zip(occluded, beyond, overhead, (False, True), strict=True)
    ]
    occluded = (hidden[0], hidden[1])
    tests = params.footprint_tests
    if faces.is_corner:
        return place_corner(faces, view, origin, kinds, sigma, tests, occluded, q.shape[0])
    return place_one_face(faces, view, origin, kinds, sigma, tests, occluded, q.shape[0])
