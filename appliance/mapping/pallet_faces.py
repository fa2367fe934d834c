"""The visible faces of one cluster: one straight face, or two at right angles (an L),
fitted jointly as the sides of one rectangle.

**Which.** The points, in azimuth order around the viewpoint, are one face when one
weighted line (`line_fit.fit_line`: the range noise lies along each ray) passes the χ²
test. Otherwise the corner is the split that leaves the two pieces' isotropic lines the
least scatter (every split at once, from running moment sums); each piece must pass its
own χ² test (else: not straight), and the two lines must be at right angles within a
tolerance widened by 3σ of their angles (else: not a rectangle's corner). A face may
carry a few strays, farther than 4σ from its line (a cloud's fork opening whose bin
caught no point of the deck's edge, and so the underside behind it): up to a tenth of
a face's points are dropped as such, and the face tested again without them.

**Joint fit.** A pallet is a rectangle, so the L is refitted as two *perpendicular*
lines sharing one orientation θ: face 1 ``n·p = a``, face 2 ``t·p = b`` with
``n = (cos θ, sin θ)``, ``t = (−sin θ, cos θ)``. For fixed weights the cost
``nᵀS₁n + tᵀS₂t`` (S the pieces' weighted scatters about their weighted means) is
``nᵀ(S₁ + R₉₀ᵀS₂R₉₀)n``, so θ is that matrix's minor axis, in closed form. The weights
depend on θ (``σ_r² (normal·ray)² + σ_surface²``), so the fit is iterated to its fixed
point, as the line fit is. The covariance of (θ, a, b) is the inverse of ``Σ w g gᵀ``
with ``g = (t·p, −1, 0)`` on face 1 and ``(−n·p, 0, −1)`` on face 2: the line fit's
first-order derivation, with the right angle built in. One face is the same fit with
no face 2, over (θ, a).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from appliance.mapping.pallets import FloatArray, posture_difference_rad
from appliance.perception.gates import chi_square_quantile
from appliance.perception.line_fit import LineFit, fit_line, moment_columns
from appliance.perception.types import ScannerModel

BoolArray = npt.NDArray[np.bool_]


class PalletRejectReason(StrEnum):
    """Why a cluster gave no pallet."""

    BAD_INPUT = "bad_input"  # not (M, 2) numbers, a viewpoint or sigma unusable, no kinds
    NON_FINITE = "non_finite"  # nan/inf in the points, or the arithmetic overflowed
    TOO_FEW_POINTS = "too_few_points"
    TOO_SHORT = "too_short"  # a leg, a post: smaller than any pallet's side
    DEGENERATE = "degenerate"  # coincident points, a point at the viewpoint
    NOT_STRAIGHT = "not_straight"  # neither one straight face nor two
    NOT_RIGHT_ANGLE = "not_right_angle"
    NOT_CONVEX = "not_convex"  # an inside corner, or a face seen edge-on
    NO_KIND = "no_kind"  # the faces' lengths match no candidate kind
    AMBIGUOUS = "ambiguous"  # several kinds or placements fit equally
    OCCLUDED = "occluded"  # one face with both ends hidden: its position along is unknown


@dataclass(frozen=True)
class PalletRejection:
    """A cluster that is not (or not surely) a pallet, and why; returned, never raised."""

    reason: PalletRejectReason
    detail: str = ""


@dataclass(frozen=True)
class FaceTests:
    """How straight a face and how square a corner must be (see `PalletFitParams`)."""

    min_leg_points: int = 3
    straight_gate_z: float = 3.09
    right_angle_tolerance_rad: float = math.radians(5.0)
    max_iterations: int = 20
    outlier_gate_z: float = 4.0
    max_outlier_fraction: float = 0.1


class Faces(NamedTuple):
    """The joint fit: orientation, offsets, their covariance, and each face's points
    (in azimuth order: face 1 holds the cluster's first point, face 2 its last)."""

    theta: float
    a: float  # face 1: n·p = a
    b: float  # face 2: t·p = b (nan with one face)
    covariance: FloatArray  # over (θ, a), or (θ, a, b) for an L
    face1: FloatArray
    face2: FloatArray  # (0, 2) with one face

    @property
    def is_corner(self) -> bool:
        return bool(self.face2.shape[0] > 0)


def face_axes(theta: float) -> tuple[FloatArray, FloatArray]:
    """``n`` (face 1's normal) and ``t`` (face 1's direction, face 2's normal)."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([c, s]), np.array([-s, c])


def find_faces(
    q: FloatArray, rays: FloatArray, view: FloatArray, scanner: ScannerModel, tests: FaceTests
) -> Faces | PalletRejection:
    """One face or an L in points ``q`` (azimuth order) seen from ``view`` along unit
    ``rays``. An L must be convex towards the viewpoint (`seen_from_outside`).

    numpy's floating-point warnings are the caller's to silence; a singular information
    matrix raises `numpy.linalg.LinAlgError`, the caller's to turn into a rejection.
    """
    one = fit_line(q, rays, scanner, tests.max_iterations)
    if not isinstance(one, LineFit):
        return PalletRejection(PalletRejectReason.DEGENERATE, one.detail)
    if _straight(one, tests):
        return fit_faces(q, rays, q.shape[0], one.alpha_rad, scanner, tests.max_iterations)
    corner = _corner(q, rays, scanner, tests)
    if isinstance(corner, Faces) and not seen_from_outside(corner, view, 3.0 * scanner.sigma_m):
        corner = PalletRejection(PalletRejectReason.NOT_CONVEX, "inside corner, or edge-on")
    if isinstance(corner, Faces):
        return corner
    # Not an L either: one face with a few strays (a glimpse through a fork opening, the
    # first point of a face seen edge-on)?
    keep = _inliers(q, rays, one, scanner, tests)
    if keep is not None:
        trimmed = fit_line(q[keep], rays[keep], scanner, tests.max_iterations)
        if isinstance(trimmed, LineFit) and _straight(trimmed, tests):
            count = int(np.count_nonzero(keep))
            return fit_faces(
                q[keep], rays[keep], count, trimmed.alpha_rad, scanner, tests.max_iterations
            )
    return corner


def _corner(
    q: FloatArray, rays: FloatArray, scanner: ScannerModel, tests: FaceTests
) -> Faces | PalletRejection:
    corner = best_corner(q, tests.min_leg_points)
    if corner is None:
        return PalletRejection(PalletRejectReason.NOT_STRAIGHT, "too few points for an L")
    legs = _legs(q, rays, corner, scanner, tests)
    if legs is not None:  # the corner where the legs' own noise model puts it
        settled = settle_corner(q, rays, legs, scanner, tests.min_leg_points)
        legs = legs if settled == corner else _legs(q, rays, settled, scanner, tests)
        corner = settled
    if legs is not None and not (_straight(legs[0], tests) and _straight(legs[1], tests)):
        keeps = [
            np.ones(part.shape[0], dtype=np.bool_)
            if _straight(leg, tests)
            else _inliers(part, part_rays, leg, scanner, tests)
            for part, part_rays, leg in (
                (q[:corner], rays[:corner], legs[0]),
                (q[corner:], rays[corner:], legs[1]),
            )
        ]
        if keeps[0] is None or keeps[1] is None:
            return PalletRejection(PalletRejectReason.NOT_STRAIGHT, "neither one face nor two")
        keep = np.concatenate((keeps[0], keeps[1]))
        q, rays, corner = q[keep], rays[keep], int(np.count_nonzero(keeps[0]))
        legs = _legs(q, rays, corner, scanner, tests)
    if legs is None:
        return PalletRejection(PalletRejectReason.DEGENERATE, "a leg has no direction")
    first, second = legs
    if not (_straight(first, tests) and _straight(second, tests)):
        return PalletRejection(PalletRejectReason.NOT_STRAIGHT, "neither one face nor two")
    bend = posture_difference_rad(first.alpha_rad - second.alpha_rad, math.pi / 2.0, math.pi)
    spread = 3.0 * math.sqrt(float(first.covariance[1, 1] + second.covariance[1, 1]))
    if not abs(bend) <= max(tests.right_angle_tolerance_rad, spread):
        return PalletRejection(
            PalletRejectReason.NOT_RIGHT_ANGLE, f"{math.degrees(abs(bend)):.1f} deg off"
        )
    return fit_faces(q, rays, corner, first.alpha_rad, scanner, tests.max_iterations)


def seen_from_outside(faces: Faces, view: FloatArray, margin_m: float) -> bool:
    """Whether an L is a convex corner seen from outside: each face runs from the corner
    away from the viewpoint's side of the other face's line, and the viewpoint is more
    than ``margin_m`` off both lines (an inside corner is a wall's or a shelf's; a face
    whose line passes through the viewpoint is seen edge-on, and its side is noise)."""
    normal, along = face_axes(faces.theta)
    run1 = float(np.mean(faces.face1 @ along)) - faces.b  # face 1 from the corner along t
    run2 = float(np.mean(faces.face2 @ normal)) - faces.a  # face 2 from the corner along n
    behind1 = faces.a - float(view @ normal)  # > 0: the viewpoint is at n·p < a
    behind2 = faces.b - float(view @ along)
    return (
        abs(behind1) > margin_m
        and abs(behind2) > margin_m
        and behind1 * run2 > 0.0
        and behind2 * run1 > 0.0
    )


def _inliers(
    q: FloatArray, rays: FloatArray, fit: LineFit, scanner: ScannerModel, tests: FaceTests
) -> BoolArray | None:
    """The points of a face that is straight but for a few strays: those within
    ``outlier_gate_z`` of their σ of the line, when the others are at most
    ``max_outlier_fraction`` of them (None: no strays, or too many to call strays)."""
    normal = np.array([math.cos(fit.alpha_rad), math.sin(fit.alpha_rad)])
    residual = q @ normal - fit.r_m
    z = np.abs(residual) / np.sqrt(scanner.normal_variance(rays @ normal))
    keep: BoolArray = z <= tests.outlier_gate_z
    strays = q.shape[0] - int(np.count_nonzero(keep))
    if strays == 0 or strays > tests.max_outlier_fraction * q.shape[0]:
        return None
    return keep if int(np.count_nonzero(keep)) >= tests.min_leg_points else None


def _legs(
    q: FloatArray, rays: FloatArray, corner: int, scanner: ScannerModel, tests: FaceTests
) -> tuple[LineFit, LineFit] | None:
    first = fit_line(q[:corner], rays[:corner], scanner, tests.max_iterations)
    second = fit_line(q[corner:], rays[corner:], scanner, tests.max_iterations)
    if isinstance(first, LineFit) and isinstance(second, LineFit):
        return first, second
    return None


def settle_corner(
    q: FloatArray,
    rays: FloatArray,
    legs: tuple[LineFit, LineFit],
    scanner: ScannerModel,
    min_leg: int,
) -> int:
    """The boundary that minimises the legs' summed *weighted* squared residuals.

    The split that found the corner weighs every point alike, but a face seen obliquely
    is sharp along its normal (the range noise is nearly along the face): a point of the
    other face given to it by the isotropic split is many of its σ off, and fails the
    χ² test that a correctly split L passes.
    """
    n = q.shape[0]
    costs = np.empty((2, n))
    for row, line in zip(costs, legs, strict=True):
        normal = np.array([math.cos(line.alpha_rad), math.sin(line.alpha_rad)])
        residual = q @ normal - line.r_m
        np.multiply(residual, residual, out=row)
        row /= scanner.normal_variance(rays @ normal)
    head = np.cumsum(costs[0])  # head[k - 1]: points [0, k) on leg 1
    tail = np.cumsum(costs[1, ::-1])[::-1]  # tail[k]: points [k, n) on leg 2
    splits = np.arange(min_leg, n - min_leg + 1)
    return int(splits[int(np.argmin(head[splits - 1] + tail[splits]))])


def _straight(fit: LineFit, tests: FaceTests) -> bool:
    return fit.chi_square <= chi_square_quantile(fit.n_points - 2, tests.straight_gate_z)


def best_corner(q: FloatArray, min_leg: int) -> int | None:
    """The split ``[0, k) | [k, n)`` whose two isotropic lines leave the least scatter,
    or None when the points are too few for two legs."""
    n = q.shape[0]
    if n < 2 * min_leg:
        return None
    running = np.cumsum(moment_columns(q), axis=0)
    splits = np.arange(min_leg, n - min_leg + 1)
    before = running[splits - 1]
    cost = _least_scatter(before) + _least_scatter(running[-1] - before)
    return int(splits[int(np.argmin(cost))])


def _least_scatter(sums: FloatArray) -> FloatArray:
    """Each row's scatter matrix's smallest eigenvalue, from (1, x, y, xx, yy, xy) sums."""
    count, sx, sy = sums[:, 0], sums[:, 1], sums[:, 2]
    cxx = sums[:, 3] - sx * sx / count
    cyy = sums[:, 4] - sy * sy / count
    cxy = sums[:, 5] - sx * sy / count
    least: FloatArray = 0.5 * (cxx + cyy) - np.hypot(0.5 * (cxx - cyy), cxy)
    return least


def fit_faces(
    q: FloatArray,
    rays: FloatArray,
    corner: int,
    theta: float,
    scanner: ScannerModel,
    iterations: int,
) -> Faces:
    """The joint fit of face 1 ``q[:corner]`` and face 2 ``q[corner:]`` (none when
    ``corner`` is n), from face 1's normal ``theta``."""
    face1, face2 = q[:corner], q[corner:]
    rays1, rays2 = rays[:corner], rays[corner:]
    weights1, weights2 = np.ones(face1.shape[0]), np.ones(face2.shape[0])
    for _ in range(max(iterations, 1)):
        normal, along = face_axes(theta)
        weights1 = 1.0 / scanner.normal_variance(rays1 @ normal)
        weights2 = 1.0 / scanner.normal_variance(rays2 @ along)
        s1, s2 = _scatter(face1, weights1), _scatter(face2, weights2)
        m_xx, m_yy, m_xy = s1[0] + s2[1], s1[1] + s2[0], s1[2] - s2[2]
        new = 0.5 * math.atan2(-2.0 * m_xy, m_yy - m_xx)
        new += math.pi * round((theta - new) / math.pi)  # the same normal, not its opposite
        converged = abs(new - theta) <= 1e-12
        theta = new
        if converged:
            break
    normal, along = face_axes(theta)
    a = float(weights1 @ (face1 @ normal)) / float(weights1.sum())
    gradients = np.zeros((q.shape[0], 3))  # rows g over (θ, a, b)
    gradients[:corner, 0] = face1 @ along
    gradients[:corner, 1] = -1.0
    gradients[corner:, 0] = -(face2 @ normal)
    gradients[corner:, 2] = -1.0
    weights = np.concatenate((weights1, weights2))
    b = math.nan
    if face2.shape[0]:
        b = float(weights2 @ (face2 @ along)) / float(weights2.sum())
    else:
        gradients = gradients[:, :2]
    information = (gradients * weights[:, None]).T @ gradients
    covariance = np.asarray(np.linalg.inv(information), dtype=np.float64)
    return Faces(theta, a, b, covariance, face1, face2)


def _scatter(points: FloatArray, weights: FloatArray) -> tuple[float, float, float]:
    """(Sxx, Syy, Sxy) of the points about their weighted mean (zeros for none)."""
    if points.shape[0] == 0:
        return 0.0, 0.0, 0.0
    centred = points - (weights @ points) / weights.sum()
    weighted = centred * weights[:, None]
    return (
        float(weighted[:, 0] @ centred[:, 0]),
        float(weighted[:, 1] @ centred[:, 1]),
        float(weighted[:, 0] @ centred[:, 1]),
    )


def continuation_hidden(
    faces: Faces,
    view: FloatArray,
    beyond: FloatArray | None,
    at_end: bool,
    scanner: ScannerModel,
    margin_m: float,
) -> bool:
    """Whether any of the points ``beyond`` (k, 2) the cluster's first point (``at_end``
    False) or last is in front of the continuation of the face that ends there, or on
    it: the face may then go on behind it, and its length is only a lower bound. A
    negative ``margin_m`` asks for points in front by more than 3σ and ``-margin_m``
    (what stands above the band shadows it only from in front).

    Judged against the fitted line, as the scan lines' ends are (`perception.lines`),
    across it rather than along the ray (a ray that grazes the line meets it anywhere
    along a metre): a point on the viewpoint's side of the line, or within 3σ of its own
    noise (and ``margin_m``) behind it. The other face of a corner recedes behind the
    line, and so does what is seen through a gap: a true end; the face's own
    continuation, cut off where it turns grazing or past a gap, lies on it; a post
    stands in front of it. No point beyond, or rays that never meet the line's
    continuation, is a true end.
    """
    if beyond is None or beyond.shape[0] == 0:
        return False
    normal, along = face_axes(faces.theta)
    offset = faces.a
    if at_end and faces.is_corner:
        normal, offset = along, faces.b
    rays = beyond - view
    distance = np.hypot(rays[:, 0], rays[:, 1])
    if not distance.min() > 0.0:
        return True  # a point at the viewpoint hides everything
    facing = (rays @ normal) / distance
    viewer_side = offset - float(view @ normal)  # > 0: the viewpoint is at n·p < offset
    ahead = (np.abs(facing) >= 1e-12) & (viewer_side * facing > 0.0)  # meets the line
    in_front_m = math.copysign(1.0, viewer_side) * (offset - beyond @ normal)
    noise_m = np.sqrt(scanner.normal_variance(facing))
    allowance = 3.0 * noise_m + abs(margin_m)
    hides = in_front_m > (-allowance if margin_m >= 0.0 else allowance)
    return bool((ahead & hides).any())
