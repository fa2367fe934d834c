"""A pallet's footprint placed on its visible faces (`pallet_faces`), for every kind and
turn whose sides the faces allow.

Hidden faces are behind the visible ones, away from the viewpoint. An L's legs (it is
convex towards the viewpoint: `pallet_faces` refuses an inside corner), measured from
the corner to their farthest point, must match the kind's length and width: within a
tolerance when the far end is a true end, at most that long when it is occluded (the
length is then only a lower bound). The corner fixes the pose.

With one face the depth is fixed by the line, the position *along* it only by its
visible ends: by their mean when both are true ends (the face's length must then match
a side), by the one true end and the side's length otherwise; with both ends occluded
it is not fixed at all, and the fit says so. The variance along the face is honest
about what an end point is: the true end lies up to one point spacing ``s`` beyond the
last point (uniform: ``s²/12``; on a regular sampling what one end gains the other
loses, so the mean of two ends keeps it), plus that point's noise along the face and
``end_sigma_m`` for chamfers and mixed points.

Every hypothesis (kind × which face is the length) that fits is placed; if they do not
all agree on one pallet, the fit is refused as ambiguous rather than guessed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from appliance.mapping.pallet_faces import (
    Faces,
    PalletRejection,
    PalletRejectReason,
    face_axes,
)
from appliance.mapping.pallets import FloatArray, Pallet, PalletKind, posture_difference_rad


@dataclass(frozen=True)
class FootprintTests:
    """How well the faces must match a footprint (see `PalletFitParams`)."""

    length_tolerance_m: float = 0.025
    surface_sigma_m: float = 0.003
    smear_sigma_m: float = 0.0
    end_sigma_m: float = 0.01
    same_pallet_m: float = 0.02
    same_pallet_rad: float = math.radians(1.0)


class _Placement(NamedTuple):
    kind: PalletKind
    centre: FloatArray  # (2,) about the cluster's centroid
    yaw: float
    covariance: FloatArray  # 3x3 over (x, y, yaw)
    mismatch_m: float  # how far the true ends are from the sides (0 for bounds)


def _end_spacing(coordinates: FloatArray, at_end: bool) -> float:
    """The mean spacing of the last few points towards one end of a face (a face is
    sampled more sparsely where it is seen more obliquely: the local figure counts)."""
    count = min(4, int(coordinates.shape[0]) - 1)
    if count < 1:
        return 0.0
    tail = coordinates[-count - 1 :] if at_end else coordinates[: count + 1]
    return abs(float(tail[-1] - tail[0])) / count


def _end_noise(ray: FloatArray, along: FloatArray, sigma: float, tests: FootprintTests) -> float:
    """The variance of an end point's measurement along its face: its range noise
    projected on the face, and the isotropic (surface) part."""
    return (sigma * float(ray @ along)) ** 2 + tests.surface_sigma_m**2


def _length_fits(
    measured: float,
    side: float,
    spacing: float,
    end_variance: float,
    occluded: bool,
    tests: FootprintTests,
) -> float | None:
    """How far a face measured between its end points is from ``side`` (0 when only a
    lower bound), or None when it cannot be that side. Its end points fall short of the
    ends by up to a spacing, and their noise along the face (``end_variance``, both
    ends') may carry them either way: 3σ of it widens the tolerance (a JIS side read
    3 cm long from a noisy cloud must not pass for a EUR length); a smeared cloud's
    faces are longer still, never shorter (`FootprintTests.smear_sigma_m`)."""
    noise_m = 3.0 * math.sqrt(end_variance)
    smear_m = 3.0 * math.sqrt(end_variance + 2.0 * tests.smear_sigma_m**2)
    if measured > side + tests.length_tolerance_m + smear_m:
        return None
    if occluded:
        return 0.0
    shortfall = side - (measured + 0.5 * spacing)
    if shortfall > tests.length_tolerance_m + noise_m + 0.5 * spacing:
        return None
    return abs(shortfall)


def _sides(kind: PalletKind) -> list[tuple[float, float, bool]]:
    """(this face's side, the other side, this face is the length) per distinct turn."""
    sides = [(kind.length_m, kind.width_m, True)]
    if kind.length_m != kind.width_m:
        sides.append((kind.width_m, kind.length_m, False))
    return sides


def place_one_face(
    faces: Faces,
    view: FloatArray,
    origin: FloatArray,
    kinds: tuple[PalletKind, ...],
    sigma: float,
    tests: FootprintTests,
    occluded: tuple[bool, bool],
    support: int,
) -> Pallet | PalletRejection:
    """The footprint one face is a side of: its depth from the line, its position along
    the face from the face's true ends."""
    if occluded[0] and occluded[1]:
        return PalletRejection(PalletRejectReason.OCCLUDED, "one face, both ends hidden")
    normal, along = face_axes(faces.theta)
    inward = faces.a - float(view @ normal)
    if abs(inward) < 1e-9:
        return PalletRejection(PalletRejectReason.NOT_CONVEX, "face seen edge-on")
    u = faces.face1 @ along
    # The points are in azimuth order: find which of them is the end at the lower u.
    forward = bool(u[-1] >= u[0])
    low, high = (0, -1) if forward else (-1, 0)
    low_hidden, high_hidden = occluded if forward else occluded[::-1]
    rays = faces.face1 - view
    rays /= np.hypot(rays[:, 0], rays[:, 1])[:, None]
    ordered = u if forward else u[::-1]
    spacing = (_end_spacing(ordered, False), _end_spacing(ordered, True))
    noise = (
        _end_noise(rays[low], along, sigma, tests),
        _end_noise(rays[high], along, sigma, tests),
    )
    low_u, high_u = float(u[low]), float(u[high])
    visible = high_u - low_u
    placements: list[_Placement] = []
    for kind in kinds:
        for side, other, is_length in _sides(kind):
            mismatch = _length_fits(
                visible,
                side,
                spacing[0] + spacing[1],
                noise[0] + noise[1],
                low_hidden or high_hidden,
                tests,
            )
            if mismatch is None:
                continue
            if not (low_hidden or high_hidden):
                # The true ends lie up to a spacing beyond the end points, by amounts
                # that move together on a regular sampling (what one gains at one end
                # the other loses): the mean of the ends keeps the sampling's s²/12.
                centre_u = 0.5 * (low_u + high_u)
                sampling = 0.5 * (spacing[0] + spacing[1])
                rough = 0.5 * tests.end_sigma_m**2  # the ends' own, apart
                rough += 0.5 * tests.smear_sigma_m**2
                variance_u = sampling**2 / 12.0 + 0.25 * (noise[0] + noise[1]) + rough
            elif not low_hidden:
                centre_u = low_u - 0.5 * spacing[0] + 0.5 * side
                rough = tests.end_sigma_m**2 + tests.smear_sigma_m**2
                variance_u = spacing[0] ** 2 / 12.0 + noise[0] + rough
            else:
                centre_u = high_u + 0.5 * spacing[1] - 0.5 * side
                rough = tests.end_sigma_m**2 + tests.smear_sigma_m**2
                variance_u = spacing[1] ** 2 / 12.0 + noise[1] + rough
            half_depth = math.copysign(0.5 * other, inward)
            jacobian = np.zeros((3, 3))  # (x, y, yaw) by (θ, a, u)
            jacobian[:2, 0] = half_depth * along - centre_u * normal
            jacobian[:2, 1] = normal
            jacobian[:2, 2] = along
            jacobian[2, 0] = 1.0
            parameters = np.zeros((3, 3))
            parameters[:2, :2] = faces.covariance
            parameters[2, 2] = variance_u
            placements.append(
                _Placement(
                    kind,
                    (faces.a + half_depth) * normal + centre_u * along,
                    faces.theta + (math.pi / 2.0 if is_length else 0.0),
                    jacobian @ parameters @ jacobian.T,
                    mismatch,
                )
            )
    return _choose(placements, origin, tests, support, f"one face of {visible:.3f} m")


def place_corner(
    faces: Faces,
    view: FloatArray,
    origin: FloatArray,
    kinds: tuple[PalletKind, ...],
    sigma: float,
    tests: FootprintTests,
    occluded: tuple[bool, bool],
    support: int,
) -> Pallet | PalletRejection:
    """The footprint whose corner is the L's and whose sides its legs can be."""
    normal, along = face_axes(faces.theta)
    u1 = faces.face1 @ along - faces.b  # face 1 runs along t from the corner
    v2 = faces.face2 @ normal - faces.a  # face 2 runs along n from the corner
    run1 = math.copysign(1.0, float(u1.mean()))
    run2 = math.copysign(1.0, float(v2.mean()))
    leg1, leg2 = float(np.abs(u1).max()), float(np.abs(v2).max())
    # Face 1's far end is the cluster's first point, face 2's its last.
    spacing1 = _end_spacing(u1, False)
    spacing2 = _end_spacing(v2, True)
    # The far ends' noise along their faces, and the corner's along each face.
    far1, far2 = faces.face1[0] - view, faces.face2[-1] - view
    far1 /= math.hypot(float(far1[0]), float(far1[1]))
    far2 /= math.hypot(float(far2[0]), float(far2[1]))
    noise1 = _end_noise(far1, along, sigma, tests) + float(faces.covariance[2, 2])
    noise2 = _end_noise(far2, normal, sigma, tests) + float(faces.covariance[1, 1])
    corner = faces.a * normal + faces.b * along
    placements: list[_Placement] = []
    for kind in kinds:
        for side1, side2, face1_is_length in _sides(kind):
            fit1 = _length_fits(leg1, side1, spacing1, noise1, occluded[0], tests)
            fit2 = _length_fits(leg2, side2, spacing2, noise2, occluded[1], tests)
            if fit1 is None or fit2 is None:
                continue
            half1, half2 = run1 * 0.5 * side1, run2 * 0.5 * side2
            jacobian = np.zeros((3, 3))  # (x, y, yaw) by (θ, a, b)
            jacobian[:2, 0] = (faces.a + half2) * along - (faces.b + half1) * normal
            jacobian[:2, 1] = normal
            jacobian[:2, 2] = along
            jacobian[2, 0] = 1.0
            placements.append(
                _Placement(
                    kind,
                    corner + half1 * along + half2 * normal,
                    faces.theta + (math.pi / 2.0 if face1_is_length else 0.0),
                    jacobian @ faces.covariance @ jacobian.T,
                    fit1 + fit2,
                )
            )
    return _choose(placements, origin, tests, support, f"legs {leg1:.3f} and {leg2:.3f} m")


def _choose(
    placements: list[_Placement],
    origin: FloatArray,
    tests: FootprintTests,
    support: int,
    detail: str,
) -> Pallet | PalletRejection:
    """The best placement, if every other one that fits is the same pallet."""
    if not placements:
        return PalletRejection(PalletRejectReason.NO_KIND, detail)
    best = min(placements, key=lambda p: p.mismatch_m)  # the first of equals: stable
    for other in placements:
        apart = float(np.hypot(*(other.centre - best.centre).tolist()))
        turned = abs(posture_difference_rad(other.yaw, best.yaw, best.kind.symmetry_rad))
        if (
            other.kind != best.kind
            or apart > tests.same_pallet_m
            or (turned > tests.same_pallet_rad)
        ):
            pair = f"{best.kind} or {other.kind}"
            what = pair if other.kind != best.kind else f"{best.kind}, two ways"
            return PalletRejection(PalletRejectReason.AMBIGUOUS, f"{detail}: {what}")

    covariance = 0.5 * (best.covariance + best.covariance.T)
    x, y = (best.centre + origin).tolist()
    yaw = posture_difference_rad(best.yaw, 0.0, best.kind.symmetry_rad)
    healthy = math.isfinite(x + y + yaw) and bool(np.isfinite(covariance).all())
    if not (healthy and bool((np.diag(covariance) > 0.0).all())):
        return PalletRejection(PalletRejectReason.NON_FINITE, "the fit overflowed")
    return Pallet(x, y, yaw, covariance, best.kind, "", support)
