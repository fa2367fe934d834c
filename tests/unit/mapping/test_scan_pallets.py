"""Pallets in the forklift's own scans: the simulated LMS111 on the pallets site."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from appliance.config.loader import load_config
from appliance.mapping.pallets import PalletKind, posture_difference_rad
from appliance.mapping.scan_pallets import detect_scan_pallets
from appliance.sim.scanner_errors import draw_scanner_errors
from appliance.sim.scanner_model import beam_angles_rad, render_scan
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from drivers.lms111.mounted import DEVICE_FORWARD_RAD, mount_pose

STEP_RAD = math.radians(0.25)
SENSOR_ANGLES = beam_angles_rad(step_rad=STEP_RAD) - DEVICE_FORWARD_RAD


def _scan(vehicle: Pose2D, side: str, seed: int) -> tuple[np.ndarray, Pose2D]:
    """One realistic scan and the scanner's pose as a calibration knows it (its true
    mount and range offset: `dbw calibrate scanners`), in the site frame."""
    config = load_config("forklift-sim")
    site = load_site("pallets")
    mount = mount_pose(getattr(config.geometry, f"scanner_{side}_mount"))
    errors = draw_scanner_errors(seed, 0 if side == "left" else 1, True)
    ranges, _ = render_scan(
        site, 0.0, vehicle, mount, rng=np.random.default_rng(seed), errors=errors,
        step_rad=STEP_RAD,
    )  # fmt: skip
    corrected = np.where(ranges > 0.0, ranges - errors.range_offset_m, 0.0)
    return corrected, vehicle.compose(errors.true_mount(mount))


@pytest.mark.parametrize("seed", [1, 2, 3])
@pytest.mark.parametrize(
    "vehicle", [Pose2D(-2.0, -1.5, 0.0), Pose2D(1.0, -2.0, 0.2), Pose2D(7.5, -6.5, 1.9)]
)
def test_every_pallet_found_is_a_real_one_where_it_stands(vehicle: Pose2D, seed: int) -> None:
    site = load_site("pallets")
    truth = {p.name: p for p in site.pallets}
    found = 0
    for side in ("left", "right"):
        ranges, scanner = _scan(vehicle, side, seed)
        for pallet in detect_scan_pallets(ranges, SENSOR_ANGLES, scanner).pallets:
            nearest = min(
                truth.values(),
                key=lambda p: math.hypot(p.pose.x_m - pallet.x_m, p.pose.y_m - pallet.y_m),
            )
            error_m = math.hypot(nearest.pose.x_m - pallet.x_m, nearest.pose.y_m - pallet.y_m)
            # A face seen from metres away with 12 mm noise, after calibration: a few mm;
            # 20 mm allows the end points' roughness along a single face.
            assert error_m < 0.02, (nearest.name, error_m)
            kind = PalletKind.EUR if nearest.length_m == 1.2 else PalletKind.JIS
            assert pallet.kind is kind
            yaw_error = posture_difference_rad(
                pallet.yaw_rad, nearest.pose.yaw_rad, kind.symmetry_rad
            )
            # Within the detection's own uncertainty (a short face seen obliquely fixes
            # the yaw to a degree; a long one to a tenth), plus the pallet's 0.2 deg.
            sigma_yaw = math.sqrt(pallet.covariance[2, 2])
            assert abs(yaw_error) < 4.0 * sigma_yaw + math.radians(0.2), (nearest.name, yaw_error)
            found += 1
    assert found >= 2  # every pose sees at least a couple of pallets


@pytest.mark.parametrize(
    ("ranges", "angles"),
    [
        (np.zeros(5), np.linspace(0, 1, 5)),
        (np.ones(5), np.array([0.0, 0.1, 0.3, 0.4, 0.5])),  # uneven beams
        (np.ones(4), np.linspace(0, 1, 5)),  # mismatched
        (np.full(100, np.nan), np.linspace(-1, 1, 100)),
    ],
)
def test_a_malformed_or_empty_scan_gives_nothing(ranges: np.ndarray, angles: np.ndarray) -> None:
    found = detect_scan_pallets(ranges, angles, Pose2D(0.0, 0.0, 0.0))
    assert found.pallets == ()


@settings(max_examples=60, deadline=None)
@given(
    ranges=arrays(np.float64, 181, elements=st.one_of(st.floats(-1.0, 30.0), st.just(math.nan))),
    yaw=st.floats(-4.0, 4.0),
)
def test_any_ranges_give_pallets_or_nothing_never_an_exception(
    ranges: np.ndarray, yaw: float
) -> None:
    angles = np.linspace(-math.pi / 2.0, math.pi / 2.0, 181)
    found = detect_scan_pallets(ranges, angles, Pose2D(1.0, 2.0, yaw))
    for pallet in found.pallets:
        assert math.isfinite(pallet.x_m) and np.isfinite(pallet.covariance).all()
