"""Smith, Self and Cheeseman's compounding of planar poses, with its Jacobians.

Qian et al. predict the vehicle's pose as ``x ⊕ u`` (eq. 2) and then approximate the
covariance by ``P + Q`` (eq. 3), which holds only while the heading stays near zero. The
Jacobians below give the first-order propagation at any heading, so a run that crosses
ψ = ±π is handled like one that does not: the filter uses them and the approximation is
not needed. Arrays in, arrays out; poses are ``(x_m, y_m, yaw_rad)``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


def wrap_angle_rad(angle_rad: float) -> float:
    """The angle in [-π, π): a heading or a bearing residual compared across the cut."""
    return (angle_rad + math.pi) % math.tau - math.pi


def compound(pose: FloatArray, delta: FloatArray) -> FloatArray:
    """``pose ⊕ delta``: ``delta`` (given in ``pose``'s frame) expressed in the parent frame."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array(
        [
            pose[0] + c * delta[0] - s * delta[1],
            pose[1] + s * delta[0] + c * delta[1],
            wrap_angle_rad(float(pose[2] + delta[2])),
        ]
    )


def compound_jacobians(pose: FloatArray, delta: FloatArray) -> tuple[FloatArray, FloatArray]:
    """∂(pose ⊕ delta)/∂pose and ∂(pose ⊕ delta)/∂delta at the given point."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    j_pose = np.array(
        [
            [1.0, 0.0, -s * delta[0] - c * delta[1]],
            [0.0, 1.0, c * delta[0] - s * delta[1]],
            [0.0, 0.0, 1.0],
        ]
    )
    j_delta = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return j_pose, j_delta


def inverse(pose: FloatArray) -> FloatArray:
    """``⊖ pose``: the parent frame seen from ``pose``."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array(
        [-c * pose[0] - s * pose[1], s * pose[0] - c * pose[1], wrap_angle_rad(float(-pose[2]))]
    )


def relative(from_pose: FloatArray, to_pose: FloatArray) -> FloatArray:
    """``⊖ from_pose ⊕ to_pose``: where ``to_pose`` is, seen from ``from_pose``."""
    return compound(inverse(from_pose), to_pose)
