"""Pure pursuit for proportional four-wheel counter-steer: the pure functions.

Stanley et al.'s eqs. 1-3, written in this repository's frames, the look-ahead's floor and
the anchor's prediction the tracker (``pure_pursuit.py``) needs; the path it reads is
``path_geometry``. Everything here is a function of its arguments.

**Signs.** Frames are counter-clockwise positive. ``eta_rad`` is the angle from the
vehicle's heading to the line from the anchor to the goal (a goal to the left is positive)
and a positive front wheel angle turns left; the rear wheels counter-steer by ``k`` times
the front angle, positive in the counter-steer direction, as ``appliance.sim.vehicle``
has it (``yaw_rate = v / L * (tan phi_f + tan phi_r) * G_ss``). The paper's leading minus
sign is its own convention's (after Kuwata et al., steer angle and eta counted in opposite
senses); here a goal to the left must give a left turn, so the minus is dropped, and the
tests drive the simulated vehicle at the commanded angle to check that the anchor does
reach the goal.

**Geometry** (Fig. 8). With ``tan(phi_r) = r * tan(phi_f)`` the instant centre of rotation
lies ``R = L / ((1 + r) tan phi_f)`` to the side, level with a *virtual rear axle*
``L r / (1 + r)`` ahead of the real one. The anchor, ``l_fw`` ahead of the real rear
axle (the paper measures from the rear axle; the vehicle file's
``anchor_point_forward_m`` is from the centre, so ``l_fw = L / 2 + anchor_point_forward_m``),
is ``l = l_fw - L r / (1 + r)`` ahead of the virtual axle. The circle about the centre
of rotation through the anchor passes through a goal at distance ``D`` and angle eta
when ``R = (D / 2 + l cos eta) / sin eta``, hence

    tan phi_f = (L / (1 + r)) sin eta / (D / 2 + (l_fw - L r / (1 + r)) cos eta)

which is eq. 2 with ``r = tan(k phi_f) / tan(phi_f)`` (the wheel *angles* are
proportional), eq. 3 with ``r = k`` and eq. 1 with ``r = 0``.

**Sideslip.** The model's gain ``G_ss`` scales the yaw rate but not the direction of
travel at the centre, so the centre of rotation moves out *from the vehicle centre* by
``1 / G_ss``: the radius grows and the virtual axle slides back by
``(1 / G_ss - 1) (L / 2 - L r / (1 + r))``. ``sideslip_gain`` < 1 puts both into the
formula, so the arc the plant drives is the one pure pursuit meant; with ``G_ss = 1`` the
formula is the paper's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from drivers.geometry import Pose2D

FloatArray = NDArray[np.float64]

EQ2_TOLERANCE_RAD = 1e-12
EQ2_MAX_ITERATIONS = 50
# Below this |phi| the ratio tan(k phi) / tan(phi) is replaced by its series, because the
# quotient of two tiny tangents loses digits and is 0/0 at phi = 0.
_SMALL_ANGLE_RAD = 1e-4


def steer_for_ratio_rad(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    rear_ratio: float,
    sideslip_gain: float = 1.0,
) -> float:
    """Front wheel angle whose arc takes the anchor through the goal (module docstring).

    ``lookahead_m`` is the straight distance from the anchor to the goal (``L_fw``) and
    ``rear_ratio`` is ``tan(phi_r) / tan(phi_f)``. When the denominator is not positive
    the circle through anchor and goal curves away from the goal (it reaches it the long
    way round; with the anchor at or ahead of the virtual axle, only ever for a goal
    behind the anchor), so the answer is full lock towards the goal instead: ``atan2``
    clipped to ±pi/2, continuous as the denominator passes through zero.
    """
    effective_wheelbase_m = wheelbase_m / ((1.0 + rear_ratio) * sideslip_gain)
    virtual_axle_from_centre_m = (
        wheelbase_m * rear_ratio / (1.0 + rear_ratio) - wheelbase_m / 2.0
    ) / sideslip_gain
    anchor_from_virtual_axle_m = anchor_from_rear_axle_m - (
        wheelbase_m / 2.0 + virtual_axle_from_centre_m
    )
    numerator = effective_wheelbase_m * math.sin(eta_rad)
    denominator = lookahead_m / 2.0 + anchor_from_virtual_axle_m * math.cos(eta_rad)
    phi = math.atan2(numerator, denominator)
    return max(-math.pi / 2.0, min(math.pi / 2.0, phi))


def steer_eq3_rad(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
    *,
    sideslip_gain: float = 1.0,
) -> float:
    """The paper's general form, eq. 3 (eq. 1 when ``k = 0``), in our signs.

    ``lookahead_m`` is the distance from the anchor to the goal, ``L_fw`` in the paper.
    """
    return steer_for_ratio_rad(
        eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k, sideslip_gain
    )


def counter_steer_tan_ratio(phi_rad: float, k: float) -> float:
    """``tan(k phi) / tan(phi)``: the tangent ratio when the wheel *angles* are in ratio k.

    Tends to ``k`` as phi -> 0 (series ``k (1 - (1 - k^2) phi^2 / 3)``), and to 0 at
    ±pi/2 where tan(phi) is unbounded.
    """
    if abs(phi_rad) < _SMALL_ANGLE_RAD:
        return k * (1.0 - (1.0 - k * k) * phi_rad * phi_rad / 3.0)
    return math.tan(k * phi_rad) / math.tan(phi_rad)


@dataclass(frozen=True)
class Eq2Solution:
    phi_rad: float
    iterations: int
    converged: bool


def solve_eq2(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
    *,
    sideslip_gain: float = 1.0,
    tolerance_rad: float = EQ2_TOLERANCE_RAD,
    max_iterations: int = EQ2_MAX_ITERATIONS,
) -> Eq2Solution:
    """The open form, eq. 2, by fixed-point iteration.

    ``phi_{n+1} = F(r(phi_n))`` with ``F`` = :func:`steer_for_ratio_rad` and
    ``r(phi) = tan(k phi) / tan(phi)``, from eq. 3's answer (``r = k``). Converged when
    two iterates differ by at most ``tolerance_rad`` (1e-12 rad); after ``max_iterations``
    (50) the last iterate is returned with ``converged=False``. It contracts because ``r``
    changes slowly with phi (``dr/dphi ~ -2 k (1 - k^2) phi / 3``): for the Husky at most
    10 iterations within ±35° and 15 for any goal ahead; it slows only towards ±90°,
    beyond any steering limit. At phi -> 0, ``r`` -> k through its series
    (:func:`counter_steer_tan_ratio`), so eq. 2 meets eq. 3 there and the iteration ends
    at once; with ``k = 0`` the two are the same equation. ``k`` must lie in [0, 1] so
    that ``k phi`` stays within ±pi/2.
    """
    if not 0.0 <= k <= 1.0:
        raise ValueError(f"k must lie in [0, 1] for the open form (got {k})")
    phi = steer_for_ratio_rad(
        eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k, sideslip_gain
    )
    for iteration in range(1, max_iterations + 1):
        ratio = counter_steer_tan_ratio(phi, k)
        following = steer_for_ratio_rad(
            eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, ratio, sideslip_gain
        )
        if abs(following - phi) <= tolerance_rad:
            return Eq2Solution(following, iteration, True)
        phi = following
    return Eq2Solution(phi, max_iterations, False)


def steer_eq2_rad(
    eta_rad: float,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
    *,
    sideslip_gain: float = 1.0,
) -> float:
    """The open form, eq. 2, in our signs (see :func:`solve_eq2`)."""
    return solve_eq2(
        eta_rad, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k, sideslip_gain=sideslip_gain
    ).phi_rad


@dataclass(frozen=True)
class Eq2Eq3Comparison:
    """Eq. 2 against eq. 3 over a grid of eta, for the paper's "<= 2 % within ±30°"."""

    eta_rad: FloatArray
    eq2_rad: FloatArray
    eq3_rad: FloatArray
    relative_difference: FloatArray  # |eq3 - eq2| / |eq2|, 0 where both are 0

    def max_within(self, steer_limit_rad: float, max_abs_eta_rad: float = math.pi / 2) -> float:
        """Largest relative difference where the exact (eq. 2) angle is within the limit.

        Only goals ahead (``|eta| <= max_abs_eta_rad``) by default: a goal behind the
        anchor can also need a small angle (a long way round), which is not tracking.
        """
        inside = (np.abs(self.eq2_rad) <= steer_limit_rad) & (
            np.abs(self.eta_rad) <= max_abs_eta_rad
        )
        return float(np.max(self.relative_difference[inside], initial=0.0))


def eq2_vs_eq3_difference(
    eta_grid_rad: FloatArray,
    lookahead_m: float,
    wheelbase_m: float,
    anchor_from_rear_axle_m: float,
    k: float,
) -> Eq2Eq3Comparison:
    eta = np.asarray(eta_grid_rad, dtype=np.float64)
    eq2 = np.array(
        [steer_eq2_rad(e, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k) for e in eta]
    )
    eq3 = np.array(
        [steer_eq3_rad(e, lookahead_m, wheelbase_m, anchor_from_rear_axle_m, k) for e in eta]
    )
    scale = np.abs(eq2)
    difference = np.abs(eq3 - eq2)
    relative = np.divide(difference, scale, out=np.zeros_like(difference), where=scale > 0)
    return Eq2Eq3Comparison(eta, eq2, eq3, relative)


# --- look-ahead -----------------------------------------------------------------------


def minimum_turn_radius_m(
    wheelbase_m: float, k: float, max_steer_rad: float, sideslip_gain: float = 1.0
) -> float:
    """Lateral distance to the centre of rotation at full lock (eq. 3's geometry)."""
    return wheelbase_m / ((1.0 + k) * math.tan(max_steer_rad) * sideslip_gain)


def minimum_lookahead_m(
    min_turn_radius_m: float, anchor_from_virtual_axle_m: float, linear_eta_rad: float
) -> float:
    """Shortest goal distance at which a goal ``linear_eta_rad`` off the heading is reachable.

    A goal at distance D and angle eta needs ``R = (D / 2 + l cos eta) / sin eta``; below
    ``D = 2 (R_min sin eta - l cos eta)`` that radius is tighter than full lock, so every
    goal further off than eta saturates the steering and pure pursuit stops being a
    smooth law and becomes bang-bang. With this floor a goal up to ``linear_eta_rad``
    off the heading is always inside the reachable set.
    """
    return max(
        0.0,
        2.0
        * (
            min_turn_radius_m * math.sin(linear_eta_rad)
            - anchor_from_virtual_axle_m * math.cos(linear_eta_rad)
        ),
    )


# --- prediction -------------------------------------------------------------------


def predict_pose(
    pose: Pose2D, forward_mps: float, lateral_mps: float, yaw_rate_radps: float, horizon_s: float
) -> Pose2D:
    """Pose after ``horizon_s`` of constant body-frame velocity and yaw rate (an SE(2) arc)."""
    turn = yaw_rate_radps * horizon_s
    if abs(turn) < 1e-9:
        dx_body, dy_body = forward_mps * horizon_s, lateral_mps * horizon_s
    else:
        sin_t, one_minus_cos = math.sin(turn), 1.0 - math.cos(turn)
        dx_body = (forward_mps * sin_t - lateral_mps * one_minus_cos) / yaw_rate_radps
        dy_body = (forward_mps * one_minus_cos + lateral_mps * sin_t) / yaw_rate_radps
    moved = pose.compose(Pose2D(dx_body, dy_body, turn))
    return Pose2D(moved.x_m, moved.y_m, math.remainder(moved.yaw_rad, math.tau))
