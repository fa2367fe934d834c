"""A scan's casts (`raycast_scan`) equal `raycast`'s plain ones, bit for bit.

The scanner model casts with shared shape terms and fewer array operations; the recorded
runs of the docking simulation must not move because of it, so each check here is exact
equality with `raycast.nearest_hits_along` (and `nearer_of` for the walkers), also where
the geometry is awkward (a scanner on a segment's line, at its end, next to a circle)
and where the plain cast drops far shapes (more than 16 of a kind).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.sim.raycast import (
    RayHits,
    beam_directions,
    inside_any_circle,
    nearer_of,
    nearest_hits_along,
)
from appliance.sim.raycast_scan import _VIEWS, nearest_hits_seen, shape_terms, with_walkers


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
    angles = np.random.default_rng(seed).uniform(-4.0, 4.0, beams)
    directions = beam_directions(angles)
    terms = shape_terms(ox, oy, segs, circs)
    _assert_same(
        nearest_hits_seen(terms, directions, max_range_m),
        nearest_hits_along(ox, oy, directions, segs, circs, max_range_m),
    )


@pytest.mark.parametrize("seed", range(60))
def test_static_site_and_walkers_as_two_casts(seed: int) -> None:
    """The static shapes (the segments, the first circles) cast together, the walkers
    (the other circles, one or several) apart, the nearer taken: as `nearer_of` does."""
    scene = _scene(seed, seed % 9, 2 + seed % 20)
    if scene is None:
        return
    ox, oy, segs, circs = scene
    angles = -0.8 + math.radians(0.25) * np.arange(1081)
    directions = beam_directions(angles)
    terms = shape_terms(ox, oy, segs, circs)
    first_walker = 1 + seed % (circs.shape[0] - 1)
    static = nearest_hits_seen(terms, directions, 20.0, slice(first_walker))
    expected_static = nearest_hits_along(ox, oy, directions, segs, circs[:first_walker], 20.0)
    _assert_same(static, expected_static)
    walking = nearest_hits_along(ox, oy, directions, np.empty((0, 4)), circs[first_walker:], 20.0)
    first_number = segs.shape[0] + first_walker
    _assert_same(
        with_walkers(static, terms, directions, 20.0, slice(first_walker, None), first_number),
        nearer_of(expected_static, walking, first_number),
    )


def test_scratch_views_stay_few_whatever_the_beam_counts() -> None:
    """The footprints' casts ask for another row count nearly every scan: the views kept
    for them must not pile up (nor the memory they hold)."""
    terms = shape_terms(0.0, 0.0, np.array([[5.0, -1.0, 5.0, 1.0]]), np.array([[0.0, 3.0, 0.5]]))
    for beams in range(1, 400):
        directions = beam_directions(np.linspace(-1.0, 1.0, beams))
        nearest_hits_seen(terms, directions, 20.0)
    assert len(_VIEWS.floats) <= 64 and len(_VIEWS.flags) <= 64
