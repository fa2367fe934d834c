"""The LMS111 error model: every effect against the ideal scanner, and against a reference.

The reference (`_reference_echo`) is written from the model's figures alone: one beam at a
time, a plain-Python ray-shape intersection per sub-ray, and a loop over the returns. The
vectorised renderer must agree with it wherever it casts sub-rays.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.sim import (
    LMS111_NOISE_SIGMA_M,
    Circle,
    Pose2D,
    ScannerErrors,
    Segment,
    Site,
    beam_angles_rad,
    draw_scanner_errors,
    ideal_scanner,
    load_site,
    render_scan,
    scanner_pose,
)
from appliance.sim.raycast import nearest_hits
from appliance.sim.scanner_errors import (
    MAX_MOUNT_OFFSET_M,
    MAX_MOUNT_YAW_RAD,
    MAX_RANGE_OFFSET_M,
    MAX_RANGE_SCALE,
    BeamFootprint,
    RemissionLimit,
    first_strong_echo,
)
from appliance.sim.scanner_model import RayCache, footprint_beams

AHEAD = 540  # the 90° beam of a 1081-beam scan: along the scanner's x
STEP_025 = math.radians(0.25)
STEP_050 = math.radians(0.5)
IDEAL = ideal_scanner()
QUIET = ScannerErrors(noise_sigma_m=0.0)  # the footprint and the remission limit only
ORIGIN = (0.0, 0.0, 0.0)

# The model's figures, restated here so the reference does not read them from the code.
PULSE_MERGE_M = 0.6
MIN_ENERGY = 0.10 / 18.0**2  # 10 % remission at 18 m, energy ~ remission / r^2
SUB_RAYS = 7


def _scan(
    site: Site,
    errors: ScannerErrors,
    vehicle: tuple[float, float, float] = ORIGIN,
    mount: tuple[float, float, float] = ORIGIN,
    *,
    step_rad: float = STEP_025,
    seed: int = 0,
    t_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    return render_scan(
        site, t_s, vehicle, mount, rng=np.random.default_rng(seed), errors=errors, step_rad=step_rad
    )


def _board_before_wall(wall_x_m: float, board_remission: float = 0.9) -> Site:
    """A board at x = 5 m whose right end is just left of the 90° beam, a wall behind."""
    return Site(
        (
            Segment(5.0, 0.01, 5.0, 3.0, board_remission, "board"),
            Segment(wall_x_m, -10.0, wall_x_m, 10.0, 0.5, "wall"),
        )
    )


# ---- the ideal scanner ---------------------------------------------------------------


def test_the_ideal_scanner_measures_exact_geometry_and_draws_no_noise() -> None:
    site = Site(
        (Segment(10.0, -30.0, 10.0, 30.0, 0.02, "black wall at 10 m"),),
        (Circle(4.0, 2.0, 0.3, 0.9, "post"),),
    )
    rng = np.random.default_rng(0)
    state = rng.bit_generator.state
    ranges, remission = render_scan(site, 0.0, ORIGIN, ORIGIN, rng=rng, errors=IDEAL)
    assert rng.bit_generator.state == state
    world = beam_angles_rad() - math.pi / 2.0
    hits = nearest_hits(
        0.0, 0.0, world, site.shapes_at(0.0).segments, site.shapes_at(0.0).circles, 20.0
    )
    np.testing.assert_array_equal(ranges, hits.ranges_m)
    assert ranges[AHEAD] == 10.0  # black, but the ideal scanner has no remission limit
    on_wall = (np.abs(world) < 1.0) & (remission == 0.02)
    np.testing.assert_allclose(ranges[on_wall], 10.0 / np.cos(world[on_wall]), rtol=1e-12)
    assert set(np.unique(remission)) == {0.0, 0.02, 0.9}


def test_an_ideal_scanner_cannot_have_errors() -> None:
    assert draw_scanner_errors(5, 0, realistic=False) == IDEAL
    assert IDEAL.true_mount((1.0, 2.0, 0.5)) == Pose2D(1.0, 2.0, 0.5)
    for change in (
        {"range_offset_m": 0.01},
        {"noise_sigma_m": 0.012},
        {"footprint": BeamFootprint()},
        {"remission_limit": RemissionLimit()},
        {"mount_error": Pose2D(0.001, 0.0, 0.0)},
    ):
        with pytest.raises(ValueError, match="ideal"):
            dataclasses.replace(IDEAL, **change)


# ---- drawn errors: reproducible, per scanner, of the stated size ---------------------


def test_drawn_errors_are_reproducible_and_differ_per_scanner_and_seed() -> None:
    first = draw_scanner_errors(7, 0, realistic=True)
    assert draw_scanner_errors(7, 0, realistic=True) == first
    others = [draw_scanner_errors(7, 1, True), draw_scanner_errors(8, 0, True)]
    for other in others:
        assert other.range_offset_m != first.range_offset_m
        assert other.mount_error != first.mount_error
    assert first.noise_sigma_m == LMS111_NOISE_SIGMA_M
    assert first.footprint == BeamFootprint() and first.remission_limit == RemissionLimit()


def test_drawn_errors_stay_within_the_data_sheet_and_the_mount_tolerance() -> None:
    drawn = [draw_scanner_errors(seed, index, True) for seed in range(150) for index in (0, 1)]
    offset = np.array([e.range_offset_m for e in drawn])
    scale = np.array([e.range_scale for e in drawn])
    mount = np.array([e.mount_error for e in drawn])
    # Systematic error: never beyond the data sheet's 30 mm anywhere up to 20 m.
    assert np.all(np.abs(offset) + np.abs(scale) * 20.0 <= 0.030 + 1e-12)
    assert np.all(np.abs(offset) <= MAX_RANGE_OFFSET_M) and np.all(np.abs(scale) <= MAX_RANGE_SCALE)
    # Mount: a few millimetres and a few tenths of a degree, uniform in the tolerance.
    assert np.all(np.abs(mount[:, :2]) <= MAX_MOUNT_OFFSET_M)
    assert np.all(np.abs(mount[:, 2]) <= math.radians(0.3))
    for values, bound in (
        (offset, MAX_RANGE_OFFSET_M),
        (scale, MAX_RANGE_SCALE),
        (mount[:, 0], MAX_MOUNT_OFFSET_M),
        (mount[:, 1], MAX_MOUNT_OFFSET_M),
        (mount[:, 2], MAX_MOUNT_YAW_RAD),
    ):
        assert values.std() == pytest.approx(bound / math.sqrt(3.0), rel=0.15)
        assert abs(values.mean()) < 0.15 * bound


def test_noise_is_twelve_millimetres_around_a_fixed_per_scanner_offset() -> None:
    """Beams on a white wall 10 m ahead, far from any edge, over many scans."""
    site = Site((Segment(10.0, -5.0, 10.0, 5.0, 0.9, "wall"),))
    board = slice(AHEAD - 40, AHEAD + 41)
    means = []
    for index in (0, 1):
        errors = draw_scanner_errors(3, index, realistic=True)
        truth, _ = _scan(site, IDEAL, mount=errors.true_mount(ORIGIN))
        expected = errors.range_offset_m + errors.range_scale * truth[board]
        batches = []
        for batch in range(2):  # the offset stays the same from scan to scan
            rng = np.random.default_rng(100 * index + batch)
            error = np.array(
                [
                    render_scan(site, 0.0, ORIGIN, ORIGIN, rng=rng, errors=errors)[0][board]
                    - truth[board]
                    - expected
                    for _ in range(150)
                ]
            )
            assert error.std() == pytest.approx(LMS111_NOISE_SIGMA_M, rel=0.03)
            assert abs(error.mean()) < 4 * LMS111_NOISE_SIGMA_M / math.sqrt(error.size)
            batches.append(error.mean() + expected.mean())
        assert batches[0] == pytest.approx(batches[1], abs=0.0005)
        means.append(batches[0])
    assert abs(means[0] - means[1]) > 0.001  # two scanners, two offsets


# ---- the footprint: mixed ranges at edges --------------------------------------------


def test_the_footprint_is_the_data_sheets_and_its_profile_gaussian() -> None:
    footprint = BeamFootprint()
    assert footprint.diameter_m(10.0) == pytest.approx(0.158)  # 8 mm + 15 mrad x 10 m
    # Seen from the scanner, half of it: 7.5 mrad plus the exit aperture's 4 mm.
    assert footprint.half_angle_rad(np.array([10.0]))[0] == pytest.approx(0.0075 + 0.0004)
    offsets, weights = footprint.profile
    assert offsets.size == SUB_RAYS and offsets[SUB_RAYS // 2] == 0.0
    assert weights.sum() == pytest.approx(1.0) and weights.argmax() == SUB_RAYS // 2
    np.testing.assert_allclose(weights / weights.max(), np.exp(-2.0 * offsets**2))


@pytest.mark.parametrize("step_rad", [STEP_025, STEP_050], ids=["0.25deg", "0.5deg"])
def test_a_beam_across_a_board_edge_merges_with_a_wall_close_behind(step_rad: float) -> None:
    site = _board_before_wall(5.4)  # 0.4 m behind: within one pulse length
    ahead = round(math.radians(135.0) / step_rad)  # the 90° beam
    window = slice(ahead - 6, ahead + 7)
    ideal, _ = _scan(site, IDEAL, step_rad=step_rad)
    mixed, remission = _scan(site, QUIET, step_rad=step_rad)
    # The ideal scanner jumps from the wall to the board; the real one passes between.
    assert not np.any((ideal[window] > 5.02) & (ideal[window] < 5.38))
    between = (mixed[window] > 5.02) & (mixed[window] < 5.38)
    assert between.any()
    # Mixed echoes report less than either surface's full remission would at that range.
    assert np.all(remission[window][between] < 0.9)
    assert np.all((mixed[window] > 4.999) & (mixed[window] < ideal[window].max() + 1e-9))


@pytest.mark.parametrize("step_rad", [STEP_025, STEP_050], ids=["0.25deg", "0.5deg"])
def test_a_beam_across_a_board_edge_sees_the_board_when_the_wall_is_far(step_rad: float) -> None:
    site = _board_before_wall(9.0)  # 4 m behind: two echoes, the first is taken
    ideal, _ = _scan(site, IDEAL, step_rad=step_rad)
    real, _ = _scan(site, QUIET, step_rad=step_rad)
    ahead = round(math.radians(135.0) / step_rad)  # the 90° beam
    window = slice(ahead - 8, ahead + 9)  # the board's right end, and the wall behind it
    secant = 1.0 / np.cos(beam_angles_rad(step_rad=step_rad)[window] - math.pi / 2.0)
    on_board = np.abs(real[window] - 5.0 * secant) < 0.005
    on_wall = np.abs(real[window] - 9.0 * secant) < 0.005
    assert np.all(on_board | on_wall)  # never a range between the two
    # The board looks wider: beams partly on it report it, not the wall behind.
    assert np.count_nonzero(on_board) > np.count_nonzero(ideal[window] < 6.0)


def test_too_little_of_a_dark_board_in_the_beam_gives_no_echo() -> None:
    """A dark board at 12 m (5 % remission, just above the 4.4 % needed there) with
    nothing behind it: beams only partly on it return nothing, the ideal scanner 12 m."""
    site = Site((Segment(12.0, 0.01, 12.0, 3.0, 0.05, "dark board"),))
    ideal, _ = _scan(site, IDEAL)
    real, _ = _scan(site, QUIET)
    assert real[AHEAD + 20] == pytest.approx(12.0 / math.cos(math.radians(5.0)), abs=1e-3)
    seen, ideal_seen = np.flatnonzero(real), np.flatnonzero(ideal)
    lost = sorted(set(ideal_seen) - set(seen))
    assert set(seen) <= set(ideal_seen) and lost  # fewer beams see it, none sees more
    # The ones lost are at its ends, where part of the footprint misses the board.
    ends = (ideal_seen[0], ideal_seen[-1])
    assert all(min(abs(beam - end) for end in ends) <= 2 for beam in lost)
    assert ideal_seen[0] in lost and ideal_seen[-1] in lost


# ---- remission limit ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("remission", "seen_m", "unseen_m"),
    [(0.10, 17.0, 19.0), (0.05, 12.0, 13.5), (0.9, 19.8, None), (5.0, 19.8, None)],
)
def test_a_target_beyond_the_range_its_remission_allows_gives_no_echo(
    remission: float, seen_m: float, unseen_m: float | None
) -> None:
    """Needed: 0.10 x (r / 18 m)^2, so 10 % reaches 18 m and 5 % 12.7 m; 20 m at most."""
    limit = RemissionLimit()
    assert limit.min_remission(18.0) == pytest.approx(0.10)
    assert limit.max_range_m(0.05) == pytest.approx(18.0 * math.sqrt(0.5))
    for distance_m, expect_echo in ((seen_m, True), (unseen_m, False)):
        if distance_m is None:
            continue
        site = Site((Segment(distance_m, -8.0, distance_m, 8.0, remission, "target"),))
        real, reported = _scan(site, QUIET)
        ideal, _ = _scan(site, IDEAL)
        assert ideal[AHEAD] == pytest.approx(distance_m)
        assert bool(real[AHEAD] > 0.0) is expect_echo
        if expect_echo:
            assert real[AHEAD] == pytest.approx(distance_m) and reported[AHEAD] == remission


# ---- mount errors ----------------------------------------------------------------------


def test_the_scan_is_taken_from_the_true_mount() -> None:
    """A post appears where the true mount predicts, not where the configured one does."""
    post = Circle(8.0, 1.0, 0.15, 0.9, "post")
    site = Site((), (post,))
    vehicle, configured = (-2.0, 0.5, math.radians(10.0)), (1.5, -0.4, math.radians(-20.0))
    errors = ScannerErrors(
        noise_sigma_m=0.0,
        footprint=None,
        remission_limit=None,
        mount_error=Pose2D(0.2, -0.15, math.radians(3.0)),
    )
    ranges, _ = _scan(site, errors, vehicle, configured)
    true_pose = scanner_pose(vehicle, errors.true_mount(configured))
    said_pose = scanner_pose(vehicle, configured)

    def predicted(pose: Pose2D) -> tuple[int, float]:
        bearing = math.atan2(post.cy_m - pose.y_m, post.cx_m - pose.x_m) - pose.yaw_rad
        beam = round((math.degrees(bearing) + 90.0 + 45.0) / 0.25)
        return beam, math.hypot(post.cx_m - pose.x_m, post.cy_m - pose.y_m) - post.radius_m

    nearest = int(np.argmin(np.where(ranges > 0.0, ranges, np.inf)))
    true_beam, true_range_m = predicted(true_pose)
    said_beam, _ = predicted(said_pose)
    assert abs(nearest - true_beam) <= 1 and abs(nearest - said_beam) > 5
    assert ranges[nearest] == pytest.approx(true_range_m, abs=0.002)


def test_a_drawn_mount_error_moves_the_scan_exactly_as_the_true_mount_says() -> None:
    site = load_site("launcher")
    vehicle, configured = (-10.0, 0.3, math.radians(2.0)), (2.6, 1.1, math.radians(45.0))
    drawn = draw_scanner_errors(11, 1, realistic=True)
    geometry_only = dataclasses.replace(
        drawn, range_offset_m=0.0, range_scale=0.0, noise_sigma_m=0.0, footprint=None
    )
    geometry_only = dataclasses.replace(geometry_only, remission_limit=None)
    seen, _ = _scan(site, geometry_only, vehicle, configured, t_s=1.0)
    expected, _ = _scan(site, IDEAL, vehicle, drawn.true_mount(configured), t_s=1.0)
    np.testing.assert_array_equal(seen, expected)
    configured_view, _ = _scan(site, IDEAL, vehicle, configured, t_s=1.0)
    assert np.abs(seen - configured_view).max() > 0.01


# ---- the cache ---------------------------------------------------------------------------


@pytest.mark.parametrize("realistic", [True, False], ids=["realistic", "ideal"])
def test_the_ray_cache_changes_nothing_with_drawn_errors(realistic: bool) -> None:
    site = load_site("launcher")
    errors = draw_scanner_errors(2, 0, realistic=realistic)
    mount = (2.6, 1.1, math.radians(45.0))
    cache = RayCache()
    for step in range(8):
        vehicle = (-12.0 + 0.5 * (step // 2), 0.4, math.radians(3.0))  # moves every 2nd scan
        t_s = 0.5 * step
        kept = render_scan(
            site, t_s, vehicle, mount, rng=np.random.default_rng(step), errors=errors, cache=cache
        )
        fresh = render_scan(
            site, t_s, vehicle, mount, rng=np.random.default_rng(step), errors=errors
        )
        np.testing.assert_allclose(kept[0], fresh[0], rtol=0.0, atol=1e-9)
        np.testing.assert_array_equal(kept[0] > 0.0, fresh[0] > 0.0)
        np.testing.assert_allclose(kept[1], fresh[1], rtol=1e-12, atol=0.0)
    assert (cache.misses, cache.hits) == (4, 4)


# ---- against a per-beam reference ------------------------------------------------------


def _ray_hit(
    x_m: float, y_m: float, angle_rad: float, shapes: object, max_range_m: float = 20.0
) -> tuple[float, float]:
    """(range, remission) of the nearest surface along one ray, (0, 0) if none in range."""
    segments, segment_remission, circles, circle_remission, _ = shapes  # type: ignore[misc]
    dx, dy = math.cos(angle_rad), math.sin(angle_rad)
    best = (math.inf, 0.0)
    for (x0, y0, x1, y1), remission in zip(segments, segment_remission, strict=True):
        ex, ey, wx, wy = x1 - x0, y1 - y0, x0 - x_m, y0 - y_m
        denominator = dx * ey - dy * ex
        if abs(denominator) < 1e-12:
            continue
        t = (wx * ey - wy * ex) / denominator
        s = (wx * dy - wy * dx) / denominator
        if t >= 0.0 and 0.0 <= s <= 1.0 and t < best[0]:
            best = (t, float(remission))
    for (cx, cy, radius), remission in zip(circles, circle_remission, strict=True):
        mx, my = x_m - cx, y_m - cy
        b = mx * dx + my * dy
        discriminant = b * b - (mx * mx + my * my - radius * radius)
        if discriminant < 0.0:
            continue
        t = -b - math.sqrt(discriminant)
        if t >= 0.0 and t < best[0]:
            best = (t, float(remission))
    return best if 0.0 < best[0] <= max_range_m else (0.0, 0.0)


def _first_strong_echo_reference(
    returns: list[tuple[float, float]], min_energy: float
) -> tuple[float, float]:
    """(range, energy) of the first strong echo from (range, energy) returns, one by one."""
    echoes: list[list[tuple[float, float]]] = []
    for range_m, energy in sorted(r for r in returns if r[0] > 0.0):
        if echoes and range_m - echoes[-1][-1][0] <= PULSE_MERGE_M:
            echoes[-1].append((range_m, energy))
        else:
            echoes.append([(range_m, energy)])
    for echo in echoes:
        total = sum(e for _, e in echo)
        if (total >= min_energy) if min_energy > 0.0 else (total > 0.0):
            return sum(r * e for r, e in echo) / total, total
    return 0.0, 0.0


def _reference_echo(pose: Pose2D, angle_rad: float, shapes: object) -> tuple[float, float]:
    """One beam of a quiet LMS111: its footprint's sub-rays and what the receiver makes of them."""
    centre_m, _ = _ray_hit(pose.x_m, pose.y_m, angle_rad, shapes)
    half_rad = 0.015 / 2.0 + 0.008 / 2.0 / max(centre_m or 20.0, 0.05)
    offsets = [(2 * k + 1) / SUB_RAYS - 1.0 for k in range(SUB_RAYS)]
    profile = [math.exp(-2.0 * u * u) for u in offsets]
    returns = []
    for u, weight in zip(offsets, profile, strict=True):
        range_m, remission = _ray_hit(pose.x_m, pose.y_m, angle_rad + u * half_rad, shapes)
        if range_m > 0.0:
            returns.append((range_m, weight / sum(profile) * remission / range_m**2))
    range_m, energy = _first_strong_echo_reference(returns, MIN_ENERGY)
    return range_m, energy * range_m**2


@pytest.mark.parametrize(
    ("vehicle", "t_s"),
    [((-10.0, 0.3, math.radians(2.0)), 0.0), ((-4.0, -1.0, math.radians(-15.0)), 7.0)],
)
def test_the_vectorised_footprints_match_a_per_beam_reference(
    vehicle: tuple[float, float, float], t_s: float
) -> None:
    site = load_site("launcher")
    mount = (2.6, 1.1, math.radians(45.0))
    ranges, remission = _scan(site, QUIET, vehicle, mount, t_s=t_s)
    pose = scanner_pose(vehicle, mount)
    shapes = site.shapes_at(t_s)
    world = beam_angles_rad() + pose.yaw_rad - math.pi / 2.0
    hits = nearest_hits(pose.x_m, pose.y_m, world, shapes.segments, shapes.circles, 20.0)
    cast_again = footprint_beams(hits, len(shapes.segments), BeamFootprint(), STEP_025, 20.0)
    assert cast_again.size > 20
    mixed = 0
    for beam in cast_again:
        expected_m, expected_remission = _reference_echo(pose, float(world[beam]), shapes)
        assert ranges[beam] == pytest.approx(expected_m, abs=1e-9)
        assert remission[beam] == pytest.approx(expected_remission, rel=1e-9, abs=1e-12)
        mixed += abs(expected_m - hits.ranges_m[beam]) > 0.005
    assert mixed > 0  # the reference does mix somewhere: the comparison is not vacuous
    # Elsewhere the central ray stands for the footprint: within millimetres of it.
    for beam in range(0, world.size, 37):
        expected_m, _ = _reference_echo(pose, float(world[beam]), shapes)
        assert ranges[beam] == pytest.approx(expected_m, abs=0.003)


returns_strategy = st.lists(
    st.tuples(
        st.one_of(st.just(0.0), st.floats(0.1, 20.0)),
        st.floats(0.0, 2e-3),
    ),
    min_size=1,
    max_size=7,
)


@settings(max_examples=60, derandomize=True)
@given(beams=st.lists(returns_strategy, min_size=1, max_size=4), strong=st.booleans())
def test_first_strong_echo_matches_the_loop(
    beams: list[list[tuple[float, float]]], strong: bool
) -> None:
    width = max(len(b) for b in beams)
    ranges_m = np.zeros((len(beams), width))
    energy = np.zeros((len(beams), width))
    for row, returns in enumerate(beams):
        for column, (range_m, e) in enumerate(returns):
            ranges_m[row, column], energy[row, column] = range_m, e
    min_energy = MIN_ENERGY if strong else 0.0
    found_m, found_energy = first_strong_echo(ranges_m, energy, PULSE_MERGE_M, min_energy)
    for row, returns in enumerate(beams):
        expected_m, expected_energy = _first_strong_echo_reference(returns, min_energy)
        assert found_m[row] == pytest.approx(expected_m, rel=1e-12, abs=1e-12)
        assert found_energy[row] == pytest.approx(expected_energy, rel=1e-12, abs=1e-15)
