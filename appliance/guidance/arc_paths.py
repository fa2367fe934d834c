"""Paths made of arcs and straights, and the shortest forward one between two poses
(Dubins, 1957): what the pallet planner's search strings together.

A path is a start pose and a sequence of pieces, each a curvature held over a length
(left positive; zero for a straight). The vehicle drives them with its guide point
(``pallet_geometry``), so a piece's curvature is ``tan(steer) / wheelbase`` and a path
whose pieces all stay within ``1 / minimum turning radius`` is one it can drive; the
pieces change curvature abruptly, which the tracker smooths by looking ahead.

**Dubins.** Forward only, with curvature bounded by ``1 / r``, a shortest path is one of
six words of at most three pieces: LSL, RSR, LSR, RSL, RLR, LRL (L, R: arcs of radius
``r`` to the left and right; S: a straight). The lengths below are the classic closed
forms in the frame where the start is at the origin and the goal at ``(d, 0)``, in units
of ``r`` (Shkel and Lumelsky, 2001). Every candidate's end is checked against the goal
by integrating its pieces, so a word whose formula does not apply (the branch of an
``atan2``) is dropped rather than trusted.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]

# A word's end must land this near the goal (m, rad) to be kept.
_END_TOLERANCE_M = 1e-6
_END_TOLERANCE_RAD = 1e-6


class PathPiece(NamedTuple):
    curvature_per_m: float  # left positive, 0 for a straight
    length_m: float


def pose_after(pose: Pose2D, piece: PathPiece) -> Pose2D:
    """Where ``piece`` driven from ``pose`` ends."""
    k, s = piece.curvature_per_m, piece.length_m
    if abs(k * s) < 1e-9:
        return Pose2D(
            pose.x_m + s * math.cos(pose.yaw_rad),
            pose.y_m + s * math.sin(pose.yaw_rad),
            pose.yaw_rad,
        )
    yaw = pose.yaw_rad + k * s
    return Pose2D(
        pose.x_m + (math.sin(yaw) - math.sin(pose.yaw_rad)) / k,
        pose.y_m - (math.cos(yaw) - math.cos(pose.yaw_rad)) / k,
        yaw,
    )


def sample_piece(pose: Pose2D, piece: PathPiece, along_m: FloatArray) -> FloatArray:
    """(N, 3) poses at distances ``along_m`` along ``piece`` from ``pose``."""
    k = piece.curvature_per_m
    c, s = math.cos(pose.yaw_rad), math.sin(pose.yaw_rad)
    if abs(k) < 1e-12:
        return np.column_stack(
            [pose.x_m + along_m * c, pose.y_m + along_m * s, np.full_like(along_m, pose.yaw_rad)]
        )
    yaw = pose.yaw_rad + k * along_m
    return np.column_stack(
        [pose.x_m + (np.sin(yaw) - s) / k, pose.y_m - (np.cos(yaw) - c) / k, yaw]
    )


def sample_pieces(
    start: Pose2D, pieces: Sequence[PathPiece], step_m: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The path sampled about every ``step_m`` (each piece's ends included): poses (N, 3),
    the curvature at each sample (the piece's it starts; the last one's at the end), and
    the arc length of each sample from the start."""
    poses: list[FloatArray] = [np.array([[start.x_m, start.y_m, start.yaw_rad]])]
    curvatures: list[FloatArray] = [np.array([pieces[0].curvature_per_m if pieces else 0.0])]
    arcs: list[FloatArray] = [np.zeros(1)]
    pose, travelled = start, 0.0
    for piece in pieces:
        if piece.length_m <= 0.0:
            continue
        count = max(1, math.ceil(piece.length_m / step_m))
        along = np.linspace(0.0, piece.length_m, count + 1)[1:]
        poses.append(sample_piece(pose, piece, along))
        curvatures.append(np.full(count, piece.curvature_per_m))
        arcs.append(travelled + along)
        pose = pose_after(pose, piece)
        travelled += piece.length_m
    return np.concatenate(poses), np.concatenate(curvatures), np.concatenate(arcs)


def _mod_tau(angle: float) -> float:
    return angle % math.tau


Word = tuple[float, float, float]


def _lsl(a: float, b: float, d: float) -> Word | None:
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    # The straight is the line between the two circles' centres: its length as their
    # distance, not as the textbook's 2 + d² − 2 cos(a − b) + ..., which loses a goal a
    # few 1e-8 turning radii straight ahead to cancellation (a path shorter than the way).
    heading = math.atan2(cb - ca, d + sa - sb)
    return _mod_tau(heading - a), math.hypot(d + sa - sb, cb - ca), _mod_tau(b - heading)


def _rsr(a: float, b: float, d: float) -> Word | None:
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    heading = math.atan2(ca - cb, d - sa + sb)  # the straight's length as in `_lsl`
    return _mod_tau(a - heading), math.hypot(d - sa + sb, ca - cb), _mod_tau(heading - b)


def _lsr(a: float, b: float, d: float) -> Word | None:
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    # The centres' distance less the two radii, times it plus them: the tangent's square.
    centres = math.hypot(d + sa + sb, ca + cb)
    p2 = (centres - 2.0) * (centres + 2.0)
    if p2 < 0.0:
        return None
    p = math.sqrt(p2)
    heading = math.atan2(-ca - cb, d + sa + sb) - math.atan2(-2.0, p)
    return _mod_tau(heading - a), p, _mod_tau(heading - b)


def _rsl(a: float, b: float, d: float) -> Word | None:
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    centres = math.hypot(d - sa - sb, ca + cb)  # as in `_lsr`
    p2 = (centres - 2.0) * (centres + 2.0)
    if p2 < 0.0:
        return None
    p = math.sqrt(p2)
    heading = math.atan2(ca + cb, d - sa - sb) - math.atan2(2.0, p)
    return _mod_tau(a - heading), p, _mod_tau(b - heading)


def _rlr(a: float, b: float, d: float) -> Word | None:
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    cos_p = (6.0 - d * d + 2.0 * math.cos(a - b) + 2.0 * d * (sa - sb)) / 8.0
    if abs(cos_p) > 1.0:
        return None
    p = _mod_tau(math.tau - math.acos(cos_p))
    t = _mod_tau(a - math.atan2(ca - cb, d - sa + sb) + p / 2.0)
    return t, p, _mod_tau(a - b - t + p)


def _lrl(a: float, b: float, d: float) -> Word | None:
    sa, sb, ca, cb = math.sin(a), math.sin(b), math.cos(a), math.cos(b)
    cos_p = (6.0 - d * d + 2.0 * math.cos(a - b) + 2.0 * d * (sb - sa)) / 8.0
    if abs(cos_p) > 1.0:
        return None
    p = _mod_tau(math.tau - math.acos(cos_p))
    t = _mod_tau(-a + math.atan2(-ca + cb, d + sa - sb) + p / 2.0)
    return t, p, _mod_tau(b - a - t + p)


# Each word's formula and the sign of each piece's curvature (0: straight).
_WORDS: tuple[tuple[Callable[[float, float, float], Word | None], tuple[int, int, int]], ...] = (
    (_lsl, (1, 0, 1)),
    (_rsr, (-1, 0, -1)),
    (_lsr, (1, 0, -1)),
    (_rsl, (-1, 0, 1)),
    (_rlr, (-1, 1, -1)),
    (_lrl, (1, -1, 1)),
)


def _lands(start: Pose2D, pieces: Sequence[PathPiece], goal: Pose2D) -> bool:
    pose = start
    for piece in pieces:
        pose = pose_after(pose, piece)
    return (
        math.hypot(pose.x_m - goal.x_m, pose.y_m - goal.y_m) <= _END_TOLERANCE_M
        and abs(math.remainder(pose.yaw_rad - goal.yaw_rad, math.tau)) <= _END_TOLERANCE_RAD
    )


def dubins_paths(start: Pose2D, goal: Pose2D, radius_m: float) -> list[tuple[PathPiece, ...]]:
    """Every Dubins word from ``start`` to ``goal`` with turns of ``radius_m``, shortest
    first (each one checked to end at the goal)."""
    dx, dy = goal.x_m - start.x_m, goal.y_m - start.y_m
    d = math.hypot(dx, dy) / radius_m
    theta = math.atan2(dy, dx) if d > 0.0 else 0.0
    a = _mod_tau(start.yaw_rad - theta)
    b = _mod_tau(goal.yaw_rad - theta)
    found: list[tuple[float, tuple[PathPiece, ...]]] = []
    for formula, signs in _WORDS:
        word = formula(a, b, d)
        if word is None:
            continue
        pieces = tuple(
            PathPiece(sign / radius_m, length * radius_m)
            for sign, length in zip(signs, word, strict=True)
            if length * radius_m > 1e-9
        )
        if _lands(start, pieces, goal):
            found.append((sum(length for length in word) * radius_m, pieces))
    found.sort(key=lambda item: item[0])
    return [pieces for _, pieces in found]


def dubins_length_m(start: Pose2D, goal: Pose2D, radius_m: float) -> float:
    """The shortest forward path's length (inf when none is found)."""
    paths = dubins_paths(start, goal, radius_m)
    return sum(p.length_m for p in paths[0]) if paths else math.inf
