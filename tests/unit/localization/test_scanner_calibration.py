"""The scanner calibration against the simulator: scans rendered at the docked pose from
each scanner's true mount, with its drawn range offset, scale error, noise and footprint;
the fit must find the offsets the simulator drew, say how well it knows them, and refuse
what it cannot use, never raise."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import numpy.typing as npt
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.localization.launcher_map import LauncherMap
from appliance.localization.scanner_calibration import calibrate_scanner, calibrated_mount
from appliance.localization.scanner_calibration_params import CalibrationParams, DockedPose
from appliance.localization.scanner_calibration_points import BOARD
from appliance.localization.scanner_calibration_verdict import ScannerCalibrationResult
from appliance.sim.scanner_errors import ScannerErrors, draw_scanner_errors, ideal_scanner
from appliance.sim.scanner_model import DEVICE_FORWARD_RAD, RayCache, beam_angles_rad, render_scan
from appliance.sim.site import Circle, Site
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D

FloatArray = npt.NDArray[np.float64]
SITE = load_site("launcher")
LAUNCHER = LauncherMap()
MOUNTS = (Pose2D(5.8, 1.5, math.radians(45.0)), Pose2D(5.8, -1.5, math.radians(-45.0)))
DOCKED = DockedPose.at_front_end(Pose2D(0.0, 0.0, 0.0), 6.0)
ANGLES = beam_angles_rad() - DEVICE_FORWARD_RAD  # sensor frame, 0.25°: 1081 beams
SCANS = 20  # 0.8 s at 25 Hz: σ 0.7 mm and 0.01° from the points


def render(
    mount: Pose2D,
    errors: ScannerErrors,
    *,
    vehicle: Pose2D = DOCKED.centre,
    site: Site = SITE,
    scans: int = SCANS,
    seed: int = 0,
) -> list[tuple[FloatArray, FloatArray]]:
    rng = np.random.default_rng(seed)
    cache = RayCache()
    return [
        (render_scan(site, 0.0, vehicle, mount, rng=rng, errors=errors, cache=cache)[0], ANGLES)
        for _ in range(scans)
    ]


def fit(
    index: int,
    errors: ScannerErrors,
    *,
    vehicle: Pose2D = DOCKED.centre,
    site: Site = SITE,
    docked: DockedPose = DOCKED,
    params: CalibrationParams | None = None,
    seed: int = 0,
) -> ScannerCalibrationResult:
    mount = MOUNTS[index]
    scans = render(mount, errors, vehicle=vehicle, site=site, seed=seed)
    return calibrate_scanner(scans, mount, docked, LAUNCHER, params)


def true_lateral_m(index: int, errors: ScannerErrors) -> float:
    """The drawn mount error's offset along the vehicle's y (it is drawn in the mount's)."""
    yaw = MOUNTS[index].yaw_rad
    error = errors.mount_error
    return math.sin(yaw) * error.x_m + math.cos(yaw) * error.y_m


def assert_finite(result: ScannerCalibrationResult) -> None:
    estimate = result.estimate
    if estimate is None:
        return
    values = [
        estimate.range_offset_m,
        estimate.range_offset_sigma_m,
        estimate.mount_yaw_offset_rad,
        estimate.mount_yaw_offset_sigma_rad,
        estimate.mount_yaw_offset_statistical_sigma_rad,
        estimate.lateral_offset_sigma_m,
        estimate.residual_rms_m,
    ]
    values += [v for p in estimate.parameters for v in (p.value, p.sigma, p.statistical_sigma)]
    if estimate.lateral_offset_m is not None:
        values.append(estimate.lateral_offset_m)
    assert all(math.isfinite(v) for v in values), values


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
@pytest.mark.parametrize("index", [0, 1])
def test_recovers_the_drawn_range_offset_and_yaw(seed: int, index: int) -> None:
    errors = draw_scanner_errors(seed, index, True)
    result = fit(index, errors, seed=seed)
    assert result.accepted, result.reasons
    estimate = result.estimate
    assert estimate is not None
    # The render's scale error (≤ 0.05 % of 1-3 m: ≤ 1.5 mm) is not modelled.
    range_error = abs(estimate.range_offset_m - errors.range_offset_m)
    assert range_error <= min(0.003, 4.0 * estimate.range_offset_sigma_m + 0.0015)
    yaw_error = abs(estimate.mount_yaw_offset_rad - errors.mount_error.yaw_rad)
    assert math.degrees(yaw_error) <= 0.03
    assert yaw_error <= 4.0 * estimate.mount_yaw_offset_statistical_sigma_rad
    assert estimate.residual_rms_m < 0.010  # the data sheet's 12 mm, projected on the normals
    assert result.points_used[BOARD] >= 30 * SCANS
    assert result.scans_used == SCANS
    # The troughs' tolerances hide the mount's position: reported, not applied.
    assert estimate.lateral_offset_m is None
    assert estimate.lateral_offset_sigma_m == pytest.approx(0.010, abs=0.001)
    assert math.degrees(estimate.mount_yaw_offset_sigma_rad) == pytest.approx(0.3, abs=0.01)
    assert any("lateral mount offset not observable" in note for note in result.notes)


@pytest.mark.parametrize("index", [0, 1])
def test_the_ideal_scanner_gives_zeros(index: int) -> None:
    result = fit(index, ideal_scanner())
    assert result.accepted, result.reasons
    estimate = result.estimate
    assert estimate is not None
    assert estimate.range_offset_m == pytest.approx(0.0, abs=1e-6)
    assert estimate.mount_yaw_offset_rad == pytest.approx(0.0, abs=1e-6)
    for parameter in estimate.parameters:
        assert parameter.value == pytest.approx(0.0, abs=1e-6), parameter


@pytest.mark.parametrize("index", [0, 1])
@pytest.mark.parametrize(
    ("longitudinal_m", "lateral_m", "heading_deg"),
    [(0.0, 0.01, 0.0), (0.0, -0.01, 0.0), (0.0, 0.0, 0.2), (0.0, 0.0, -0.2), (0.003, 0.0, 0.0)],
)
def test_a_vehicle_off_its_docked_pose_moves_the_result_only_as_sigma_says(
    index: int, longitudinal_m: float, lateral_m: float, heading_deg: float
) -> None:
    """Scans from a vehicle displaced within the troughs, fitted as if it stood exactly
    docked: each parameter moves by the displacement's share of its pose σ, plus noise."""
    errors = draw_scanner_errors(11, index, True)
    base = fit(index, errors)
    moved_pose = DOCKED.displaced(longitudinal_m, lateral_m, math.radians(heading_deg))
    moved = fit(index, errors, vehicle=moved_pose)
    assert base.estimate is not None and moved.estimate is not None
    assert base.accepted and moved.accepted
    share = max(
        abs(longitudinal_m) / DOCKED.longitudinal_tolerance_m,
        abs(lateral_m) / DOCKED.lateral_tolerance_m,
        abs(math.radians(heading_deg)) / DOCKED.heading_tolerance_rad,
    )
    for before, after in zip(base.estimate.parameters, moved.estimate.parameters, strict=True):
        shift = abs(after.value - before.value)
        noise = 4.0 * math.sqrt(before.statistical_sigma**2 + after.statistical_sigma**2)
        assert shift <= share * before.pose_sigma + noise, (before.name, shift, before)
    # And the pose part goes where the geometry says: a turn is all yaw, a shift all offset.
    yaw_shift = moved.estimate.mount_yaw_offset_rad - base.estimate.mount_yaw_offset_rad
    assert math.degrees(yaw_shift) == pytest.approx(heading_deg, abs=0.03)
    range_shift = moved.estimate.range_offset_m - base.estimate.range_offset_m
    assert abs(range_shift) <= 4.0 * base.estimate.range_offset_sigma_m


@pytest.mark.parametrize("index", [0, 1])
def test_a_standoff_and_a_known_turn_are_taken_into_account(index: int) -> None:
    """Docked short of the board (a standoff) and turned by a known degree: the predicted
    board and cylinders move with the pose, and the offsets still come out."""
    docked = DockedPose.at_front_end(Pose2D(-0.3, 0.02, math.radians(1.0)), 6.0)
    errors = draw_scanner_errors(8, index, True)
    result = fit(index, errors, vehicle=docked.centre, docked=docked)
    assert result.accepted, result.reasons
    assert result.range_offset_m == pytest.approx(errors.range_offset_m, abs=0.003)
    yaw = result.mount_yaw_offset_rad
    assert yaw is not None
    assert math.degrees(yaw) == pytest.approx(math.degrees(errors.mount_error.yaw_rad), abs=0.04)


def test_the_lateral_offset_is_observable_when_the_pose_is_known_well() -> None:
    tight = replace(
        DOCKED,
        lateral_tolerance_m=0.0005,
        longitudinal_tolerance_m=0.0005,
        heading_tolerance_rad=math.radians(0.01),
    )
    for index in (0, 1):
        errors = draw_scanner_errors(5, index, True)
        result = fit(index, errors, docked=tight, seed=index)
        assert result.accepted, result.reasons
        estimate = result.estimate
        assert estimate is not None
        assert estimate.lateral_offset_m is not None
        assert estimate.lateral_offset_sigma_m < 0.0025
        assert estimate.lateral_offset_m == pytest.approx(true_lateral_m(index, errors), abs=0.003)
        assert not any("lateral mount offset not observable" in n for n in result.notes)


@pytest.mark.parametrize(
    "person_xy",
    [(-0.1, 2.09), (-0.95, 2.57)],
    ids=["in front of the left cylinder", "just behind its edge"],
)
def test_a_person_at_a_cylinder_refuses_that_scanner_with_the_reason(
    person_xy: tuple[float, float],
) -> None:
    person = Circle(*person_xy, 0.25, 0.3, "person")
    site = replace(SITE, circles=(*SITE.circles, person))
    left = fit(0, draw_scanner_errors(2, 0, True), site=site)
    assert not left.accepted
    assert left.estimate is None
    assert left.points_used["cylinder_left"] == 0
    assert left.points_used[BOARD] > 30 * SCANS  # the board is still seen
    (reason,) = left.reasons
    assert "too few points on any cylinder" in reason
    # What the extractor said of the arc where the cylinder stands: cut short or crowded.
    assert any(f"cylinder_left.{why}" in reason for why in ("too_narrow", "not_isolated"))
    right = fit(1, draw_scanner_errors(2, 1, True), site=site)  # the right one cannot see it
    assert right.accepted, right.reasons


def test_a_person_a_little_away_from_the_cylinder_does_not_matter() -> None:
    errors = draw_scanner_errors(2, 0, True)
    person = Circle(-1.6, 2.9, 0.25, 0.3, "person")
    site = replace(SITE, circles=(*SITE.circles, person))
    result = fit(0, errors, site=site)
    assert result.accepted, result.reasons
    assert result.range_offset_m == pytest.approx(errors.range_offset_m, abs=0.003)


def test_too_few_points_refuse() -> None:
    scans = render(MOUNTS[0], draw_scanner_errors(1, 0, True), scans=1)
    ranges, angles = scans[0]
    sparse = np.where(np.arange(ranges.size) % 8 == 0, ranges, 0.0)  # every 8th beam only
    result = calibrate_scanner([(sparse, angles)], MOUNTS[0], DOCKED, LAUNCHER)
    assert not result.accepted
    assert result.estimate is None
    assert any("too few points" in reason for reason in result.reasons)

    nothing = calibrate_scanner([], MOUNTS[0], DOCKED, LAUNCHER)
    assert not nothing.accepted and nothing.reasons == ("no scans",)

    blind = calibrate_scanner([(np.zeros(1081), angles)], MOUNTS[0], DOCKED, LAUNCHER)
    assert not blind.accepted
    assert blind.points_used == {BOARD: 0, "cylinder_left": 0, "cylinder_right": 0}

    strict = CalibrationParams(min_board_points=10 * SCANS * 100)
    result = calibrate_scanner(scans, MOUNTS[0], DOCKED, LAUNCHER, strict)
    assert not result.accepted
    assert "too few points on the front board" in result.reasons[0]


def test_the_wrong_scanner_is_refused() -> None:
    """The right scanner's scans taken for the left's: nothing is where the left one
    would see it."""
    scans = render(MOUNTS[1], draw_scanner_errors(1, 1, True), scans=2)
    result = calibrate_scanner(scans, MOUNTS[0], DOCKED, LAUNCHER)
    assert not result.accepted
    assert result.reasons


def test_thresholds_refuse_with_their_numbers() -> None:
    errors = draw_scanner_errors(3, 0, True)  # a range offset of -14 mm, yaw -0.28°
    strict = CalibrationParams(
        max_range_offset_m=0.005,
        max_yaw_offset_rad=math.radians(0.1),
        max_residual_rms_m=0.001,
    )
    result = fit(0, errors, params=strict)
    assert not result.accepted
    assert result.estimate is not None  # a refusal after the fit keeps what was found
    text = " | ".join(result.reasons)
    assert "residual rms" in text and "> 1.0 mm" in text
    assert "range offset" in text and "±5 mm" in text
    assert "mount yaw offset" in text and "±0.1°" in text


def test_mismatched_arrays_are_refused_not_raised() -> None:
    result = calibrate_scanner([(np.ones(10), np.ones(9))], MOUNTS[0], DOCKED, LAUNCHER)
    assert not result.accepted
    assert "not 1-D arrays of one length" in result.reasons[0]


def test_calibrated_mount_turns_and_shifts_along_the_vehicle_axes() -> None:
    mount = MOUNTS[0]
    assert calibrated_mount(mount, 0.01) == Pose2D(5.8, 1.5, mount.yaw_rad + 0.01)
    assert calibrated_mount(mount, 0.0, 0.004) == Pose2D(5.8, 1.504, mount.yaw_rad)
    assert calibrated_mount(mount, -0.02, None) == Pose2D(5.8, 1.5, mount.yaw_rad - 0.02)


def test_a_turn_within_the_troughs_keeps_the_front_end_in_place() -> None:
    turned = DOCKED.displaced(0.0, 0.0, math.radians(0.3))
    front = turned.compose(Pose2D(6.0, 0.0, 0.0))
    assert front.x_m == pytest.approx(0.0, abs=1e-12)
    assert front.y_m == pytest.approx(0.0, abs=1e-12)
    assert DOCKED.centre == Pose2D(-6.0, 0.0, 0.0)
    assert DOCKED.displaced(0.001, -0.002, 0.0) == pytest.approx((-5.999, -0.002, 0.0))


# Property: whatever the scans hold, a result or a refusal, never an exception or a NaN.
REAL = render(MOUNTS[0], draw_scanner_errors(4, 0, True), scans=1)[0][0]
junk_beam = st.one_of(
    st.floats(-1.0, 40.0),
    st.sampled_from([0.0, math.nan, math.inf, -math.inf, 1e-300, 1e300, 0.2, 1.0]),
)


@settings(max_examples=40)
@given(
    scans=st.lists(
        st.one_of(
            # a real docked scan with some beams replaced by anything
            st.dictionaries(st.integers(0, REAL.size - 1), junk_beam, max_size=200).map(
                lambda changes: _patched(REAL, changes)
            ),
            # or anything at all, of any short length
            st.lists(junk_beam, min_size=0, max_size=60).map(
                lambda beams: np.asarray(beams, dtype=np.float64)
            ),
        ),
        min_size=0,
        max_size=3,
    ),
    mount=st.sampled_from(MOUNTS),
)
def test_any_scans_give_a_result_or_a_refusal(scans: list[FloatArray], mount: Pose2D) -> None:
    pairs = [(ranges, _angles(ranges.size)) for ranges in scans]
    result = calibrate_scanner(pairs, mount, DOCKED, LAUNCHER)
    assert isinstance(result, ScannerCalibrationResult)
    assert result.accepted == (not result.reasons)
    assert_finite(result)
    if result.accepted:
        assert result.estimate is not None


def _patched(ranges: FloatArray, changes: dict[int, float]) -> FloatArray:
    patched = ranges.copy()
    for index, value in changes.items():
        patched[index] = value
    return patched


def _angles(count: int) -> FloatArray:
    if count == ANGLES.size:
        return ANGLES
    return np.linspace(-0.75 * math.pi, 0.75 * math.pi, count)
