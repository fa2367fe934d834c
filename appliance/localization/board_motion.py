"""The control input of Qian et al.'s EKF: the vehicle's motion read off the front board.

The flat-bed has no odometry worth the name (hydraulic motors, idling wheels), so the
paper takes "the change of the parameters of the line segment [of the front board] in k
and k+1" as the input u of the prediction (eq. 2). The board is fixed in the launcher
frame, so if O_f moves by ``(t, Δψ)`` (expressed in its frame at k), the board's line
``(r, α)`` seen from O_f changes by ``α_{k+1} = α_k - Δψ`` and ``r_{k+1} = r_k - n_k·t``;
the component of ``t`` along the board comes from the board's ends, where an end is a
true end (not hidden by something in front of it) in both frames.

Why over a window and not frame to frame: u from two consecutive frames carries the
newest line's noise whole into the prediction, and the same line then updates the
filter, so the estimate jumps with every line (what the paper saw, section 4.3). The
change across a window of about 0.2 s, divided by its duration, is a velocity with a
fraction of that noise; the prediction integrates it over each measurement's time step.
At the walking pace of a docking, the motion hardly changes within the window.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from appliance.localization.compound import wrap_angle_rad
from appliance.localization.ekf_floats import Matrix, inverse_3x3
from appliance.localization.launcher_ekf import BodyMotion

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class BoardEnd:
    """A true end of the board, in the O_f frame, with its uncertainty along the line."""

    x_m: float
    y_m: float
    sigma_m: float


@dataclass(frozen=True)
class BoardSighting:
    """The front board as one scanner saw it at ``t_s``, in the O_f frame."""

    t_s: float
    r_m: float
    alpha_rad: float
    covariance: FloatArray  # of (r, α)
    low_end: BoardEnd | None  # the end at the smaller coordinate along the line, if true
    high_end: BoardEnd | None


@dataclass(frozen=True)
class BoardMotionParams:
    window_s: float = 0.2
    # A pair of sightings further apart than this says nothing about the present motion.
    max_age_s: float = 0.5
    # Along the board, with no true end in view, the motion is known only this well:
    # the fastest the vehicle moves sideways (oblique pattern at docking pace).
    unknown_along_sigma_mps: float = 0.3


def _along(direction: tuple[float, float], end_a: BoardEnd, end_b: BoardEnd, dyaw: float) -> float:
    """How far ``end_a`` is from ``end_b`` (turned by ``dyaw`` into a's frame) along the
    board's ``direction``."""
    c, s = math.cos(dyaw), math.sin(dyaw)
    apart_x = end_a.x_m - (c * end_b.x_m - s * end_b.y_m)
    apart_y = end_a.y_m - (s * end_b.x_m + c * end_b.y_m)
    return direction[0] * apart_x + direction[1] * apart_y


def motion_between(
    older: BoardSighting, newer: BoardSighting, params: BoardMotionParams
) -> BodyMotion | None:
    """O_f's velocity in its own frame from two sightings of the board, with covariance.

    In floats (asked at every scan; a few small arrays cost more than their arithmetic):
    the covariance is ``B diag(var_normal, var_along) Bᵀ`` with ``B`` the board's normal
    and direction as columns, written out."""
    dt_s = newer.t_s - older.t_s
    if not dt_s > 0.0:
        return None
    dyaw = wrap_angle_rad(older.alpha_rad - newer.alpha_rad)
    nx, ny = math.cos(older.alpha_rad), math.sin(older.alpha_rad)
    dx, dy = -ny, nx  # the direction along the board
    along_normal = older.r_m - newer.r_m
    var_normal = older.covariance.item(0, 0) + newer.covariance.item(0, 0)
    var_yaw = older.covariance.item(1, 1) + newer.covariance.item(1, 1)
    weight_sum, weighted = 0.0, 0.0
    for a, b in ((older.low_end, newer.low_end), (older.high_end, newer.high_end)):
        if a is not None and b is not None:
            lever_m = math.hypot(b.x_m, b.y_m)
            weight = 1.0 / (a.sigma_m**2 + b.sigma_m**2 + lever_m**2 * var_yaw)
            weight_sum += weight
            weighted += weight * _along((dx, dy), a, b, dyaw)
    if weight_sum > 0.0:
        along = weighted / weight_sum
        var_along = 1.0 / weight_sum
    else:
        along = 0.0
        var_along = (params.unknown_along_sigma_mps * dt_s) ** 2
    rate = 1.0 / dt_s
    rate_sq = rate * rate
    c00 = (nx * nx * var_normal + dx * dx * var_along) * rate_sq
    c01 = (nx * ny * var_normal + dx * dy * var_along) * rate_sq
    c11 = (ny * ny * var_normal + dy * dy * var_along) * rate_sq
    velocity = np.array(
        [
            (nx * along_normal + dx * along) * rate,
            (ny * along_normal + dy * along) * rate,
            dyaw * rate,
        ]
    )
    covariance = np.array([[c00, c01, 0.0], [c01, c11, 0.0], [0.0, 0.0, var_yaw * rate_sq]])
    return BodyMotion(velocity, covariance, correlation_time_s=dt_s)


class _WindowMotion(NamedTuple):
    """One scanner's window's motion, kept while the window's ends stay the same."""

    older: BoardSighting
    newer: BoardSighting
    motion: BodyMotion | None
    information: Matrix | None  # the inverse of the motion's covariance, as floats
    velocity: list[float]  # the motion's velocity, as floats


class BoardMotion:
    """Keeps each scanner's recent sightings; ``motion`` is the fused velocity.

    ``motion`` is asked for at every scan, and a scan changes one scanner's window: each
    window's motion is kept until its first or last sighting changes (the same sightings
    give the same figures, so nothing but the time is saved)."""

    def __init__(self, params: BoardMotionParams | None = None) -> None:
        self.params = params or BoardMotionParams()
        self._history: dict[str, deque[BoardSighting]] = {}
        self._window_motion: dict[str, _WindowMotion] = {}

    def reset(self) -> None:
        self._history.clear()
        self._window_motion.clear()

    def update(self, sensor: str, sighting: BoardSighting) -> None:
        history = self._history.setdefault(sensor, deque())
        if history and sighting.t_s <= history[-1].t_s:
            return  # out of order or repeated: the window is kept in time order
        history.append(sighting)
        while len(history) > 2 and sighting.t_s - history[1].t_s >= self.params.window_s:
            history.popleft()

    def motion(self, now_s: float) -> BodyMotion | None:
        """The inverse-covariance fusion of every scanner's window, or None when no
        scanner has two recent sightings."""
        estimates: list[_WindowMotion] = []
        for sensor, history in self._history.items():
            if len(history) < 2 or now_s - history[-1].t_s > self.params.max_age_s:
                continue
            if history[-1].t_s - history[0].t_s > self.params.max_age_s:
                continue
            found = self._window(sensor, history[0], history[-1])
            if found.motion is not None and found.information is not None:
                estimates.append(found)
        if not estimates:
            return None
        if len(estimates) == 1:
            return estimates[0].motion
        return _fuse(estimates)

    def _window(self, sensor: str, older: BoardSighting, newer: BoardSighting) -> _WindowMotion:
        kept = self._window_motion.get(sensor)
        if kept is not None and kept.older is older and kept.newer is newer:
            return kept
        found = motion_between(older, newer, self.params)
        information = None if found is None else inverse_3x3(found.covariance.tolist())
        velocity = [] if found is None else found.velocity.tolist()
        kept = _WindowMotion(older, newer, found, information, velocity)
        self._window_motion[sensor] = kept
        return kept


def _fuse(estimates: list[_WindowMotion]) -> BodyMotion | None:
    """The inverse-covariance fusion of windows' motions, ``(Σ Iᵢ)⁻¹ Σ Iᵢ vᵢ``, in floats
    (3x3: numpy's inverses and products cost more than their arithmetic)."""
    total = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    weighted = [0.0, 0.0, 0.0]
    for window in estimates:
        information, velocity = window.information, window.velocity
        assert information is not None
        for i in range(3):
            row = information[i]
            total_row = total[i]
            for j in range(3):
                total_row[j] += row[j]
            weighted[i] += row[0] * velocity[0] + row[1] * velocity[1] + row[2] * velocity[2]
    covariance = inverse_3x3(total)
    if covariance is None:
        return None
    fused = [sum(covariance[i][j] * weighted[j] for j in range(3)) for i in range(3)]
    correlation_s = max(w.motion.correlation_time_s for w in estimates if w.motion is not None)
    return BodyMotion(np.array(fused), np.array(covariance), correlation_s)
