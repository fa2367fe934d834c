"""The launcher EKF's matrix algebra in plain floats: 3 states, 2-D measurements.

Why floats: at these sizes (3x3, 2x3, 2x2) every numpy call costs a microsecond or two
of overhead for a handful of multiplications, and the filter runs several updates per
scan, two scans every 40 ms, inside the control step. The same algebra written with
numpy (filterpy's ``ExtendedKalmanFilter.update``, ``J P Jᵀ``) is the reference the
tests hold these to, to rounding (``tests/unit/localization/test_ekf_floats.py``).

Matrices are lists of rows; nothing here allocates an array.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

Matrix = list[list[float]]


def nis_2d(h: Matrix, p: Matrix, r: Matrix, y0: float, y1: float) -> float:
    """``yᵀ S⁻¹ y`` with ``S = H P Hᵀ + R`` (2x3, 3x3, 2x2), Cramer's rule for the solve.
    ``ZeroDivisionError`` for a singular ``S``."""
    (a0, a1, a2), (b0, b1, b2) = h
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = p
    u0, u1, u2 = (a0 * p00 + a1 * p10 + a2 * p20, a0 * p01 + a1 * p11 + a2 * p21,
                  a0 * p02 + a1 * p12 + a2 * p22)  # fmt: skip
    v0, v1, v2 = (b0 * p00 + b1 * p10 + b2 * p20, b0 * p01 + b1 * p11 + b2 * p21,
                  b0 * p02 + b1 * p12 + b2 * p22)  # fmt: skip
    s00, s01 = u0 * a0 + u1 * a1 + u2 * a2 + r[0][0], u0 * b0 + u1 * b1 + u2 * b2 + r[0][1]
    s10, s11 = v0 * a0 + v1 * a1 + v2 * a2 + r[1][0], v0 * b0 + v1 * b1 + v2 * b2 + r[1][1]
    det = s00 * s11 - s01 * s10
    if det == 0.0:
        raise ZeroDivisionError("singular innovation covariance")
    return (y0 * (s11 * y0 - s01 * y1) + y1 * (s00 * y1 - s10 * y0)) / det


def joseph_update(
    x: list[float], p: Matrix, h: Matrix, r: Matrix, y: tuple[float, float]
) -> tuple[list[float], Matrix] | None:
    """The Kalman update of state ``x`` and covariance ``p`` by a 2-D measurement with
    Jacobian ``h``, noise ``r`` and residual ``y``, covariance in the Joseph form
    ``(I − KH) P (I − KH)ᵀ + K R Kᵀ`` (it stays symmetric and positive where ``(I − KH) P``
    does not), symmetrised. None when ``S`` is singular or the result not finite.
    Written out element by element: loops and comprehensions would cost more than the
    arithmetic."""
    (a0, a1, a2), (b0, b1, b2) = h
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = p
    (r00, r01), (r10, r11) = r
    # PHᵀ (3x2): column u is P aᵀ, column v is P bᵀ
    u0, u1, u2 = (
        p00 * a0 + p01 * a1 + p02 * a2,
        p10 * a0 + p11 * a1 + p12 * a2,
        p20 * a0 + p21 * a1 + p22 * a2,
    )
    v0, v1, v2 = (
        p00 * b0 + p01 * b1 + p02 * b2,
        p10 * b0 + p11 * b1 + p12 * b2,
        p20 * b0 + p21 * b1 + p22 * b2,
    )
    s00 = a0 * u0 + a1 * u1 + a2 * u2 + r00
    s01 = a0 * v0 + a1 * v1 + a2 * v2 + r01
    s10 = b0 * u0 + b1 * u1 + b2 * u2 + r10
    s11 = b0 * v0 + b1 * v1 + b2 * v2 + r11
    det = s00 * s11 - s01 * s10
    if not (det != 0.0 and math.isfinite(det)):
        return None
    i00, i01, i10, i11 = s11 / det, -s01 / det, -s10 / det, s00 / det
    # K = PHᵀ S⁻¹ (3x2), rows (k0, l0), (k1, l1), (k2, l2)
    k0, l0 = u0 * i00 + v0 * i10, u0 * i01 + v0 * i11
    k1, l1 = u1 * i00 + v1 * i10, u1 * i01 + v1 * i11
    k2, l2 = u2 * i00 + v2 * i10, u2 * i01 + v2 * i11
    y0, y1 = y
    moved = [x[0] + k0 * y0 + l0 * y1, x[1] + k1 * y0 + l1 * y1, x[2] + k2 * y0 + l2 * y1]
    # I − KH (3x3)
    m00, m01, m02 = 1.0 - k0 * a0 - l0 * b0, -k0 * a1 - l0 * b1, -k0 * a2 - l0 * b2
    m10, m11, m12 = -k1 * a0 - l1 * b0, 1.0 - k1 * a1 - l1 * b1, -k1 * a2 - l1 * b2
    m20, m21, m22 = -k2 * a0 - l2 * b0, -k2 * a1 - l2 * b1, 1.0 - k2 * a2 - l2 * b2
    # (I − KH) P
    n00, n01, n02 = (
        m00 * p00 + m01 * p10 + m02 * p20,
        m00 * p01 + m01 * p11 + m02 * p21,
        m00 * p02 + m01 * p12 + m02 * p22,
    )
    n10, n11, n12 = (
        m10 * p00 + m11 * p10 + m12 * p20,
        m10 * p01 + m11 * p11 + m12 * p21,
        m10 * p02 + m11 * p12 + m12 * p22,
    )
    n20, n21, n22 = (
        m20 * p00 + m21 * p10 + m22 * p20,
        m20 * p01 + m21 * p11 + m22 * p21,
        m20 * p02 + m21 * p12 + m22 * p22,
    )
    # K R (3x2)
    q0, w0 = k0 * r00 + l0 * r10, k0 * r01 + l0 * r11
    q1, w1 = k1 * r00 + l1 * r10, k1 * r01 + l1 * r11
    q2, w2 = k2 * r00 + l2 * r10, k2 * r01 + l2 * r11
    # (I − KH) P (I − KH)ᵀ + K R Kᵀ
    c00 = n00 * m00 + n01 * m01 + n02 * m02 + q0 * k0 + w0 * l0
    c01 = n00 * m10 + n01 * m11 + n02 * m12 + q0 * k1 + w0 * l1
    c02 = n00 * m20 + n01 * m21 + n02 * m22 + q0 * k2 + w0 * l2
    c10 = n10 * m00 + n11 * m01 + n12 * m02 + q1 * k0 + w1 * l0
    c11 = n10 * m10 + n11 * m11 + n12 * m12 + q1 * k1 + w1 * l1
    c12 = n10 * m20 + n11 * m21 + n12 * m22 + q1 * k2 + w1 * l2
    c20 = n20 * m00 + n21 * m01 + n22 * m02 + q2 * k0 + w2 * l0
    c21 = n20 * m10 + n21 * m11 + n22 * m12 + q2 * k1 + w2 * l1
    c22 = n20 * m20 + n21 * m21 + n22 * m22 + q2 * k2 + w2 * l2
    e01, e02, e12 = 0.5 * (c01 + c10), 0.5 * (c02 + c20), 0.5 * (c12 + c21)
    if not math.isfinite(moved[0] + moved[1] + moved[2] + c00 + c11 + c22 + e01 + e02 + e12):
        return None
    return moved, [[c00, e01, e02], [e01, c11, e12], [e02, e12, c22]]


def propagate(p: Matrix, j_pose: Matrix, j_delta: Matrix, q: Matrix) -> Matrix:
    """``J_pose P J_poseᵀ + J_delta Q J_deltaᵀ`` (all 3x3): the prediction's covariance."""
    a = sandwich(j_pose, p)
    b = sandwich(j_delta, q)
    return [
        [a[0][0] + b[0][0], a[0][1] + b[0][1], a[0][2] + b[0][2]],
        [a[1][0] + b[1][0], a[1][1] + b[1][1], a[1][2] + b[1][2]],
        [a[2][0] + b[2][0], a[2][1] + b[2][1], a[2][2] + b[2][2]],
    ]


def sandwich(j: Sequence[Sequence[float]], m: Sequence[Sequence[float]]) -> Matrix:
    """``J M Jᵀ`` of 3x3 matrices, written out."""
    (j00, j01, j02), (j10, j11, j12), (j20, j21, j22) = j
    (m00, m01, m02), (m10, m11, m12), (m20, m21, m22) = m
    t00, t01, t02 = (
        j00 * m00 + j01 * m10 + j02 * m20,
        j00 * m01 + j01 * m11 + j02 * m21,
        j00 * m02 + j01 * m12 + j02 * m22,
    )
    t10, t11, t12 = (
        j10 * m00 + j11 * m10 + j12 * m20,
        j10 * m01 + j11 * m11 + j12 * m21,
        j10 * m02 + j11 * m12 + j12 * m22,
    )
    t20, t21, t22 = (
        j20 * m00 + j21 * m10 + j22 * m20,
        j20 * m01 + j21 * m11 + j22 * m21,
        j20 * m02 + j21 * m12 + j22 * m22,
    )
    return [
        [
            t00 * j00 + t01 * j01 + t02 * j02,
            t00 * j10 + t01 * j11 + t02 * j12,
            t00 * j20 + t01 * j21 + t02 * j22,
        ],
        [
            t10 * j00 + t11 * j01 + t12 * j02,
            t10 * j10 + t11 * j11 + t12 * j12,
            t10 * j20 + t11 * j21 + t12 * j22,
        ],
        [
            t20 * j00 + t21 * j01 + t22 * j02,
            t20 * j10 + t21 * j11 + t22 * j12,
            t20 * j20 + t21 * j21 + t22 * j22,
        ],
    ]


def inverse_3x3(m: Matrix) -> Matrix | None:
    """The inverse of a 3x3 matrix by cofactors; None if singular or not finite. (For
    the well-conditioned covariances and informations of the filter, within a few
    rounding errors of ``numpy.linalg.inv``.)"""
    (a, b, c), (d, e, f), (g, h, i) = m
    co_a, co_b, co_c = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * co_a + b * co_b + c * co_c
    if not (det != 0.0 and math.isfinite(det)):
        return None
    inverse = [
        [co_a / det, (c * h - b * i) / det, (b * f - c * e) / det],
        [co_b / det, (a * i - c * g) / det, (c * d - a * f) / det],
        [co_c / det, (b * g - a * h) / det, (a * e - b * d) / det],
    ]
    if not all(math.isfinite(v) for row in inverse for v in row):
        return None
    return inverse
