"""The final approach's math: the reference, the curvature law, the detection filter."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from appliance.guidance.pallet_final import (
    DetectionFilter,
    curvature_wish_per_m,
    face_errors,
    lateral_reference,
)
from appliance.guidance.pallet_geometry import entry_face
from appliance.mapping.pallets import Pallet, PalletKind, posture_difference_rad
from drivers.geometry import Pose2D


@given(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-3.0, -0.5), st.floats(0.3, 2.0))
def test_the_reference_meets_its_end_conditions(
    lateral: float, heading: float, x0: float, span: float
) -> None:
    ref = lateral_reference(x0, lateral, heading, x0 + span)
    y, slope, curvature = ref.at(x0)
    assert (y, slope, curvature) == pytest.approx((lateral, math.tan(heading), 0.0), abs=1e-9)
    end = ref.at(x0 + span - 1e-9)
    assert end == pytest.approx((0.0, 0.0, 0.0), abs=1e-6)
    assert ref.at(x0 + span + 1.0) == (0.0, 0.0, 0.0)
    # The derivatives are the derivatives (central differences).
    x, h = x0 + 0.37 * span, 1e-5
    assert ref.at(x)[1] == pytest.approx((ref.at(x + h)[0] - ref.at(x - h)[0]) / (2 * h), abs=1e-5)
    assert ref.at(x)[2] == pytest.approx((ref.at(x + h)[1] - ref.at(x - h)[1]) / (2 * h), abs=1e-4)
    rate = (ref.at(x + h)[2] - ref.at(x - h)[2]) / (2 * h)
    assert ref.curvature_rate_per_m2(x) == pytest.approx(abs(rate), rel=1e-3, abs=1e-3)


def test_the_law_makes_the_error_critically_damped_in_distance() -> None:
    """Driven with the law on the exact kinematics (ẋ = v cos ψ, ė = v sin ψ,
    ψ̇ = v κ), the error from a straight axis follows (e0 + (e0/ℓ) s) e^(−s/ℓ) in the
    distance s along the axis, from 5 cm and from 30 cm (the law is exact, not linear)."""
    ell = 0.2
    zero = (0.0, 0.0, 0.0)
    for e0 in (0.05, 0.3):
        x, e, psi = 0.0, e0, 0.0
        ds = 1e-4
        while x < 1.0:
            kappa = curvature_wish_per_m(e, psi, zero, ell)
            # Integrated in x: de/dx = tan ψ, dψ/dx = κ / cos ψ.
            e += math.tan(psi) * ds
            psi += kappa / math.cos(psi) * ds
            x += ds
        expected = e0 * (1 + x / ell) * math.exp(-x / ell)
        assert e == pytest.approx(expected, rel=2e-3)


def test_face_errors_of_a_vehicle_square_to_a_face() -> None:
    pallet = Pallet(10.0, 2.0, math.pi, np.zeros((3, 3)), PalletKind.EUR)
    face = entry_face(pallet, 0)  # its +length side, at x = 9.4, entered toward +x
    assert face.entry_yaw_rad == pytest.approx(0.0, abs=1e-12)
    centre = Pose2D(9.4 - 0.5 - 2.02, 2.0 + 0.01, math.radians(0.2))
    errors = face_errors(centre, face, 0.8, 2.02, 0.0)
    assert errors.tips_along_m == pytest.approx(-0.5 + 2.02 * (math.cos(math.radians(0.2)) - 1))
    assert errors.tips_lateral_m == pytest.approx(0.01 + 2.02 * math.sin(math.radians(0.2)))
    assert errors.guide_lateral_m == pytest.approx(0.01 + 0.8 * math.sin(math.radians(0.2)))
    assert errors.heading_rad == pytest.approx(math.radians(0.2))
    shifted = face_errors(centre, face, 0.8, 2.02, 0.01)  # a side shifter 1 cm left
    assert shifted.tips_lateral_m == pytest.approx(errors.tips_lateral_m + 0.01, abs=1e-5)


def test_the_filter_follows_a_detection_that_drifts_as_the_vehicle_drives() -> None:
    """An estimate's heading error drifts the detections sideways along the way: the
    line through them, read where the vehicle is, is the latest truth, and the noise
    averages out."""
    rng = np.random.default_rng(3)
    filt = DetectionFilter(memory=0.995, slope_prior_m=0.1)
    drift = math.radians(0.5)
    for i in range(400):
        s = i * 0.004  # 1.6 m at 4 mm a detection
        y = 1.0 + drift * s + rng.normal(0.0, 0.003)
        yaw = 0.3 + rng.normal(0.0, math.radians(0.1)) + (math.pi if i % 3 == 0 else 0.0)
        filt.add(Pallet(5.0, y, yaw, np.zeros((3, 3)), PalletKind.EUR), s)
    fused = filt.pallet_at(1.6)
    assert fused is not None
    assert fused.y_m == pytest.approx(1.0 + drift * 1.6, abs=0.001)
    # On the first detection's branch of the symmetry (that one came half a turn round).
    off = posture_difference_rad(fused.yaw_rad, 0.3, PalletKind.EUR.symmetry_rad)
    assert off == pytest.approx(0.0, abs=math.radians(0.03))
    # Standing still, it is the mean.
    still = DetectionFilter(memory=0.995, slope_prior_m=0.1)
    for y in (1.0, 1.002, 0.998):
        still.add(Pallet(5.0, y, 0.0, np.zeros((3, 3)), PalletKind.JIS), 2.0)
    fused_still = still.pallet_at(2.0)
    assert fused_still is not None
    assert fused_still.y_m == pytest.approx(1.0, abs=1e-5)  # the newer weigh a little more
    off_m, off_rad = still.distance_to(Pallet(5.0, 1.1, math.pi / 2, np.zeros((3, 3))), 2.0)
    assert off_m == pytest.approx(0.1, abs=1e-5)
    assert off_rad == pytest.approx(0.0, abs=1e-12)  # a square pallet a quarter turn round
