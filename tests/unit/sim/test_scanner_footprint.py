"""The footprint's echoes as the plain array code computes them, to the last bit.

The scanner model's hot paths (which beams to cast again, the receiver's first strong
echo, the culled casts) are written for speed; here each is checked for exact equality
with a straightforward formulation, so that a recorded docking run replays unchanged.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.sim import load_site, render_scan, scanner_footprint, scanner_model
from appliance.sim.raycast import NO_HIT, RayHits
from appliance.sim.scanner_errors import (
    BeamFootprint,
    ScannerErrors,
    draw_scanner_errors,
    first_strong_echo,
)
from appliance.sim.scanner_footprint import JUNCTION_STEP_M, footprint_beams
from appliance.sim.scanner_model import RayCache

from .plain_cast import plain_cast, plain_first_strong_echo


def _footprint_beams_reference(
    hits: RayHits, n_segments: int, footprint: BeamFootprint, step_rad: float, max_range_m: float
) -> np.ndarray:
    ranges, index = hits.ranges_m, hits.hit_index
    count = ranges.shape[0]
    near = index >= n_segments
    edges = np.flatnonzero(
        (index[1:] != index[:-1]) & (np.abs(ranges[1:] - ranges[:-1]) > JUNCTION_STEP_M)
    )
    if edges.size == 0:
        return np.flatnonzero(near)
    before = np.where(ranges[edges] > 0.0, ranges[edges], max_range_m)
    after = np.where(ranges[edges + 1] > 0.0, ranges[edges + 1], max_range_m)
    reach = int(footprint.half_angle_rad(np.minimum(before, after)).max() // step_rad)
    for k in range(min(reach, count) + 1):
        near[np.maximum(edges - k, 0)] = True
        near[np.minimum(edges + 1 + k, count - 1)] = True
    return np.flatnonzero(near)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 10_000),
    beams=st.integers(2, 1081),
    shapes=st.integers(1, 12),
    step_deg=st.sampled_from([0.25, 0.5]),
)
def test_footprint_beams_as_the_plain_loop(
    seed: int, beams: int, shapes: int, step_deg: float
) -> None:
    rng = np.random.default_rng(seed)
    # Runs of beams on one shape at smoothly changing ranges, misses in between.
    index = np.repeat(rng.integers(-1, shapes, beams), rng.integers(1, 40, beams))[:beams]
    ranges = np.where(index >= 0, rng.uniform(0.02, 20.0, beams), 0.0)
    ranges[1:] = np.where(rng.random(beams - 1) < 0.8, ranges[:-1] + 0.001, ranges[1:])
    ranges[index < 0] = 0.0
    hits = RayHits(ranges, np.where(ranges > 0.0, index, NO_HIT))
    footprint = BeamFootprint(divergence_rad=float(rng.uniform(0.0, 0.05)))
    n_segments = int(rng.integers(0, shapes + 1))
    args = (hits, n_segments, footprint, math.radians(step_deg), 20.0)
    np.testing.assert_array_equal(footprint_beams(*args), _footprint_beams_reference(*args))


@settings(max_examples=200, deadline=None, derandomize=True)
@given(seed=st.integers(0, 10_000), beams=st.integers(1, 200), returns=st.integers(1, 9))
def test_first_strong_echo_as_the_plain_code(seed: int, beams: int, returns: int) -> None:
    rng = np.random.default_rng(seed)
    ranges = np.where(
        rng.random((beams, returns)) < 0.8, rng.uniform(0.1, 20.0, (beams, returns)), 0.0
    )
    ranges[:, 1:] = np.where(rng.random((beams, returns - 1)) < 0.3, ranges[:, :1], ranges[:, 1:])
    energy = rng.uniform(0.0, 1e-3, (beams, returns))
    for min_energy in (0.0, 3e-4):
        got = first_strong_echo(ranges, energy, 0.6, min_energy)
        expected = plain_first_strong_echo(ranges, energy, 0.6, min_energy)
        for a, b in zip(got, expected, strict=True):
            assert a.tobytes() == b.tobytes()


@pytest.mark.parametrize("cached", [False, True])
@pytest.mark.parametrize("errors", [draw_scanner_errors(3, 1, True), ScannerErrors()])
def test_render_scan_as_with_the_plain_casts(
    cached: bool, errors: ScannerErrors, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The scanner's compiled casts and echoes against the plain array code's, on the
    launcher from poses all over it, with its walker (and a scanner at rest, the static
    site's hits cached)."""
    site = load_site("launcher")
    rng = np.random.default_rng(7)
    poses = [
        (float(x), float(y), float(yaw))
        for x, y, yaw in zip(
            rng.uniform(-16.0, 2.0, 16),
            rng.uniform(-5.0, 9.0, 16),
            rng.uniform(-3.1, 3.1, 16),
            strict=True,
        )
    ]
    poses[5] = poses[4]  # a scanner at rest: the cache keeps the static site's hits

    def scans() -> list[tuple[np.ndarray, np.ndarray]]:
        cache = RayCache() if cached else None
        noise = np.random.default_rng(11)
        mount = (2.6, 1.1, math.radians(45.0))
        return [
            render_scan(site, 0.7 * i, pose, mount, rng=noise, errors=errors, cache=cache)
            for i, pose in enumerate(poses)
        ]

    fast = scans()
    monkeypatch.setattr(scanner_model, "nearest_hits_along", plain_cast)
    monkeypatch.setattr(scanner_footprint, "first_strong_echo", plain_first_strong_echo)
    plain = scans()
    for (ranges, remission), (plain_ranges, plain_remission) in zip(fast, plain, strict=True):
        assert ranges.tobytes() == plain_ranges.tobytes()
        assert remission.tobytes() == plain_remission.tobytes()
