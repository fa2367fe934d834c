"""The simulator's compiled cast (`cast_kernels`, through `raycast.nearest_hits_along`)
equals the plain element-wise array code bit for bit, also where the geometry is awkward
(a scanner on a segment's line, at its end, next to a circle) and where the cast drops
far shapes (more than 16 of a kind); and a beam's hit does not depend on what else is
cast with it, which the scanner model's cached static site and its walkers rely on.
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.sim.raycast import RayHits, beam_directions, inside_any_circle, nearer_of
from appliance.sim.raycast import nearest_hits_along as cast

from .plain_cast import plain_cast


def _assert_same(got: RayHits, expected: RayHits) -> None:
    assert got.ranges_m.tobytes() == expected.ranges_m.tobytes()
    np.testing.assert_array_equal(got.hit_index, expected.hit_index)
    assert got.hit_index.dtype == expected.hit_index.dtype


def _scene(
    seed: int, segments: int, circles: int
) -> tuple[float, float, np.ndarray, np.ndarray] | None:
    """Random shapes and an origin outside the circles, often in an awkward place."""
    rng = np.random.default_rng(seed)
    segs = rng.uniform(-10.0, 10.0, (segments, 4))
    if seed % 4 == 0 and segments:
        segs[:, 2:] = segs[:, :2] + rng.uniform(-0.01, 0.01, (segments, 2))  # short ones
    if seed % 7 == 0 and segments > 1:
        segs[1] = segs[0]  # the same segment twice: a tie, to the first
    circs = np.column_stack(
        [rng.uniform(-10.0, 10.0, (circles, 2)), rng.uniform(0.01, 2.0, circles)]
    )
    ox, oy = (float(v) for v in rng.uniform(-5.0, 5.0, 2))
    if seed % 5 == 1 and segments:  # on a segment's line, inside or beyond its ends
        x0, y0, x1, y1 = segs[int(rng.integers(segments))]
        along = float(rng.uniform(-0.5, 1.5))
        ox, oy = x0 + along * (x1 - x0), y0 + along * (y1 - y0)
    if seed % 5 == 2 and segments:  # at a segment's end
        ox, oy = (float(v) for v in segs[int(rng.integers(segments)), :2])
    if seed % 5 == 3 and circles:  # just outside a circle
        cx, cy, radius = circs[0]
        ox, oy = cx + radius * (1.0 + 1e-12), cy
    if inside_any_circle(ox, oy, circs):
        return None
    return ox, oy, segs, circs


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 10_000),
    segments=st.integers(0, 24),
    circles=st.integers(0, 24),
    beams=st.sampled_from([0, 1, 2, 541, 1081]),
    max_range_m=st.floats(0.5, 30.0),
)
def test_every_shape_as_the_plain_cast(
    seed: int, segments: int, circles: int, beams: int, max_range_m: float
) -> None:
    scene = _scene(seed, segments, circles)
    if scene is None:
        return
    ox, oy, segs, circs = scene
    directions = beam_directions(np.random.default_rng(seed).uniform(-4.0, 4.0, beams))
    _assert_same(
        cast(ox, oy, directions, segs, circs, max_range_m),
        plain_cast(ox, oy, directions, segs, circs, max_range_m),
    )


@settings(max_examples=100, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), first=st.integers(0, 1080), count=st.integers(1, 40))
def test_a_beam_is_cast_the_same_in_any_company(seed: int, first: int, count: int) -> None:
    """A footprint's fan is cast apart from the scan: any run of beams, any directions
    array (strided too), gives what the whole scan gives for them."""
    scene = _scene(seed, 1 + seed % 12, seed % 7)
    if scene is None:
        return
    ox, oy, segs, circs = scene
    directions = beam_directions(np.linspace(-3.0, 3.0, 1081))
    whole = cast(ox, oy, directions, segs, circs, 20.0)
    run = slice(first, first + count)
    for part in (directions[run], np.asfortranarray(directions[run]), directions[::-1][::-1][run]):
        _assert_same(cast(ox, oy, part, segs, circs, 20.0), RayHits(whole[0][run], whole[1][run]))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000))
def test_static_site_and_walkers_as_two_casts_are_one_cast(seed: int) -> None:
    """The static shapes (the segments, the first circles) cast together, the walkers
    (the other circles, one or several) apart, the nearer taken by `nearer_of`: the
    same bits as one cast of everything. Not from a point on a segment (`_scene`'s
    seeds 1 and 2 mod 5): there a beam's 0 m hit is no echo and hides what is behind it
    in its own cast only, a case of measure zero for a scanner on a moving vehicle."""
    # 0 mod 5: the origin anywhere; 3 mod 5: just outside a circle.
    scene = _scene(seed - seed % 5 + 3 * (seed % 2), seed % 9, 2 + seed % 20)
    if scene is None:
        return
    ox, oy, segs, circs = scene
    directions = beam_directions(-0.8 + np.radians(0.25) * np.arange(1081))
    first_walker = 1 + seed % (circs.shape[0] - 1)
    static = cast(ox, oy, directions, segs, circs[:first_walker], 20.0)
    walking = cast(ox, oy, directions, np.empty((0, 4)), circs[first_walker:], 20.0)
    _assert_same(
        nearer_of(static, walking, segs.shape[0] + first_walker),
        cast(ox, oy, directions, segs, circs, 20.0),
    )


def test_far_shapes_dropped_or_not_the_same_hits() -> None:
    """Above 16 shapes of a kind the far ones are dropped before the cast; the hits and
    their shape numbers are those of the cast of all of them."""
    rng = np.random.default_rng(5)
    segs = rng.uniform(-60.0, 60.0, (200, 4))
    segs[:, 2:] = segs[:, :2] + rng.uniform(-2.0, 2.0, (200, 2))
    circs = np.column_stack([rng.uniform(-60.0, 60.0, (200, 2)), rng.uniform(0.1, 1.0, 200)])
    directions = beam_directions(np.linspace(-np.pi, np.pi, 1081))
    origin = (0.3, -0.2)
    assert not inside_any_circle(*origin, circs)
    hits = cast(*origin, directions, segs, circs, 20.0)
    _assert_same(hits, plain_cast(*origin, directions, segs, circs, 20.0))
    assert (hits.hit_index >= 200).any() and ((hits.hit_index >= 0) & (hits.hit_index < 200)).any()
