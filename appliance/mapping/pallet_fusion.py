"""One pallet seen from several viewpoints: its detections merged into one estimate.

Detections are grouped greedily in the order given (deterministic): each joins the
nearest group of the same kind whose first member is within ``gate_m`` and whose
posture agrees within ``gate_rad`` modulo the kind's symmetry, or starts a group. A
group's estimate is the information-weighted mean of its members' poses, the postures
first brought next to the first member's (a EUR pallet at 179° and one at −179° are 2°
apart, not 358°), the covariance the inverse of the summed information. That is the
right answer for independent detections and too confident for correlated ones (two
viewpoints that pick the very same points): the caller's viewpoints should differ.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from appliance.mapping.pallets import FloatArray, Pallet, posture_difference_rad


def fuse_pallets(pallets: Sequence[Pallet], gate_m: float, gate_rad: float) -> tuple[Pallet, ...]:
    """The pallets with every group of detections of one pallet merged, in the order of
    each group's first detection."""
    groups: list[list[Pallet]] = []
    for pallet in pallets:
        nearest: list[Pallet] | None = None
        nearest_m = math.inf
        for group in groups:
            first = group[0]
            if first.kind != pallet.kind:
                continue
            apart_m = math.hypot(pallet.x_m - first.x_m, pallet.y_m - first.y_m)
            turn = posture_difference_rad(pallet.yaw_rad, first.yaw_rad, first.kind.symmetry_rad)
            if apart_m <= gate_m and abs(turn) <= gate_rad and apart_m < nearest_m:
                nearest, nearest_m = group, apart_m
        if nearest is None:
            groups.append([pallet])
        else:
            nearest.append(pallet)
    return tuple(_merged(group) for group in groups)


def _merged(group: list[Pallet]) -> Pallet:
    first = group[0]
    if len(group) == 1:
        return first
    symmetry = first.kind.symmetry_rad
    poses = np.array(
        [
            (
                p.x_m,
                p.y_m,
                first.yaw_rad + posture_difference_rad(p.yaw_rad, first.yaw_rad, symmetry),
            )
            for p in group
        ]
    )
    with np.errstate(all="ignore"):
        try:
            informations = np.linalg.inv(np.stack([p.covariance for p in group]))
            covariance = np.linalg.inv(informations.sum(axis=0))
        except np.linalg.LinAlgError:
            return _surest(group)
        mean: FloatArray = covariance @ np.einsum("kij,kj->i", informations, poses)
    covariance = 0.5 * (covariance + covariance.T)
    if not (np.isfinite(mean).all() and np.isfinite(covariance).all()):
        return _surest(group)
    x, y, yaw = mean.tolist()
    return Pallet(
        x,
        y,
        posture_difference_rad(yaw, 0.0, symmetry),
        covariance,
        first.kind,
        first.name,
        sum(p.support for p in group),
    )


def _surest(group: list[Pallet]) -> Pallet:
    """The member with the smallest positional uncertainty, when the information form
    cannot be computed (a covariance too small or too large to invert)."""
    return min(group, key=lambda p: float(np.trace(p.covariance[:2, :2])))
