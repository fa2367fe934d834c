"""Fitting a pallet to outline points: poses of both kinds at several postures and
distances, the covariance against the errors (NEES over seeded draws), one face against
an L, occluded ends, clutter refused, symmetry, and never raising."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from appliance.mapping.pallet_fit import (
    PalletFitParams,
    PalletRejection,
    PalletRejectReason,
    fit_pallet,
)
from appliance.mapping.pallets import Pallet, PalletKind, posture_difference_rad

from .pallet_scenes import Rect, arc, outline, pallet_rect, polyline

EUR, JIS = PalletKind.EUR, PalletKind.JIS
SIGMA_M = 0.01
# The noise model exactly: no surface roughness, no end roughness (for the NEES tests).
EXACT = PalletFitParams(surface_sigma_m=1e-5, end_sigma_m=0.0)
# χ² with 3 degrees of freedom at 99.9 %: one pose's squared Mahalanobis error.
CHI2_3_999 = 16.27


def _error(pallet: Pallet, truth: Rect) -> np.ndarray:
    yaw = posture_difference_rad(pallet.yaw_rad, truth.yaw_rad, pallet.kind.symmetry_rad)
    return np.array([pallet.x_m - truth.x_m, pallet.y_m - truth.y_m, yaw])


def _mahalanobis2(pallet: Pallet, truth: Rect) -> float:
    error = _error(pallet, truth)
    return float(error @ np.linalg.solve(pallet.covariance, error))


def _fit(truth: Rect, seed: int, spacing_m: float = 0.02, **kwargs: object) -> Pallet:
    rng = np.random.default_rng(seed)
    points = outline([truth], 0, (0.0, 0.0), spacing_m, SIGMA_M, rng)
    result = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M, **kwargs)
    assert isinstance(result, Pallet), result
    return result


@pytest.mark.parametrize("kind", [EUR, JIS])
@pytest.mark.parametrize("yaw_deg", [0.0, 25.0, 60.0, 90.0, 140.0, -35.0])
@pytest.mark.parametrize("distance_m", [2.0, 5.0, 8.0])
def test_pose_is_recovered(kind: PalletKind, yaw_deg: float, distance_m: float) -> None:
    """1 cm range noise and a face sampled every 0.25° of azimuth (as a scanner would:
    8 mm at 2 m, 32 mm at 8 m): the corner of an L is fixed to a few mm, one face's
    position along it to its ends' spacing; 2 cm and 1° bound both with a margin, and
    the covariance explains the error (99.9 % χ² gate)."""
    truth = pallet_rect(kind.value, distance_m, 0.3 * distance_m, math.radians(yaw_deg))
    pallet = _fit(
        truth, seed=int(yaw_deg) + 180 + 7 * int(distance_m), spacing_m=0.0044 * distance_m
    )
    assert pallet.kind == kind
    error = _error(pallet, truth)
    assert math.hypot(error[0], error[1]) < 0.02
    assert abs(error[2]) < math.radians(1.0)
    assert _mahalanobis2(pallet, truth) < CHI2_3_999
    assert -kind.symmetry_rad / 2.0 <= pallet.yaw_rad < kind.symmetry_rad / 2.0


@pytest.mark.parametrize(
    ("truth", "faces"),
    [
        (pallet_rect("1200x800", 3.0, 0.5, math.radians(30.0)), "L"),
        (pallet_rect("1100x1100", 4.0, -1.0, math.radians(10.0)), "L"),
        (pallet_rect("1200x800", 3.0, 0.0, 0.0), "one face (the width)"),
        (pallet_rect("1200x800", 3.0, 0.0, math.pi / 2.0), "one face (the length)"),
        (pallet_rect("1100x1100", 3.0, 0.0, 0.0), "one face"),
    ],
)
def test_covariance_is_consistent_with_the_errors(truth: Rect, faces: str) -> None:
    """Mean NEES over 200 seeded draws: 3N times it is χ² with 3N degrees of freedom;
    the 99.9 % band for N = 200 is 3 ± 0.57. With the default roughness terms (3 mm
    surface, 10 mm ends) the covariance may only be larger: the mean stays under the
    band's top."""
    draws = 200
    exact, default = [], []
    for seed in range(draws):
        exact.append(_mahalanobis2(_fit(truth, seed, params=EXACT), truth))
        default.append(_mahalanobis2(_fit(truth, seed), truth))
    assert 2.43 < np.mean(exact) < 3.57, faces
    assert np.mean(default) < 3.57, faces


def test_one_face_is_loose_along_itself_and_looser_with_one_end() -> None:
    """With one face, the position along it rests on its ends: more uncertain than an
    L's corner, and more again when one end is hidden (EUR's length side, 1.2 m)."""
    along = np.array([0.0, 1.0])  # the faces seen whole run along y
    corner = _fit(pallet_rect("1200x800", 3.0, 0.6, math.radians(30.0)), 1)
    whole = _fit(pallet_rect("1200x800", 3.2, 0.0, math.pi / 2.0), 1)
    points = outline(
        [pallet_rect("1200x800", 3.2, 0.0, math.pi / 2.0)],
        0,
        (0.0, 0.0),
        0.02,
        SIGMA_M,
        np.random.default_rng(1),
    )
    cut = points[points[:, 1] < 0.45]  # the end at +y hidden: the larger azimuth
    half = fit_pallet(cut, (0.0, 0.0), [EUR], SIGMA_M, end_occluded=True)
    assert isinstance(half, Pallet)
    assert abs(half.y_m) < 0.02 and abs(half.x_m - 3.2) < 0.01
    variance = [along @ p.covariance[:2, :2] @ along for p in (corner, whole, half)]
    assert variance[0] < variance[1] < variance[2]


def _occluded_scene(seed: int) -> tuple[np.ndarray, Rect]:
    """A EUR pallet seen from the origin as an L (nearest corner at 24° azimuth, the long
    leg to 10°, the short one to 35°), a post hiding the long leg's far half."""
    truth = pallet_rect("1200x800", 3.0, 1.2, math.radians(-20.0))
    post = Rect(1.956, 0.416, 0.0, 0.2, 0.2)  # at 12° azimuth, hiding ~8.5-15.5°
    points = outline([truth, post], 0, (0.0, 0.0), 0.015, SIGMA_M, np.random.default_rng(seed))
    return points, truth


def test_an_occluded_end_bounds_the_length_from_below() -> None:
    points, truth = _occluded_scene(3)
    claimed_true = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M)
    assert isinstance(claimed_true, PalletRejection)
    assert claimed_true.reason == PalletRejectReason.NO_KIND
    # The hidden end: the long leg's far end, the smallest azimuth from the origin.
    pallet = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M, start_occluded=True)
    assert isinstance(pallet, Pallet) and pallet.kind == EUR
    assert _mahalanobis2(pallet, truth) < CHI2_3_999
    assert math.hypot(*_error(pallet, truth)[:2]) < 0.01


def test_the_post_as_the_point_beyond_hides_the_end() -> None:
    """The same scene with the post's nearest point given as the point beyond the
    cluster's start, for the fit to judge: the same pallet as with the flag."""
    points, _ = _occluded_scene(3)
    post = (1.856, 0.5)  # on the post's near face, at 15° azimuth: next to the cluster
    pallet = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M, beyond_xy_m=(post, None))
    flagged = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M, start_occluded=True)
    assert isinstance(pallet, Pallet) and isinstance(flagged, Pallet)
    assert (pallet.x_m, pallet.y_m, pallet.yaw_rad) == (flagged.x_m, flagged.y_m, flagged.yaw_rad)


@pytest.mark.parametrize(
    ("beyond", "expected"),
    [
        (None, "placed"),
        ((2.6, 0.4), "placed"),  # the side face, receding behind the corner: a true end
        ((3.0, 0.4), "placed"),
        ((2.4, 0.47), "ambiguous"),  # on the face's own continuation: it may go on
        ((2.0, 0.4), "ambiguous"),  # something in front of the continuation
    ],
)
def test_a_point_beyond_an_end_is_judged_against_the_face(
    beyond: tuple[float, float] | None, expected: str
) -> None:
    """EUR's 0.8 m face at x = 2.4 seen head-on. Its far side is seen edge-on, so a
    cluster of it ends at the corner whichever way it goes on: receding (a corner, a true
    end) or on (hidden, a lower bound, and 0.8 m may then be either side)."""
    truth = pallet_rect("1200x800", 3.0, 0.0, 0.0)
    points = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, np.random.default_rng(4))
    result = fit_pallet(points, (0.0, 0.0), [EUR], SIGMA_M, beyond_xy_m=(None, beyond))
    if expected == "placed":
        assert isinstance(result, Pallet) and _mahalanobis2(result, truth) < CHI2_3_999
    else:
        assert isinstance(result, PalletRejection)
        assert result.reason == PalletRejectReason.AMBIGUOUS


def test_one_face_hidden_at_both_ends_is_not_placed() -> None:
    points = outline(
        [pallet_rect("1200x800", 3.0, 0.0, math.pi / 2.0)],
        0,
        (0.0, 0.0),
        0.02,
        SIGMA_M,
        np.random.default_rng(0),
    )
    result = fit_pallet(
        points[np.abs(points[:, 1]) < 0.5], (0.0, 0.0), start_occluded=True, end_occluded=True
    )
    assert isinstance(result, PalletRejection) and result.reason == PalletRejectReason.OCCLUDED


def test_a_short_face_with_a_hidden_end_is_ambiguous_not_guessed() -> None:
    """0.7 m of a face with one end hidden may be EUR's width, EUR's length or JIS's."""
    points = outline(
        [pallet_rect("1200x800", 3.0, 0.0, math.pi / 2.0)],
        0,
        (0.0, 0.0),
        0.02,
        SIGMA_M,
        np.random.default_rng(0),
    )
    result = fit_pallet(points[points[:, 1] < 0.1], (0.0, 0.0), end_occluded=True)
    assert isinstance(result, PalletRejection) and result.reason == PalletRejectReason.AMBIGUOUS


@pytest.mark.parametrize(("length_m", "expected"), [(1.2, EUR), (0.8, EUR), (1.1, JIS)])
def test_a_face_with_true_ends_names_its_kind(length_m: float, expected: PalletKind) -> None:
    other = 0.8 if length_m == 1.2 else (1.2 if length_m == 0.8 else 1.1)
    truth = Rect(3.0, 0.0, math.pi / 2.0, length_m, other)
    pallet = _fit(truth, 5)
    assert pallet.kind == expected
    assert abs(pallet.x_m - 3.0) < 0.01 and abs(pallet.y_m) < 0.02


@pytest.mark.parametrize(
    ("points", "reasons"),
    [
        # a post, 0.1 m square: two short faces
        (
            outline(
                [Rect(3.0, 0.0, 0.4, 0.1, 0.1)], 0, (0, 0), 0.01, SIGMA_M, np.random.default_rng(0)
            ),
            {PalletRejectReason.TOO_SHORT},
        ),
        # a leg: an arc of a 6 cm radius
        (arc((2.0, 0.5), 0.06, 2.5, 12), {PalletRejectReason.TOO_SHORT}),
        # a wall, 4 m
        (polyline([(3.0, -2.0), (3.0, 2.0)], 0.02, SIGMA_M, 0), {PalletRejectReason.NO_KIND}),
        # an inside corner whose legs are EUR's sides: a shelf's bay, not a pallet
        (
            polyline([(3.0, -0.8), (3.0, 0.4), (2.2, 0.4)], 0.02, SIGMA_M, 0),
            {PalletRejectReason.NOT_CONVEX},
        ),
        # two faces of EUR's lengths at 120°
        (
            polyline([(2.5, -1.0), (3.0, 0.0), (2.5, 0.69)], 0.02, SIGMA_M, 0),
            {PalletRejectReason.NOT_RIGHT_ANGLE},
        ),
        # a drum: an arc of 0.6 m radius
        (arc((3.0, 0.0), 0.6, 2.0, 80), {PalletRejectReason.NOT_STRAIGHT}),
        # an L with a leg too long for any kind (1.6 x 0.8)
        (
            polyline([(3.631, -1.131), (2.5, 0.0), (3.066, 0.566)], 0.02, SIGMA_M, 0),
            {PalletRejectReason.NO_KIND},
        ),
    ],
    ids=["post", "leg", "wall", "inside-corner", "obtuse", "drum", "too-long"],
)
def test_clutter_is_refused(points: np.ndarray, reasons: set[PalletRejectReason]) -> None:
    result = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M)
    assert isinstance(result, PalletRejection), result
    assert result.reason in reasons, result


@pytest.mark.parametrize("yaw_deg", [12.0, 33.0, -20.0])
def test_a_square_pallet_is_known_modulo_a_quarter_turn(yaw_deg: float) -> None:
    results = [
        _fit(pallet_rect("1100x1100", 3.0, 1.0, math.radians(yaw_deg + turn)), 11)
        for turn in (0.0, 90.0, 180.0, -90.0)
    ]
    for pallet in results:
        assert -math.pi / 4.0 <= pallet.yaw_rad < math.pi / 4.0
        assert (
            abs(posture_difference_rad(pallet.yaw_rad, math.radians(yaw_deg), math.pi / 2)) < 0.02
        )
    # A rectangle is known modulo half a turn only: a quarter turn is a different pallet.
    eur = _fit(pallet_rect("1200x800", 3.0, 1.0, math.radians(yaw_deg + 90.0)), 11)
    assert abs(posture_difference_rad(eur.yaw_rad, math.radians(yaw_deg + 90.0), math.pi)) < 0.02


def test_the_answer_does_not_depend_on_the_map_origin_or_the_point_order() -> None:
    truth = pallet_rect("1200x800", 3.0, 0.8, math.radians(40.0))
    points = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, np.random.default_rng(2))
    near = fit_pallet(points, (0.0, 0.0))
    shift = np.array([4.0e4, -7.0e4])
    far = fit_pallet(points + shift, (shift[0], shift[1]))
    shuffled = fit_pallet(np.random.default_rng(0).permutation(points), (0.0, 0.0))
    assert isinstance(near, Pallet) and isinstance(far, Pallet) and isinstance(shuffled, Pallet)
    assert far.x_m - shift[0] == pytest.approx(near.x_m, abs=1e-6)
    assert far.y_m - shift[1] == pytest.approx(near.y_m, abs=1e-6)
    np.testing.assert_allclose(far.covariance, near.covariance, rtol=1e-5, atol=1e-12)
    assert (shuffled.x_m, shuffled.y_m, shuffled.yaw_rad) == pytest.approx(
        (near.x_m, near.y_m, near.yaw_rad), abs=1e-9
    )


@pytest.mark.parametrize(
    "points",
    [np.zeros((0, 2)), np.zeros((5, 2)), np.ones((20, 2)), np.zeros((20, 3)), np.zeros(40)],
    ids=["empty", "five", "coincident", "three-columns", "flat"],
)
def test_degenerate_inputs_are_rejections(points: np.ndarray) -> None:
    assert isinstance(fit_pallet(points, (0.0, 0.0)), PalletRejection)


def test_non_finite_points_are_a_rejection() -> None:
    truth = pallet_rect("1200x800", 3.0, 0.8, math.radians(40.0))
    points = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, np.random.default_rng(2))
    points[7, 1] = math.nan
    result = fit_pallet(points, (0.0, 0.0))
    assert isinstance(result, PalletRejection) and result.reason == PalletRejectReason.NON_FINITE


def _check(result: Pallet | PalletRejection) -> None:
    assert isinstance(result, Pallet | PalletRejection)
    if isinstance(result, Pallet):
        covariance = result.covariance
        assert np.isfinite(covariance).all()
        np.testing.assert_array_equal(covariance, covariance.T)
        assert (np.diag(covariance) > 0.0).all()


_floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
_coordinates = st.floats(-1e6, 1e6) | _floats


_beyond = st.none() | hnp.arrays(
    np.float64, st.tuples(st.integers(0, 4), st.just(2)), elements=_coordinates
)


@given(
    hnp.arrays(np.float64, st.tuples(st.integers(0, 60), st.just(2)), elements=_coordinates),
    st.tuples(_coordinates, _coordinates),
    _floats,
    st.booleans(),
    st.booleans(),
    st.tuples(_beyond, _beyond),
)
def test_fit_never_raises(
    points: np.ndarray,
    viewpoint: tuple[float, float],
    sigma: float,
    start_occluded: bool,
    end_occluded: bool,
    beyond: tuple[np.ndarray | None, np.ndarray | None],
) -> None:
    _check(
        fit_pallet(
            points,
            viewpoint,
            range_sigma_m=sigma,
            start_occluded=start_occluded,
            end_occluded=end_occluded,
            beyond_xy_m=beyond,
        )
    )


@given(st.integers(0, 10_000), st.floats(0.0, 0.05), st.floats(-math.pi, math.pi))
def test_fit_never_raises_on_near_pallets(seed: int, sigma: float, yaw: float) -> None:
    """Outlines that are almost pallets (any noise, any posture, a piece cut away)
    exercise the branches random arrays never reach."""
    rng = np.random.default_rng(seed)
    truth = pallet_rect(str(rng.choice(["1200x800", "1100x1100"])), 3.0, 0.5, yaw)
    points = outline([truth], 0, (0.0, 0.0), 0.03, sigma, rng)
    keep = rng.uniform(size=points.shape[0]) > rng.uniform(0.0, 0.5)
    beyond = (rng.uniform(-1.0, 4.0, (int(rng.integers(0, 3)), 2)), None)
    _check(fit_pallet(points[keep], (0.0, 0.0), range_sigma_m=max(sigma, 1e-4), beyond_xy_m=beyond))


@pytest.mark.parametrize(("fraction", "placed"), [(0.05, True), (0.3, False)])
def test_a_few_strays_behind_a_face_are_dropped(fraction: float, placed: bool) -> None:
    """A cloud's fork opening whose bin caught no deck edge shows the underside, a few
    cm behind the face: a few such points are strays, many are not a face."""
    truth = pallet_rect("1200x800", 3.0, 0.0, math.pi / 2.0)  # the 1.2 m face at x = 2.6
    rng = np.random.default_rng(8)
    points = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, rng)
    strays = rng.choice(np.arange(2, points.shape[0] - 2), int(fraction * points.shape[0]))
    points[strays, 0] += 0.04  # behind, away from the origin
    result = fit_pallet(points, (0.0, 0.0), range_sigma_m=SIGMA_M)
    if placed:
        assert isinstance(result, Pallet) and _mahalanobis2(result, truth) < CHI2_3_999
    else:
        assert isinstance(result, PalletRejection)


def test_an_edge_on_face_is_not_an_l() -> None:
    """A face whose line passes through the viewpoint shows one point: it is a stray of
    the face seen head-on, not a leg of an L (its side of the viewpoint is noise)."""
    truth = pallet_rect("1200x800", 0.0, 3.0, math.pi / 2.0)  # 0.8 m face at y = 2.4
    points = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, np.random.default_rng(9))
    points = points[points[:, 0] < 0.4 - 0.01]  # its right end short of x = 0.4
    edge_on = np.array([[0.4, 2.5], [0.4, 2.55]])  # the side face x = 0.4, seen edge-on
    shifted = np.concatenate((points, edge_on)) - (0.4, 0.0)  # the viewpoint on x = 0.4
    view = (0.0, 0.0)
    result = fit_pallet(shifted, view, [EUR], SIGMA_M)
    moved = Rect(truth.x_m - 0.4, truth.y_m, truth.yaw_rad, truth.length_m, truth.width_m)
    assert isinstance(result, Pallet) and _mahalanobis2(result, moved) < CHI2_3_999


def test_points_beyond_are_judged_together() -> None:
    """Past a hole, the face goes on: one point behind it (a glimpse) and one on it
    make the end hidden, as the one on it alone would."""
    truth = pallet_rect("1200x800", 3.0, 0.0, 0.0)
    points = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, np.random.default_rng(4))
    glimpse, on_face = (2.45, 0.41), (2.4, 0.44)
    alone = fit_pallet(points, (0.0, 0.0), [EUR], SIGMA_M, beyond_xy_m=(None, [glimpse]))
    both = fit_pallet(points, (0.0, 0.0), [EUR], SIGMA_M, beyond_xy_m=(None, [glimpse, on_face]))
    assert isinstance(alone, Pallet)
    assert isinstance(both, PalletRejection) and both.reason == PalletRejectReason.AMBIGUOUS


def test_a_smeared_face_is_read_longer_never_shorter() -> None:
    """A cloud merged from viewpoints 2 cm apart (a consumer terminal's drift) shows a
    JIS side twice, 6 cm apart along it: 1.16 m, which must not pass for EUR's 1.2 m
    length once the smear is known; and the smear never lets 0.6 m pass for 0.8 m."""
    truth = pallet_rect("1100x1100", 3.0, 0.0, 0.0)
    rng = np.random.default_rng(12)
    face = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, rng)
    ghost = outline([truth], 0, (0.0, 0.0), 0.02, SIGMA_M, rng) + np.array([0.005, 0.06])
    union = np.concatenate((face, ghost))
    smeared = PalletFitParams(smear_sigma_m=0.02)
    unaware = fit_pallet(union, (0.0, 0.0), range_sigma_m=SIGMA_M)
    aware = fit_pallet(union, (0.0, 0.0), range_sigma_m=SIGMA_M, params=smeared)
    assert isinstance(unaware, Pallet) and unaware.kind == EUR  # the trap
    assert not (isinstance(aware, Pallet) and aware.kind == EUR)
    eur = pallet_rect("1200x800", 3.0, 0.0, 0.0)  # its 0.8 m face at x = 2.4
    short = outline([eur], 0, (0.0, 0.0), 0.02, SIGMA_M, np.random.default_rng(13))
    short = short[np.abs(short[:, 1]) < 0.3]
    result = fit_pallet(short, (0.0, 0.0), range_sigma_m=SIGMA_M, params=smeared)
    assert isinstance(result, PalletRejection) and result.reason == PalletRejectReason.NO_KIND
