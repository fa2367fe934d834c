"""The vehicle file's pallet tables: what the `pallet` source needs is checked when the
file loads, and the `forklift-sim` profile's posts, walls and columns are the simulated
site's (the two must not drift apart)."""

from __future__ import annotations

import pytest

from appliance.config import ConfigError, load_config
from appliance.config.loader import parse_config
from appliance.sim.site_file import load_site

PALLET_SOURCE = """
name = "fork"
kind = "{kind}"
[simulation]
enabled = true
site = "pallets"
[engagement]
autopilot_source = "pallet"
hold_to_move = true
max_set_speed_mps = 1.0
{pallets}
"""


def _problems(kind: str, pallets: str) -> str:
    with pytest.raises(ConfigError) as caught:
        parse_config(PALLET_SOURCE.format(kind=kind, pallets=pallets), source="<test>")
    return str(caught.value)


def test_the_pallet_source_needs_a_forklift_its_posts_and_a_worker_map() -> None:
    text = _problems("flatbed", "")
    assert 'kind = "forklift"' in text and "pallets.landmarks" in text
    assert "pallets.worker_map" in text


def test_landmarks_of_two_radii_or_one_name_twice_are_refused() -> None:
    posts = """
[pallets]
worker_map = "w.json"
[[pallets.landmarks]]
name = "a"
x_m = 0.0
y_m = 0.0
radius_m = 0.15
[[pallets.landmarks]]
name = "{name}"
x_m = 5.0
y_m = 0.0
radius_m = {radius}
"""
    assert "one radius" in _problems("forklift", posts.format(name="b", radius=0.2))
    assert "named twice: a" in _problems("forklift", posts.format(name="a", radius=0.15))


def test_forklift_sim_knows_the_site_it_is_simulated_in() -> None:
    config = load_config("forklift-sim")
    site = load_site(config.simulation.site)
    posts = {c.name: (c.cx_m, c.cy_m, c.radius_m) for c in site.circles}
    landmarks = {lm.name: (lm.x_m, lm.y_m, lm.radius_m) for lm in config.pallets.landmarks}
    columns = {c.name: (c.x_m, c.y_m, c.radius_m) for c in config.pallets.columns}
    assert {**landmarks, **columns} == posts
    walls = {w.name: (w.x0_m, w.y0_m, w.x1_m, w.y1_m) for w in config.pallets.walls}
    yard = {
        s.name: (s.x0_m, s.y0_m, s.x1_m, s.y1_m) for s in site.segments if s.name.startswith("yard")
    }
    assert walls == yard
    assert config.engagement.autopilot_source == "pallet" and config.tablet_page.enabled
