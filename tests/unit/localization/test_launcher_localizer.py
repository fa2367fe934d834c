"""The localizer on simulated scans: the first pose, tracking, what it refuses and gates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from appliance.localization.initial_pose import InitialPose, InitialPoseRefusal, initial_pose
from appliance.localization.launcher_localizer import (
    LauncherLocalizer,
    LocalizationStatus,
    LocalizerParams,
    ScannerSetup,
)
from appliance.localization.launcher_map import LauncherMap
from appliance.perception.features import FeatureParams, extract_features
from appliance.perception.types import ScannerModel
from appliance.sim.builders import LauncherSpec, YardSpec, launcher_site, yard_site
from appliance.sim.scanner_errors import ideal_scanner
from appliance.sim.scanner_model import beam_angles_rad, render_scan
from appliance.sim.site import Circle, Site
from drivers.geometry import Pose2D

MOUNTS = {
    "left": Pose2D(5.8, 1.5, math.radians(45.0)),
    "right": Pose2D(5.8, -1.5, math.radians(-45.0)),
}
O_F = Pose2D(5.8, 0.0, 0.0)  # midway between the scanners, in the vehicle frame
SENSOR_ANGLES = beam_angles_rad() - math.pi / 2.0
THIN = FeatureParams(scanner=ScannerModel(footprint_exit_m=0.0, footprint_divergence_rad=0.0))
SITE = launcher_site(LauncherSpec()).merged(yard_site(YardSpec(x_m=-8.0)))


def _centre(gap_m: float, y_m: float = 0.0, heading_deg: float = 0.0) -> Pose2D:
    """The vehicle centre whose front end (6 m ahead) is ``gap_m`` before the board."""
    front = Pose2D(-gap_m, y_m, math.radians(heading_deg))
    return front.compose(Pose2D(-6.0, 0.0, 0.0))


def _scans(
    site: Site, centre: Pose2D, seed: int, ideal: bool, t_s: float = 0.0
) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    errors = {"errors": ideal_scanner()} if ideal else {}
    return {
        name: render_scan(site, t_s, centre, mount, rng=rng, **errors)[0]
        for name, mount in MOUNTS.items()
    }


def _sensors() -> dict[str, Pose2D]:
    return {n: Pose2D(m.x_m - O_F.x_m, m.y_m, m.yaw_rad) for n, m in MOUNTS.items()}


def _features(site: Site, centre: Pose2D, seed: int, ideal: bool) -> dict[str, object]:
    scans = _scans(site, centre, seed, ideal)
    params = THIN if ideal else FeatureParams()
    return {n: extract_features(scans[n], SENSOR_ANGLES, _sensors()[n], params) for n in MOUNTS}


@pytest.mark.parametrize(
    ("gap", "y", "heading"), [(10.0, 0.0, 0.0), (8.0, 0.7, 4.0), (4.0, -0.4, -3.0)]
)
@pytest.mark.parametrize("ideal", [True, False])
def test_the_first_pose_is_found_from_the_whole_board(
    gap: float, y: float, heading: float, ideal: bool
) -> None:
    centre = _centre(gap, y, heading)
    truth = centre.compose(O_F)
    found = initial_pose(_features(SITE, centre, 1, ideal), _sensors(), LauncherMap())  # type: ignore[arg-type]
    assert isinstance(found, InitialPose), found
    assert found.sensors == ("left", "right")
    # the board's ends fall between beams 1.7-4.4 cm apart: the position is known to that
    tolerance_m, tolerance_deg = (0.02, 0.05) if ideal else (0.06, 0.5)
    assert math.dist(found.pose[:2], truth[:2]) < tolerance_m
    assert abs(math.degrees(found.pose.yaw_rad - truth.yaw_rad)) < tolerance_deg
    # the covariance is honest enough: the error within 4 sigma
    error = np.array(found.pose) - np.array(truth)
    assert float(error @ np.linalg.solve(found.covariance, error)) < 16.0


def test_a_person_in_front_of_the_board_is_a_stated_refusal() -> None:
    person = Site((), (Circle(-1.0, 1.2, 0.25, 0.3, "person"),))
    found = initial_pose(
        _features(SITE.merged(person), _centre(6.0), 1, False), _sensors(), LauncherMap()
    )  # type: ignore[arg-type]
    assert isinstance(found, InitialPoseRefusal)
    assert "partly hidden" in found.reason


def test_no_launcher_is_a_stated_refusal() -> None:
    walls = yard_site(YardSpec(x_m=-8.0))
    found = initial_pose(_features(walls, _centre(6.0), 1, False), _sensors(), LauncherMap())  # type: ignore[arg-type]
    assert isinstance(found, InitialPoseRefusal)
    assert "not in view" in found.reason


def _approach(
    site: Site,
    ideal: bool,
    seconds: float = 8.0,
    silence: str | None = None,
    silence_at_s: float = math.inf,
) -> tuple[LauncherLocalizer, list[float], list[LocalizationStatus]]:
    """Straight at 0.3 m/s from 8 m out, slightly off the axis, the two scanners' scans
    staggered; returns the localizer, its position errors and statuses per scan."""
    params = LocalizerParams(features=THIN) if ideal else LocalizerParams()
    localizer = LauncherLocalizer({n: ScannerSetup(m) for n, m in MOUNTS.items()}, params)
    rng = np.random.default_rng(5)
    errors_kw = {"errors": ideal_scanner()} if ideal else {}
    start = _centre(8.0, 0.2, 1.0)
    errors, statuses = [], []
    t_s = 0.0
    index = 0
    while t_s < seconds:
        name = "left" if index % 2 == 0 else "right"
        centre = start.compose(Pose2D(0.3 * t_s, 0.0, 0.0))
        if not (name == silence and t_s >= silence_at_s):
            ranges, _ = render_scan(site, t_s, centre, MOUNTS[name], rng=rng, **errors_kw)
            localizer.update(name, ranges, SENSOR_ANGLES, t_s, t_s)
        estimate = localizer.estimate(t_s)
        statuses.append(estimate.status)
        if estimate.centre_pose is not None:
            errors.append(math.dist(estimate.centre_pose[:2], centre[:2]))
        t_s += 0.02
        index += 1
    return localizer, errors, statuses


def test_tracking_an_approach_with_the_ideal_scanner_is_millimetre_exact() -> None:
    localizer, errors, statuses = _approach(SITE, ideal=True)
    assert statuses[-1] is LocalizationStatus.OK
    assert max(errors[-50:]) < 0.005
    assert localizer.ekf.accepted["cylinder"] > 100 and localizer.ekf.accepted["board"] > 100


def test_tracking_an_approach_with_realistic_scanners_stays_within_centimetres() -> None:
    _, errors, statuses = _approach(SITE, ideal=False)
    assert statuses[-1] is LocalizationStatus.OK
    assert float(np.percentile(errors[-100:], 95)) < 0.03


@pytest.mark.parametrize(
    ("clutter", "radius_m"), [("post", 0.15), ("person", 0.25)], ids=["post", "person"]
)
@pytest.mark.parametrize("offset_m", [0.45, 0.7, 1.2])
def test_a_false_cylinder_or_a_person_beside_a_landmark_is_kept_out(
    clutter: str, radius_m: float, offset_m: float
) -> None:
    """A post of the landmark's own radius, or a person, beside the left cylinder (its
    centre ``offset_m`` further out): perception cannot tell a post from the landmark,
    so what keeps it out is the region of interest, the isolation check or the χ² gate;
    whichever it is, it must be counted, and the pose must not be pulled."""
    thing = Site((), (Circle(-0.5, 2.5 + offset_m, radius_m, 0.9, clutter),))
    localizer, errors, statuses = _approach(SITE.merged(thing), ideal=True)
    clear, _, _ = _approach(SITE, ideal=True)

    def kept_out(run: LauncherLocalizer) -> int:
        return (
            run.ekf.rejected["cylinder"]
            + run.feature_rejections["circle.not_isolated"]
            + run.feature_rejections["circle.too_wide"]
            + run.feature_rejections["circle.too_narrow"]
        )

    if offset_m - radius_m < LocalizerParams().cylinder_roi_m:  # else outside every region
        assert kept_out(localizer) > kept_out(clear)
    assert max(errors[-50:]) < 0.005
    # The landmark itself stays in use: only the clutter is kept out. (This once
    # expected `degraded` at 0.45 m, which came from thin-ray arcs of the landmark
    # itself refused as too narrow, a fault the clear site showed too.)
    assert statuses[-1] is LocalizationStatus.OK


def test_a_scanner_that_goes_silent_degrades_the_estimate() -> None:
    _, _, statuses = _approach(SITE, ideal=True, silence="right", silence_at_s=4.0)
    assert LocalizationStatus.OK in statuses[:150]
    assert statuses[-1] is LocalizationStatus.DEGRADED


def test_a_stale_scan_is_never_used() -> None:
    localizer = LauncherLocalizer({n: ScannerSetup(m) for n, m in MOUNTS.items()})
    scans = _scans(SITE, _centre(6.0), 1, False)
    localizer.update("left", scans["left"], SENSOR_ANGLES, t_s=0.0, now_s=0.5)
    assert localizer.stale_scans == 1
    assert localizer.last_features == {}
    assert localizer.estimate(0.5).status is LocalizationStatus.LOST


def test_a_map_that_does_not_match_the_launcher_degrades_the_estimate() -> None:
    """The map puts the left cylinder 0.3 m from where it stands: the filter rejects it
    again and again (or is pulled by it), and the status must say so rather than `ok`."""
    site = launcher_site(LauncherSpec(cylinder_lateral_m=2.5)).merged(yard_site(YardSpec(x_m=-8.0)))
    params = LocalizerParams(features=THIN, launcher=LauncherMap(cylinder_lateral_m=2.8))
    localizer = LauncherLocalizer({n: ScannerSetup(m) for n, m in MOUNTS.items()}, params)
    rng = np.random.default_rng(5)
    centre = _centre(6.0, 0.1, 0.5)
    statuses = []
    for k in range(150):
        t_s = k * 0.02
        name = "left" if k % 2 == 0 else "right"
        ranges, _ = render_scan(site, t_s, centre, MOUNTS[name], rng=rng, errors=ideal_scanner())
        localizer.update(name, ranges, SENSOR_ANGLES, t_s, t_s)
        statuses.append(localizer.estimate(t_s))
    last = statuses[-1]
    assert last.status is not LocalizationStatus.OK, last
    assert "cylinder_left not seen where the map puts it" in last.reason


def test_the_estimate_in_floats_is_the_plain_compounding() -> None:
    """`estimate` works its figures out in floats: the position σ is the largest
    eigenvalue's root (numpy's ``eigvalsh``), the centre is O_f ⊕ (−origin) with its
    covariance through the compounding's Jacobian (``compound``), to rounding."""
    from appliance.localization.compound import compound, compound_jacobians

    localizer, _, _ = _approach(SITE, ideal=False, seconds=2.0)
    estimate = localizer.estimate(2.0)
    assert estimate.pose is not None and estimate.covariance is not None
    assert estimate.centre_pose is not None and estimate.centre_covariance is not None
    state, cov = np.array(estimate.pose), estimate.covariance
    back = np.array([-localizer.origin_in_vehicle.x_m, -localizer.origin_in_vehicle.y_m, 0.0])
    j_pose, _ = compound_jacobians(state, back)
    assert np.array(estimate.centre_pose) == pytest.approx(compound(state, back), abs=1e-12)
    expected = j_pose @ cov @ j_pose.T
    assert np.abs(estimate.centre_covariance - expected).max() <= 1e-12 * np.abs(expected).max()
    sigma_m = math.sqrt(float(np.max(np.linalg.eigvalsh(cov[:2, :2]))))
    quality = round(100.0 * max(0.0, min(1.0, 1.0 - sigma_m / localizer.params.lost_sigma_m)))
    assert estimate.quality == quality
