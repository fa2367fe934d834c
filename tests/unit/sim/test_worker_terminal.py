"""The worker's simulated 3D terminal: geometry of its scans, and its error model.

The geometry is checked against a point-to-surface distance written here from the
`Site` itself (signed distance functions of boxes, capped cylinders and wall
rectangles), not from `raycast3d`'s arrays, so a slip in how the world is built from a
site is caught too. Grids are coarse (a few thousand rays) to keep the file fast.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.mapping.pallets import inverse_pose
from appliance.sim.builders import (
    PalletAreaSpec,
    PostSpec,
    YardSpec,
    clutter_site,
    pallet_area_site,
    yard_site,
)
from appliance.sim.raycast3d import (
    FLOOR_INDEX,
    WorldParams,
    cast_rays_3d,
    pallet_boxes,
    site_world,
)
from appliance.sim.site import Site, SitePallet, Walker
from appliance.sim.site_file import load_site
from appliance.sim.terminal_errors import draw_walk
from appliance.sim.worker_route import walk_around
from appliance.sim.worker_terminal import (
    CONSUMER,
    IDEAL,
    WORSE,
    TerminalScanParams,
    scan_directions,
    scan_viewpoint,
    survey,
    survey_objects,
    transform_points,
)
from drivers.geometry import Pose2D

COARSE = TerminalScanParams(
    azimuth_step_rad=math.radians(3.0), elevation_step_rad=math.radians(3.0), range_sigma_m=0.0
)
NOISY = TerminalScanParams(
    azimuth_step_rad=math.radians(3.0), elevation_step_rad=math.radians(3.0), range_sigma_m=0.01
)
VERY_COARSE = TerminalScanParams(
    azimuth_step_rad=math.radians(15.0), elevation_step_rad=math.radians(10.0)
)
MARKER = Pose2D(1.0, -1.0, 0.3)
WALL_HEIGHT_M, POST_HEIGHT_M = 2.5, 2.0


def _storage_site() -> Site:
    """Pallets with cargo in a jittered grid, a yard wall within reach, a post."""
    area = pallet_area_site(
        PalletAreaSpec(
            name="area",
            x_m=1.0,
            y_m=0.5,
            yaw_deg=20.0,
            rows=2,
            columns=2,
            cargo_height_m=0.8,
            jitter_m=0.05,
            jitter_deg=4.0,
            seed=3,
        )
    )
    yard = yard_site(YardSpec(x_m=2.0, y_m=1.0, length_m=9.0, width_m=8.0))
    post = clutter_site(posts=(PostSpec(x_m=-1.0, y_m=3.0, radius_m=0.15, name="post"),))
    return yard.merged(area).merged(post)


def _box_sdf(local: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Signed distance to an axis-aligned box centred at 0 (negative inside)."""
    d = np.abs(local) - half
    outside: np.ndarray = np.linalg.norm(np.maximum(d, 0.0), axis=1)
    return outside + np.minimum(d.max(axis=1), 0.0)


def _solid_sdfs(site: Site, xyz: np.ndarray) -> list[np.ndarray]:
    """Signed distances (negative inside) of every point to each solid of ``site``: the
    ground under the floor, pallet and cargo boxes, posts (capped cylinders)."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    sdfs = [z]
    for pallet in site.pallets:
        solids = [(0.0, pallet.height_m)]
        if pallet.cargo_height_m > 0:
            solids.append((pallet.height_m, pallet.height_m + pallet.cargo_height_m))
        c, s = math.cos(pallet.pose.yaw_rad), math.sin(pallet.pose.yaw_rad)
        rx, ry = x - pallet.pose.x_m, y - pallet.pose.y_m
        for bottom, top in solids:
            local = np.column_stack([c * rx + s * ry, -s * rx + c * ry, z - (bottom + top) / 2])
            half = np.array([pallet.length_m / 2, pallet.width_m / 2, (top - bottom) / 2])
            sdfs.append(_box_sdf(local, half))
    for circle in site.circles:
        d = np.column_stack(
            [
                np.hypot(x - circle.cx_m, y - circle.cy_m) - circle.radius_m,
                np.abs(z - POST_HEIGHT_M / 2) - POST_HEIGHT_M / 2,
            ]
        )
        sdfs.append(np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0))
    return sdfs


def _surface_distance_m(site: Site, xyz: np.ndarray) -> np.ndarray:
    """Each point's distance to the nearest surface of ``site`` in 3D, from the site's
    own shapes: floor, pallet and cargo boxes, walls (non-pallet segments), posts."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    best = np.min(np.abs(np.stack(_solid_sdfs(site, xyz))), axis=0)
    pallet_sides = tuple(f"{p.name}." for p in site.pallets)
    for seg in site.segments:
        if seg.name.startswith(pallet_sides):
            continue
        ex, ey = seg.x1_m - seg.x0_m, seg.y1_m - seg.y0_m
        u = np.clip(((x - seg.x0_m) * ex + (y - seg.y0_m) * ey) / (ex * ex + ey * ey), 0, 1)
        plan = np.hypot(seg.x0_m + u * ex - x, seg.y0_m + u * ey - y)
        above = np.maximum(np.maximum(-z, z - WALL_HEIGHT_M), 0.0)
        best = np.minimum(best, np.hypot(plan, above))
    result: np.ndarray = best
    return result


def test_every_point_lies_on_a_surface_of_the_site() -> None:
    site = _storage_site()
    stops = walk_around(site)[:3]
    exact = survey(site, MARKER, stops, rng=np.random.default_rng(0), errors=IDEAL, params=COARSE)
    in_site = transform_points(MARKER, exact.xyz_m)  # IDEAL: W is the marker's frame
    assert len(in_site) > 1000
    assert _surface_distance_m(site, in_site).max() < 1e-6
    # The yard's walls stop every ray: nothing is seen beyond them.
    assert (np.abs(in_site[:, 0] - 2.0) <= 4.5 + 1e-9).all()
    assert (np.abs(in_site[:, 1] - 1.0) <= 4.0 + 1e-9).all()
    noisy = survey(site, MARKER, stops, rng=np.random.default_rng(0), errors=IDEAL, params=NOISY)
    assert _surface_distance_m(site, transform_points(MARKER, noisy.xyz_m)).max() < 5 * 0.01
    names = {exact.surface_names[i] for i in exact.surface_index}
    assert {"floor", "area.r0c0.cargo", "yard.wall_north"} <= names


def test_rays_pass_through_no_solid_before_their_hit() -> None:
    """Nearest hit: samples every 15 mm along each ray up to its hit (or the range
    limit for a miss) are outside every solid."""
    site = _storage_site()
    world = site_world(site)
    params = TerminalScanParams(
        azimuth_step_rad=math.radians(5.0), elevation_step_rad=math.radians(5.0)
    )
    for stop in [walk_around(site)[0], Pose2D(-1.5, 3.2, 0.0)]:
        origin = np.array([stop.x_m, stop.y_m, 1.2])
        directions = scan_directions(stop.yaw_rad, params)
        hits = cast_rays_3d(world, origin, directions, params.max_range_m)
        assert np.isfinite(hits.range_m).sum() > 0.5 * len(directions)
        reach = np.minimum(hits.range_m, params.max_range_m) - 0.005
        steps = np.arange(0.0, params.max_range_m, 0.015)
        along = np.where(steps[None, :] < reach[:, None], steps[None, :], 0.0)
        samples = origin + along[:, :, None] * directions[:, None, :]
        sdf = np.min(np.stack(_solid_sdfs(site, samples.reshape(-1, 3))), axis=0)
        assert sdf.min() > -1e-9


def _two_pallets() -> tuple[Site, Pose2D]:
    near = SitePallet("near", Pose2D(2.0, 0.0, 0.0), 1.1, 1.1, 0.144, 1.0)
    far = SitePallet("far", Pose2D(4.0, 0.0, 0.0), 1.1, 1.1, 0.144, 0.5)
    return Site(pallets=(near, far)), Pose2D(0.0, 0.0, 0.0)


def test_a_box_behind_another_is_hidden_from_low_and_its_top_seen_from_high() -> None:
    site, viewpoint = _two_pallets()
    world = site_world(site)
    params = TerminalScanParams(
        azimuth_step_rad=math.radians(0.5),
        elevation_step_rad=math.radians(0.5),
        horizontal_fov_rad=math.radians(60.0),
        elevation_min_rad=math.radians(-89.0),
        elevation_max_rad=math.radians(30.0),
        max_range_m=8.0,
        range_sigma_m=0.0,
    )
    rng = np.random.default_rng(0)
    low = scan_viewpoint(world, viewpoint, 0.3, params, rng)
    low_names = {world.names[i] for i in low.surface_index}
    assert "near.cargo" in low_names
    assert not any(name.startswith("far") for name in low_names)
    high = scan_viewpoint(world, viewpoint, 3.0, params, rng)
    far_top = high.xyz_m[[world.names[i] == "far.cargo" for i in high.surface_index]]
    on_top = (np.abs(far_top[:, 2] - 0.644) < 1e-9) & (far_top[:, 0] > 3.5)
    assert on_top.sum() > 10


def test_the_floor_is_seen_and_the_range_limit_holds() -> None:
    site, viewpoint = _two_pallets()
    world = site_world(site)
    params = TerminalScanParams(
        azimuth_step_rad=math.radians(2.0),
        elevation_step_rad=math.radians(1.0),
        max_range_m=3.0,
        range_sigma_m=0.0,
    )
    scan = scan_viewpoint(world, viewpoint, 1.2, params, np.random.default_rng(0))
    floor = scan.xyz_m[scan.surface_index == FLOOR_INDEX]
    assert len(floor) > 500
    assert np.abs(floor[:, 2]).max() < 1e-9
    ranges = np.linalg.norm(scan.xyz_m - np.array([0.0, 0.0, 1.2]), axis=1)
    assert ranges.max() <= 3.0 + 1e-9
    assert ranges.max() > 2.9  # the floor reaches out to the limit
    # Every ray whose floor hit is within range does return (the floor is unbounded).
    directions = scan_directions(0.0, params)
    down = directions[:, 2] < 0
    reachable = down & (1.2 / np.maximum(-directions[:, 2], 1e-12) <= 3.0)
    assert len(scan.xyz_m) >= reachable.sum()


def test_a_narrow_field_is_centred_on_the_heading() -> None:
    params = TerminalScanParams(
        horizontal_fov_rad=math.radians(60.0),
        azimuth_step_rad=math.radians(1.0),
        elevation_min_rad=0.0,
        elevation_max_rad=0.0,
    )
    directions = scan_directions(1.0, params)
    azimuths = np.arctan2(directions[:, 1], directions[:, 0])
    assert len(directions) == 61
    assert azimuths.min() == pytest.approx(1.0 - math.radians(30.0))
    assert azimuths.max() == pytest.approx(1.0 + math.radians(30.0))
    full = scan_directions(0.0, TerminalScanParams(azimuth_step_rad=math.radians(1.0)))
    assert len(full) == 360 * 107


def test_each_viewpoint_cloud_is_the_ideal_cloud_moved_by_its_reported_error() -> None:
    site = _storage_site()
    stops = walk_around(site)[:4]
    ideal = survey(site, MARKER, stops, rng=np.random.default_rng(5), errors=IDEAL, params=NOISY)
    real = survey(site, MARKER, stops, rng=np.random.default_rng(5), errors=WORSE, params=NOISY)
    assert real.t0_true == MARKER.compose(real.marker_error)
    assert real.marker_error != Pose2D(0.0, 0.0, 0.0)
    ideal_to_real_w = inverse_pose(real.t0_true).compose(MARKER)  # ideal W is the marker's
    for k, motion in enumerate(real.cloud_motions):
        expected = transform_points(motion.compose(ideal_to_real_w), ideal.points_of(k))
        assert np.allclose(real.points_of(k), expected, atol=1e-9)
        error = real.pose_errors[k]
        believed, true = real.believed_viewpoints[k], real.true_viewpoints[k]
        assert believed.x_m - true.x_m == pytest.approx(error.x_m)
        assert np.allclose(real.origins_m[k], (believed.x_m, believed.y_m, 1.2))
        # The true viewpoint, taken to the site, is where the worker stood.
        assert np.allclose(real.t0_true.compose(true), stops[k], atol=1e-9)
    assert any(math.hypot(e.x_m, e.y_m) > 1e-3 for e in real.pose_errors)


def _error_size(errors: object, seed: int, stops: list[Pose2D], site: Site) -> float:
    assert errors is CONSUMER or errors is WORSE
    result = survey(
        site, MARKER, stops, rng=np.random.default_rng(seed), errors=errors, params=VERY_COARSE
    )
    marker = math.hypot(result.marker_error.x_m, result.marker_error.y_m)
    drift = np.mean([math.hypot(e.x_m, e.y_m) for e in result.pose_errors])
    return marker + float(drift)


def test_worse_is_worse_than_consumer_on_average() -> None:
    site = _storage_site()
    stops = walk_around(site)
    consumer = np.mean([_error_size(CONSUMER, seed, stops, site) for seed in range(20)])
    worse = np.mean([_error_size(WORSE, 100 + seed, stops, site) for seed in range(20)])
    assert worse > 1.5 * consumer
    assert 0.005 < consumer < 0.2  # a few centimetres


def test_drift_grows_with_distance_and_presets_scale_one_seeds_draws() -> None:
    line = [Pose2D(3.0 * (k + 1), 0.0, 0.0) for k in range(10)]  # 3 m legs, 30 m in all
    spread = np.array(
        [
            [
                math.hypot(b.x_m - t.x_m, b.y_m - t.y_m)
                for b, t in zip(w.believed_w, w.true_w, strict=True)
            ]
            for w in (
                draw_walk(Pose2D(0, 0, 0), line, CONSUMER, np.random.default_rng(s))
                for s in range(300)
            )
        ]
    )
    assert spread[:, -1].mean() > 2.0 * spread[:, 0].mean()
    assert 0.05 < spread[:, -1].mean() < 0.3  # ~0.6 % of 30 m straight away from the marker
    typical = draw_walk(MARKER, line, CONSUMER, np.random.default_rng(9))
    worse = draw_walk(MARKER, line, WORSE, np.random.default_rng(9))
    ideal = draw_walk(MARKER, line, IDEAL, np.random.default_rng(9))
    assert worse.marker_error.x_m == pytest.approx(2.5 * typical.marker_error.x_m)
    assert ideal.marker_error == Pose2D(0.0, 0.0, 0.0) and ideal.t0_true == MARKER
    assert np.allclose(ideal.believed_w, ideal.true_w, rtol=0.0, atol=1e-12)


def test_walkers_are_seen_where_they_are_at_the_time() -> None:
    site = Site(movers=(Walker(((2.0, 0.0), (2.0, 4.0)), name="person"),))
    result = survey(
        site,
        Pose2D(0.0, 0.0, 0.0),
        [Pose2D(0.0, 0.0, 0.0)],
        rng=np.random.default_rng(0),
        errors=IDEAL,
        params=COARSE,
        start_s=0.0,
    )
    person = result.xyz_m[[result.surface_names[i] == "person" for i in result.surface_index]]
    assert len(person) > 10
    assert 1.5 < person[:, 2].max() <= 1.7 + 1e-9  # its top (1.7 m) is above the device
    # walked 0 m: t = 0 s, the walker at its first waypoint
    assert np.hypot(person[:, 0] - 2.0, person[:, 1]).max() == pytest.approx(0.25)


def test_a_seed_gives_the_same_survey_and_another_seed_another() -> None:
    site = _storage_site()
    stops = walk_around(site)[:2]
    a, b, c = (
        survey(site, MARKER, stops, rng=np.random.default_rng(seed), params=NOISY)
        for seed in (7, 7, 8)
    )
    assert np.array_equal(a.xyz_m, b.xyz_m) and a.t0_true == b.t0_true
    assert a.xyz_m.shape == c.xyz_m.shape and not np.array_equal(a.xyz_m, c.xyz_m)


def test_a_viewpoint_inside_a_solid_sees_nothing() -> None:
    site, _ = _two_pallets()
    inside_cargo = Pose2D(2.0, 0.0, 0.0)
    result = survey(
        site,
        MARKER,
        [inside_cargo, Pose2D(0.0, 0.0, 0.0)],
        rng=np.random.default_rng(0),
        height_m=0.5,
        params=VERY_COARSE,
    )
    assert len(result.points_of(0)) == 0 and len(result.points_of(1)) > 0
    assert result.origins_m.shape == (2, 3)


def test_pallet_runners_leave_the_fork_pockets_open() -> None:
    pallet = SitePallet("p", Pose2D(2.0, 0.0, 0.0), 1.2, 1.0, 0.144, 0.5)
    names = [name for name, _ in pallet_boxes(pallet, runners=True)]
    assert names == ["p.deck", "p.runner0", "p.runner1", "p.runner2", "p.cargo"]
    world = site_world(Site(pallets=(pallet,)), WorldParams(pallet_runners=True))
    along_pocket = np.array([[1.0, 0.0, 0.0]])
    for y_m, expected in ((0.25, math.inf), (0.0, 1.4)):  # a pocket; the middle runner
        hits = cast_rays_3d(world, np.array([0.0, y_m, 0.06]), along_pocket, 5.0)
        assert hits.range_m[0] == pytest.approx(expected)


def test_walk_around_sees_every_pallet_and_stands_clear() -> None:
    site = load_site("pallets")
    stops = walk_around(site)
    assert stops == walk_around(site)
    result = survey(
        site,
        MARKER,
        stops,
        rng=np.random.default_rng(0),
        errors=IDEAL,
        params=TerminalScanParams(
            azimuth_step_rad=math.radians(4.0), elevation_step_rad=math.radians(4.0)
        ),
    )
    seen = {result.surface_names[i] for i in result.surface_index}
    assert {p.name for p in site.pallets} <= seen
    world = site_world(site)
    for stop in stops:
        for box in world.boxes:
            c, s = math.cos(box[2]), math.sin(box[2])
            rx, ry = stop.x_m - box[0], stop.y_m - box[1]
            assert abs(c * rx + s * ry) > box[3] or abs(-s * rx + c * ry) > box[4]
    with pytest.raises(KeyError):
        walk_around(site, ["no.such.pallet"])


def test_object_list_shares_the_surveys_errors_and_is_exact_when_ideal() -> None:
    site = _storage_site()
    stops = walk_around(site)
    exact = survey_objects(site, MARKER, IDEAL, np.random.default_rng(1), viewpoints=stops)
    for obj, pallet in zip(exact.objects, site.pallets, strict=True):
        placed = MARKER.compose(Pose2D(obj.x_m, obj.y_m, obj.yaw_rad))
        assert placed.x_m == pytest.approx(pallet.pose.x_m)
        assert placed.y_m == pytest.approx(pallet.pose.y_m)
        assert math.remainder(placed.yaw_rad - pallet.pose.yaw_rad, math.tau) == pytest.approx(0)
        assert (obj.name, obj.length_m, obj.width_m) == (pallet.name, 1.1, 1.1)
    objects = survey_objects(site, MARKER, CONSUMER, np.random.default_rng(1), viewpoints=stops)
    cloud = survey(site, MARKER, stops, rng=np.random.default_rng(1), params=VERY_COARSE)
    assert objects.t0_true == cloud.t0_true
    assert all(0 <= k < len(stops) for k in objects.measured_from)


pallets_site = load_site("pallets")
coordinate_x = st.floats(-12.0, 22.0, allow_nan=False)
coordinate_y = st.floats(-17.0, 17.0, allow_nan=False)
yaw = st.floats(-4.0, 4.0, allow_nan=False)
viewpoint = st.builds(Pose2D, coordinate_x, coordinate_y, yaw)


@settings(max_examples=25, deadline=None, derandomize=True)
@given(
    viewpoints=st.lists(viewpoint, min_size=0, max_size=3),
    marker=viewpoint,
    height_m=st.floats(0.05, 4.0),
    seed=st.integers(0, 2**32 - 1),
)
def test_survey_never_raises_anywhere_in_the_site(
    viewpoints: list[Pose2D], marker: Pose2D, height_m: float, seed: int
) -> None:
    result = survey(
        pallets_site,
        marker,
        viewpoints,
        rng=np.random.default_rng(seed),
        height_m=height_m,
        errors=WORSE,
        params=VERY_COARSE,
        start_s=3.0,
    )
    assert np.isfinite(result.xyz_m).all()
    assert result.xyz_m.shape == (len(result.viewpoint_index), 3)
    assert result.origins_m.shape == (len(viewpoints), 3)
    assert np.isfinite(result.origins_m).all()
    assert (result.surface_index >= 0).all()
    assert (result.surface_index < len(result.surface_names)).all()
