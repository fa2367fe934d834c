"""What the ray caster and scanner model keep between scans never leaks into a result."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from appliance.sim import load_site, render_scan
from appliance.sim.raycast import cast_rays, inside_any_circle
from appliance.sim.scanner_errors import TYPICAL_LMS111
from appliance.sim.scanner_model import RayCache, beam_angles_rad, scanner_pose
from appliance.sim.site import Site

VEHICLE = (-10.0, 0.3, math.radians(2.0))
MOUNT = (2.6, 1.1, math.radians(45.0))


def test_beam_angles_stay_fresh_arrays_while_render_scan_reuses_its_own() -> None:
    site = load_site("launcher")
    first, _ = render_scan(site, 0.0, VEHICLE, MOUNT, rng=np.random.default_rng(1))
    mine = beam_angles_rad()
    mine += 1.0  # a caller may do what it likes with its copy
    assert beam_angles_rad()[0] == math.radians(-45.0)
    again, _ = render_scan(site, 0.0, VEHICLE, MOUNT, rng=np.random.default_rng(1))
    assert again.tobytes() == first.tobytes()


def test_scans_of_other_beam_counts_in_between_change_nothing() -> None:
    site = load_site("launcher")
    step = math.radians(0.5)
    first = render_scan(site, 0.0, VEHICLE, MOUNT, rng=np.random.default_rng(2), step_rad=step)
    render_scan(site, 0.0, VEHICLE, MOUNT, rng=np.random.default_rng(2))  # 1081 beams
    cast_rays(0.0, 0.0, np.array([0.0, 1.0, 2.0]), np.array([[5.0, -1.0, 5.0, 1.0]]), None, 20.0)
    again = render_scan(site, 0.0, VEHICLE, MOUNT, rng=np.random.default_rng(2), step_rad=step)
    assert len(first[0]) == 541
    for a, b in zip(first, again, strict=True):
        assert a.tobytes() == b.tobytes() and a.flags.writeable


# ---- RayCache: the static site's hits kept while the scanner stands still


def _pair(site: Site, t_s: float, vehicle: tuple[float, float, float], cache: RayCache) -> None:
    """One scan with the cache and one without, from the same random stream: equal to
    the last bit. The default scanner model is the realistic one (footprints cast at
    edges, remission limit, noise)."""
    with_cache = render_scan(site, t_s, vehicle, MOUNT, rng=np.random.default_rng(3), cache=cache)
    without = render_scan(site, t_s, vehicle, MOUNT, rng=np.random.default_rng(3))
    assert with_cache[0].tobytes() == without[0].tobytes()
    assert with_cache[1].tobytes() == without[1].tobytes()


def test_a_scanner_at_rest_casts_the_static_site_once_and_the_walker_every_scan() -> None:
    site = load_site("launcher")
    assert site.movers  # the default site has a walking person: the cache must cope
    cache = RayCache()
    for t_s in (0.0, 0.5, 1.0, 1.5, 2.0):
        _pair(site, t_s, VEHICLE, cache)
    assert (cache.misses, cache.hits) == (1, 4)
    person = site.movers[0]
    assert person.position_at(0.0) != person.position_at(2.0)


def test_a_moving_scanner_misses_the_cache_and_still_matches() -> None:
    site = load_site("launcher")
    cache = RayCache()
    for step in range(6):
        _pair(site, 0.1 * step, (VEHICLE[0] + 0.05 * step, VEHICLE[1], VEHICLE[2]), cache)
    assert (cache.misses, cache.hits) == (6, 0)


def test_blinded_inside_the_walker_or_a_post_with_and_without_cache() -> None:
    site = load_site("launcher")
    cache = RayCache()
    x_m, y_m = site.movers[0].position_at(1.0)
    inside_walker = (x_m, y_m, 0.0)
    ranges, _ = render_scan(
        site, 1.0, inside_walker, (0.0, 0.0, 0.0), rng=np.random.default_rng(0), cache=cache
    )
    assert not ranges.any()
    post = site.circles[0]
    inside_post = (post.cx_m, post.cy_m, 0.0)
    for t_s in (0.0, 1.0):
        ranges, _ = render_scan(
            site, t_s, inside_post, (0.0, 0.0, 0.0), rng=np.random.default_rng(0), cache=cache
        )
        assert not ranges.any()


def _inside_a_walker(site: Site, vehicle: tuple[float, float, float], t_s: float) -> bool:
    """Whether the scanner stands inside the walking person at ``t_s``: blinded, every
    beam 0 before any cast, so the cache is neither asked nor filled."""
    scanner = scanner_pose(vehicle, TYPICAL_LMS111.true_mount(MOUNT))
    walkers = site.shapes_at(t_s).circles[site.static_shapes().circles.shape[0] :]
    return inside_any_circle(scanner.x_m, scanner.y_m, walkers)


@settings(max_examples=40, deadline=None)
# The person walks through the scanner at 6 s (hypothesis seed 42): a blinded scan.
@example(x_m=-12.0, y_m=3.0, yaw_deg=56.0, t_s=6.0)
@given(
    x_m=st.floats(-16.0, 2.0),
    y_m=st.floats(-4.0, 4.0),
    yaw_deg=st.floats(-180.0, 180.0),
    t_s=st.floats(0.0, 30.0),
)
def test_cache_equals_a_full_cast_anywhere(
    x_m: float, y_m: float, yaw_deg: float, t_s: float
) -> None:
    site = load_site("launcher")
    cache = RayCache()
    vehicle = (x_m, y_m, math.radians(yaw_deg))
    _pair(site, t_s, vehicle, cache)
    _pair(site, t_s + 0.25, vehicle, cache)  # the second from the cache
    blinded = [_inside_a_walker(site, vehicle, t) for t in (t_s, t_s + 0.25)]
    # Both scans cast: the second from the cache. A blinded scan casts nothing: with the
    # first blinded the second fills the cache (a miss); with the second, it is not asked.
    assert (cache.hits, cache.misses) == {
        (False, False): (1, 1),
        (True, False): (0, 1),
        (False, True): (0, 1),
        (True, True): (0, 0),
    }[blinded[0], blinded[1]]
