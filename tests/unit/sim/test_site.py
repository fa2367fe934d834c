"""Sites: the builders' geometry, walkers as functions of time, and site files."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from appliance.config import ConfigError
from appliance.sim import (
    Circle,
    LauncherSpec,
    PalletAreaSpec,
    Pose2D,
    Segment,
    Site,
    SiteError,
    Walker,
    YardSpec,
    builtin_site_names,
    launcher_site,
    load_site,
    pallet_area_site,
    parse_site,
    yard_site,
)


def _ends(segment: Segment) -> tuple[float, float, float, float]:
    return segment.x0_m, segment.y0_m, segment.x1_m, segment.y1_m


def _start(segment: Segment) -> tuple[float, float]:
    return segment.x0_m, segment.y0_m


def _end(segment: Segment) -> tuple[float, float]:
    return segment.x1_m, segment.y1_m


# -- builders ---------------------------------------------------------------------------


def test_launcher_in_its_own_frame() -> None:
    site = launcher_site(LauncherSpec())
    front = site.shape("launcher.front_board")
    left = site.shape("launcher.side_board_left")
    right = site.shape("launcher.side_board_right")
    assert isinstance(front, Segment) and isinstance(left, Segment) and isinstance(right, Segment)
    assert _ends(front) == pytest.approx((0.0, -1.5, 0.0, 1.5))
    # Side boards hinge at the front board's ends (the corners of the initial pose
    # estimate) and sweep back into the launcher at 45°.
    assert _start(left) == pytest.approx(_end(front))
    assert _start(right) == pytest.approx(_start(front))
    half_diagonal = 0.8 / math.sqrt(2.0)
    assert _end(left) == pytest.approx((half_diagonal, 1.5 + half_diagonal))
    assert left.length_m == pytest.approx(0.8)
    cylinder = site.shape("launcher.cylinder_left")
    assert isinstance(cylinder, Circle)
    assert (cylinder.cx_m, cylinder.cy_m, cylinder.radius_m) == pytest.approx((-0.5, 2.5, 0.15))
    assert site.target("launcher.docking") == pytest.approx(Pose2D(0.0, 0.0, 0.0))


def test_launcher_pose_moves_everything_and_the_docking_target() -> None:
    spec = LauncherSpec(x_m=10.0, y_m=-2.0, yaw_deg=90.0, docking_standoff_m=0.3)
    site = launcher_site(spec)
    front = site.shape("launcher.front_board")
    assert isinstance(front, Segment)
    # Yaw 90°: the vehicle docks heading +y, the board lies along x at y = -2.
    assert _ends(front) == pytest.approx((11.5, -2.0, 8.5, -2.0))
    cylinder = site.shape("launcher.cylinder_left")
    assert isinstance(cylinder, Circle)
    assert (cylinder.cx_m, cylinder.cy_m) == pytest.approx((7.5, -2.5))
    assert site.target("launcher.docking") == pytest.approx(Pose2D(10.0, -2.3, math.pi / 2))


def test_side_boards_can_point_at_the_vehicle() -> None:
    site = launcher_site(LauncherSpec(side_board_sweep_deg=-90.0))
    left = site.shape("launcher.side_board_left")
    assert isinstance(left, Segment)
    assert _end(left) == pytest.approx((-0.8, 1.5))


def test_pallets_are_closed_rectangles_on_a_grid() -> None:
    spec = PalletAreaSpec(
        x_m=2.0,
        y_m=1.0,
        rows=2,
        columns=3,
        pallet_length_m=1.2,
        pallet_width_m=1.0,
        gap_x_m=1.0,
        gap_y_m=0.5,
    )
    site = pallet_area_site(spec)
    assert len(site.segments) == 4 * 6
    assert len(site.targets) == 6
    assert site.target("pallets.r1c2") == pytest.approx(Pose2D(2.0 + 2.2, 1.0 + 3.0, 0.0))
    for index in range(6):
        sides = site.segments[4 * index : 4 * index + 4]
        for a, b in zip(sides, sides[1:] + sides[:1], strict=True):
            assert _end(a) == pytest.approx(_start(b))  # closed outline
        assert sorted(round(s.length_m, 9) for s in sides) == [1.0, 1.0, 1.2, 1.2]


def test_pallet_jitter_is_fixed_by_the_seed() -> None:
    jittered = PalletAreaSpec(jitter_m=0.05, jitter_deg=3.0, seed=11)
    first, again = pallet_area_site(jittered), pallet_area_site(jittered)
    assert first == again
    neat = pallet_area_site(PalletAreaSpec())
    offsets = [
        math.hypot(p.x_m - q.x_m, p.y_m - q.y_m)
        for (_, p), (_, q) in zip(first.targets, neat.targets, strict=True)
    ]
    assert 0.0 < max(offsets) <= 0.05 * math.sqrt(2.0)


def test_yard_is_a_rectangle_around_its_centre() -> None:
    site = yard_site(YardSpec(x_m=-8.0, length_m=40.0, width_m=30.0))
    xs = [x for s in site.segments for x in (s.x0_m, s.x1_m)]
    ys = [y for s in site.segments for y in (s.y0_m, s.y1_m)]
    assert (min(xs), max(xs), min(ys), max(ys)) == pytest.approx((-28.0, 12.0, -15.0, 15.0))


def test_specs_validate_when_built_in_python() -> None:
    with pytest.raises(ValueError, match="front_board_width_m"):
        LauncherSpec(front_board_width_m=0.0)


# -- walkers and shapes at an instant ---------------------------------------------------


def test_walker_paces_its_path_back_and_forth() -> None:
    walker = Walker(((0.0, 0.0), (6.0, 0.0), (6.0, 6.0)), speed_mps=1.2)
    assert walker.path_length_m == pytest.approx(12.0)
    assert walker.position_at(0.0) == pytest.approx((0.0, 0.0))
    assert walker.position_at(2.5) == pytest.approx((3.0, 0.0))
    assert walker.position_at(7.5) == pytest.approx((6.0, 3.0))
    assert walker.position_at(10.0) == pytest.approx((6.0, 6.0))  # the far end...
    assert walker.position_at(12.5) == pytest.approx((6.0, 3.0))  # ...and back
    assert walker.position_at(20.0) == pytest.approx((0.0, 0.0))
    assert walker.position_at(-2.5) == pytest.approx((3.0, 0.0))  # symmetric in time
    shifted = Walker(walker.waypoints_m, speed_mps=1.2, phase_s=2.5)
    assert shifted.position_at(0.0) == pytest.approx((3.0, 0.0))


def test_walker_without_a_path_stands_still() -> None:
    assert Walker(((1.0, 2.0),)).position_at(100.0) == (1.0, 2.0)
    with pytest.raises(ValueError, match="waypoint"):
        Walker(())


def test_shapes_at_lists_static_shapes_then_walkers() -> None:
    site = Site(
        (Segment(0, 0, 1, 0, 0.5, "wall"),),
        (Circle(5, 5, 0.2, 0.4, "post"),),
        (Walker(((0.0, 3.0), (10.0, 3.0)), remission=0.3, name="person"),),
    )
    shapes = site.shapes_at(5.0)
    assert shapes.segments.shape == (1, 4)
    assert shapes.circles.shape == (2, 3)
    assert shapes.circles[1] == pytest.approx((6.0, 3.0, 0.25))
    assert shapes.circle_remission == pytest.approx([0.4, 0.3])
    assert shapes.names == ("wall", "post", "person")
    empty = Site().shapes_at(0.0)
    assert empty.segments.shape == (0, 4) and empty.circles.shape == (0, 3)


def test_missing_target_and_shape_are_named() -> None:
    with pytest.raises(KeyError, match="no target 'dock'"):
        Site(name="x").target("dock")
    with pytest.raises(KeyError, match="no shape 'board'"):
        Site(name="x").shape("board")


# -- site files -------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["launcher", "pallets"])
def test_builtin_sites_load(name: str) -> None:
    assert name in builtin_site_names()
    site = load_site(name)
    assert site.name == name
    assert site.segments and site.movers
    shapes = site.shapes_at(0.0)
    assert len(shapes.names) == len(shapes.segments) + len(shapes.circles)
    assert np.isfinite(shapes.segments).all()


def test_launcher_site_has_launcher_posts_and_a_person() -> None:
    site = load_site("launcher")
    names = {s.name for s in (*site.segments, *site.circles)}
    assert {"launcher.front_board", "launcher.cylinder_left", "post_a", "post_b"} <= names
    assert [m.name for m in site.movers] == ["person"]
    assert any(n.startswith("yard.") for n in names)


def test_site_from_a_path(tmp_path: Path) -> None:
    path = tmp_path / "tiny.toml"
    path.write_text("[[posts]]\nx_m = 1.0\ny_m = 2.0\n\n[launcher]\nyaw_deg = 180.0\n")
    site = load_site(path)
    assert site.name == "tiny"
    assert site.target("launcher.docking").yaw_rad == pytest.approx(math.pi)
    assert not any(s.name.startswith("yard.") for s in site.segments)  # the yard is optional


def _problem(text: str) -> str:
    with pytest.raises(SiteError) as caught:
        parse_site(text, source="bad.toml")
    return str(caught.value)


def test_bad_value_names_the_field_and_the_range() -> None:
    message = _problem("[launcher]\nfront_board_width_m = -3.0\n")
    assert "bad.toml" in message
    assert "launcher.front_board_width_m" in message
    assert "-3.0" in message and "0.0 < value <= 20.0" in message


def test_unknown_field_is_named_with_a_suggestion() -> None:
    message = _problem("[launcher]\ncylinder_raduis_m = 0.2\n")
    assert "launcher.cylinder_raduis_m: unknown field; did you mean 'cylinder_radius_m'?" in message
    assert "unknown field" in _problem("[yard]\nsize = 3\n")


def test_problems_in_array_tables_carry_their_index() -> None:
    message = _problem(
        "[[walkers]]\nwaypoints_m = [[0.0, 0.0]]\n\n"
        "[[walkers]]\nwaypoints_m = [[0.0, 0.0], [1.0, 1.0]]\nspeed_mps = -1.2\n"
        "\n[[posts]]\ny_m = 1.0\n"
    )
    assert "walkers[1].speed_mps" in message
    assert "posts[0].x_m: Field required" in message
    assert "2 problem(s)" in message


def test_wrong_type_and_broken_toml_and_missing_file(tmp_path: Path) -> None:
    assert "launcher.x_m" in _problem('[launcher]\nx_m = "far"\n')
    assert "not valid TOML" in _problem("[launcher\n")
    with pytest.raises(SiteError, match="built-in sites are: launcher, pallets"):
        load_site(tmp_path / "nowhere.toml")


def test_site_error_is_a_config_error() -> None:
    """The CLI already prints ConfigError; a bad site file needs nothing new there."""
    assert issubclass(SiteError, ConfigError)
