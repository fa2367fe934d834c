"""What the ray caster and scanner model keep between scans never leaks into a result."""

from __future__ import annotations

import math

import numpy as np

from appliance.sim import load_site, render_scan
from appliance.sim.raycast import cast_rays
from appliance.sim.scanner_model import beam_angles_rad

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
