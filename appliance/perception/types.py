"""The features a scan yields, as the estimator reads them.

Conventions, shared by every feature (the EKF is written against these):

- Everything is in the *output frame*: the frame the scan was converted into by its
  ``frame`` pose (the scanner's mount in the vehicle frame gives vehicle-frame features;
  the identity pose gives sensor-frame ones). Metres and radians.
- A line is in Hessian normal form ``x cos α + y sin α = r`` with ``r >= 0`` (the
  distance from the output frame's origin) and ``α`` in ``(-π, π]`` (the direction of
  the normal from that origin towards the line). Its covariance is over ``(r, α)`` in
  that order: ``[[var r, cov], [cov, var α]]`` in m², m·rad, rad². A line through the
  origin (r ≈ 0) has an ill-defined α; the vehicle-frame origin is the rear axle,
  which no board passes through.
- Index ranges point into the scan's beam arrays: a segment is half-open
  ``(start, stop)`` like a Python slice, a feature's ``first_index``/``last_index`` are
  both included (the beams its first and last point came from).
- Covariances hold the statistical range noise only; the scanner's systematic error
  (up to ±30 mm, common to all beams of one scanner) is not in them.

Arrays inside frozen dataclasses are made read-only, and equality is identity
(``eq=False``): comparing arrays element-wise is not what ``==`` on a feature means.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


class RejectReason(StrEnum):
    """Why a cluster of points gave no feature. Values are the keys of the counts."""

    TOO_FEW_POINTS = "too_few_points"
    NON_FINITE = "non_finite"  # the input had nan/inf, or the arithmetic overflowed
    DEGENERATE = "degenerate"  # coincident points: no direction, no circle
    COLLINEAR = "collinear"  # a circle through collinear points has no finite centre
    NOT_CONVERGED = "not_converged"
    TOO_SHORT = "too_short"
    TOO_WIDE = "too_wide"
    TOO_NARROW = "too_narrow"
    RMS_TOO_LARGE = "rms_too_large"
    RADIUS_MISMATCH = "radius_mismatch"
    NOT_FACING = "not_facing"  # the arc is concave towards the scanner: not a cylinder
    NOT_ISOLATED = "not_isolated"  # something next to the arc: a wall corner, a person
    ISOLATED = "isolated"  # a segment of too few points
    DISPERSED = "dispersed"  # a segment whose points are spread too thin


@dataclass(frozen=True)
class FitRejection:
    """A cluster that could not be fitted, and why; returned, never raised."""

    reason: RejectReason
    detail: str = ""


def _frozen_matrix(matrix: FloatArray) -> FloatArray:
    frozen = np.array(matrix, dtype=np.float64, copy=True)
    frozen.flags.writeable = False
    return frozen


@dataclass(frozen=True, eq=False)
class LineFeature:
    """A straight piece of surface: a board, a wall.

    ``start_xy_m``/``end_xy_m`` are the first and last points (in beam order, i.e.
    counter-clockwise as seen from the scanner) projected onto the fitted line: the line
    is clipped to the data, never extrapolated. ``*_occluded`` is True when that end may
    not be where the surface ends: the beam just beyond it saw something in front of
    the line, or the line's continuation, or it is the scan's first or last beam. It is
    False for a true end: the beam beyond has no echo, or one clearly farther than the
    line, or the line meets its neighbour in a corner of one continuous surface.
    """

    r_m: float
    alpha_rad: float
    covariance: FloatArray  # 2x2 over (r_m, alpha_rad)
    start_xy_m: tuple[float, float]
    end_xy_m: tuple[float, float]
    start_occluded: bool
    end_occluded: bool
    n_points: int
    rms_m: float
    first_index: int
    last_index: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "covariance", _frozen_matrix(self.covariance))

    @property
    def length_m(self) -> float:
        return math.hypot(
            self.end_xy_m[0] - self.start_xy_m[0], self.end_xy_m[1] - self.start_xy_m[1]
        )

    @property
    def normal(self) -> tuple[float, float]:
        """Unit normal ``(cos α, sin α)``: from the origin towards the line."""
        return math.cos(self.alpha_rad), math.sin(self.alpha_rad)

    @property
    def direction(self) -> tuple[float, float]:
        """Unit vector along the line from ``start_xy_m`` to ``end_xy_m``."""
        tx, ty = -math.sin(self.alpha_rad), math.cos(self.alpha_rad)
        along = (self.end_xy_m[0] - self.start_xy_m[0]) * tx + (
            self.end_xy_m[1] - self.start_xy_m[1]
        ) * ty
        return (tx, ty) if along >= 0.0 else (-tx, -ty)


@dataclass(frozen=True, eq=False)
class CircleFeature:
    """A cylinder cut by the scan plane; ``covariance`` is the centre's, over (cx, cy).

    ``radius_m`` is the radius the centre was fitted with: the known landmark radius
    (`CircleParams.radius_m`), which the fit checked the arc against.
    ``first_index``/``last_index`` are the beams of the first and last point the fit
    used: the cluster less the edge beams its footprint straddled.
    """

    cx_m: float
    cy_m: float
    radius_m: float
    covariance: FloatArray  # 2x2 over (cx_m, cy_m)
    n_points: int
    rms_m: float
    first_index: int
    last_index: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "covariance", _frozen_matrix(self.covariance))


@dataclass(frozen=True)
class ScanFeatures:
    """Everything one scan yielded.

    ``segments`` are the clusters that survived segmentation (half-open beam index
    ranges, in beam order); ``lines`` and ``circles`` are in beam order too.
    ``rejections`` counts the candidates that gave nothing, keyed
    ``"<stage>.<reason>"`` (``"segment.isolated"``, ``"circle.not_isolated"``,
    ``"line.too_short"``, ...): a landmark that vanishes says why in the counts.
    """

    segments: tuple[tuple[int, int], ...]
    lines: tuple[LineFeature, ...]
    circles: tuple[CircleFeature, ...]
    rejections: Mapping[str, int]


@dataclass(frozen=True)
class ScannerModel:
    """What the fits assume of the scanner's errors (LMS111 data sheet figures).

    ``sigma_m`` is the statistical range error, 12 mm (1σ), along each beam.
    ``floor_sigma_m`` is a small isotropic term (surface texture, angular jitter) so that
    a point whose range error runs exactly along the surface still carries some
    uncertainty and no weight becomes infinite. The beam footprint, 8 mm + 15 mrad ×
    range across, is why the points at the edge of an object are not where the object
    is: a beam that straddles the edge reports the object's range, or a mix, at its own
    central angle.
    """

    sigma_m: float = 0.012
    floor_sigma_m: float = 0.001
    footprint_exit_m: float = 0.008
    footprint_divergence_rad: float = 0.015

    def __post_init__(self) -> None:
        if not (self.sigma_m > 0.0 and math.isfinite(self.sigma_m)):
            raise ValueError(f"sigma_m must be > 0, got {self.sigma_m}")
        for name in ("floor_sigma_m", "footprint_exit_m", "footprint_divergence_rad"):
            value = getattr(self, name)
            if not (value >= 0.0 and math.isfinite(value)):
                raise ValueError(f"{name} must be >= 0, got {value}")

    def normal_variance(self, cos_incidence: FloatArray) -> FloatArray:
        """Variance of each point's offset along a surface normal, given the cosine
        between its beam and that normal: range noise projects by the cosine."""
        variance: FloatArray = np.multiply(self.sigma_m, cos_incidence)
        variance *= variance
        variance += self.floor_sigma_m**2
        # Never exactly 0 (no floor and a beam along the surface): weights stay finite.
        # (With a floor above that minimum, every variance is above it already.)
        lowest = (1e-3 * self.sigma_m) ** 2
        return variance if self.floor_sigma_m**2 >= lowest else np.maximum(variance, lowest)

    def footprint_half_angle_rad(self, range_m: float) -> float:
        """Half the angle the beam's footprint subtends from the scanner at ``range_m``."""
        near_m = max(range_m, 0.05)
        return 0.5 * self.footprint_divergence_rad + 0.5 * self.footprint_exit_m / near_m
