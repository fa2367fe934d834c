"""`dbw route list|show|check|import` through click's runner: exit codes, what is printed,
the PNG, and one-line errors (no traceback) for bad input."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner, Result

from appliance.cli.route import route
from appliance.localization.local_frame import LocalFrame
from appliance.routes.geojson import dumps_route, write_route_file
from appliance.routes.route import Directions, LocalLine, Route
from tests.unit.routes.courses import ArcCourse

FRAME = LocalFrame(52.2, 9.3, 80.0)
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _invoke(*args: str | Path) -> Result:
    return CliRunner().invoke(route, [str(arg) for arg in args])


def _course_file(tmp_path: Path, radius_m: float, name: str = "arc", geodetic: bool = True) -> Path:
    points = ArcCourse(radius_m=radius_m).points(0.5)
    chosen = Route.from_enu(
        name,
        points,
        FRAME,
        geodetic=geodetic,
        directions=Directions.FORWARD,
        speed_limit_mps=2.0,
        vehicle="husky",
    )
    path = tmp_path / f"{name}-{radius_m:g}.geojson"
    write_route_file(path, chosen)
    return path


def test_check_passes_a_turn_the_husky_can_make(tmp_path: Path) -> None:
    result = _invoke("check", _course_file(tmp_path, 10.0), "--config", "husky")
    assert result.exit_code == 0, result.output
    assert "turns down to 3.66 m radius" in result.output
    assert "the route's tightest is 10.00 m" in result.output
    assert result.output.strip().endswith("OK (0 warning(s))")


def test_check_refuses_a_turn_too_tight_and_says_where(tmp_path: Path) -> None:
    result = _invoke("check", _course_file(tmp_path, 3.0, geodetic=False), "--config", "husky")
    assert result.exit_code == 1
    (line,) = [line for line in result.output.splitlines() if line.startswith("refused: ")]
    assert "left turn of radius 3.00 m at point" in line and "m from the start" in line
    assert "; lat 52.2" in line and "lon 9.30" in line
    assert "REFUSED (1 refusal(s), 0 warning(s))" in result.output


def test_check_uses_a_given_radius(tmp_path: Path) -> None:
    result = _invoke("check", _course_file(tmp_path, 10.0), "--min-radius-m", "12")
    assert result.exit_code == 1
    assert "the vehicle needs at least 12.00 m" in result.output


def test_a_figure_eight_is_checked_with_a_warning(tmp_path: Path) -> None:
    t = np.linspace(np.pi / 4, np.pi / 4 + 0.95 * 2 * np.pi, 600)
    eight = Route.from_enu("eight", np.column_stack((20 * np.sin(t), 10 * np.sin(2 * t))), FRAME)
    write_route_file(tmp_path / "eight.geojson", eight)
    result = _invoke("check", tmp_path / "eight.geojson", "--config", "husky")
    assert result.exit_code == 0
    assert "warning: the route crosses itself: at point" in result.output


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{", "not JSON"),
        (
            '{"type": "Feature", "properties": {"name": "x"}, "geometry": {"type": "LineString", '
            '"coordinates": [[0, 0], [200, 0]]}}',
            "geometry.coordinates[1][0]: longitude 200",
        ),
        ('{"a": NaN}', "NaN"),
    ],
)
def test_a_bad_file_is_one_line_and_exit_2(tmp_path: Path, content: str, message: str) -> None:
    path = tmp_path / "bad.geojson"
    path.write_text(content, encoding="utf-8")
    for args in (("check", path), ("import", path, "--dir", tmp_path / "store")):
        result = _invoke(*args)
        assert result.exit_code == 2
        assert result.output.count("\n") == 1 and result.output.startswith(f"error: {path}: ")
        assert message in result.output
        assert result.exception is None or isinstance(result.exception, SystemExit)


def test_a_missing_file_is_one_line_and_exit_2(tmp_path: Path) -> None:
    result = _invoke("check", tmp_path / "nope.geojson")
    assert result.exit_code == 2 and "cannot read" in result.output


def test_import_then_list_then_show(tmp_path: Path) -> None:
    store = tmp_path / "routes"
    source = _course_file(tmp_path, 10.0, name="field")
    imported = _invoke("import", source, "--dir", store, "--config", "husky")
    assert imported.exit_code == 0, imported.output
    assert f"stored route 'field' as {store / 'field.geojson'}" in imported.output
    assert (store / "field.geojson").read_text(encoding="utf-8") == source.read_text(
        encoding="utf-8"
    )
    renamed = _invoke("import", source, "--name", "field-2", "--dir", store)
    assert renamed.exit_code == 0, renamed.output
    again = _invoke("import", source, "--dir", store)
    assert again.exit_code == 2 and "exists in" in again.output and "--force" in again.output
    assert _invoke("import", source, "--dir", store, "--force").exit_code == 0

    listed = _invoke("list", "--dir", store)
    assert listed.exit_code == 0
    header, first, second = listed.output.splitlines()
    assert header.split() == ["NAME", "LENGTH_M", "POINTS", "DIRECTIONS", "LIMIT_MPS", "FILE"]
    length_m = ArcCourse(radius_m=10.0).length_m
    count = len(ArcCourse(radius_m=10.0).points(0.5))
    assert first.split() == [
        "field",
        f"{length_m:.1f}",
        str(count),
        "forward",
        "2",
        str(store / "field.geojson"),
    ]
    assert second.split()[0] == "field-2"

    png = tmp_path / "field.png"
    shown = _invoke(
        "show",
        "field",
        "--dir",
        store,
        "--output",
        png,
        "--vehicle-east-m",
        "5",
        "--vehicle-north-m",
        "-2",
    )
    assert shown.exit_code == 0, shown.output
    assert f"route 'field': {count} points (lon/lat)" in shown.output
    assert png.stat().st_size > 10_000
    assert png.read_bytes()[:8] == PNG_SIGNATURE


def test_import_refuses_a_route_the_vehicle_cannot_drive(tmp_path: Path) -> None:
    result = _invoke(
        "import", _course_file(tmp_path, 3.0), "--dir", tmp_path / "r", "--config", "husky"
    )
    assert result.exit_code == 1
    assert not (tmp_path / "r").exists()


def test_import_refuses_a_bad_name(tmp_path: Path) -> None:
    result = _invoke("import", _course_file(tmp_path, 10.0), "--name", "../up", "--dir", tmp_path)
    assert result.exit_code == 2
    assert "'../up' is not a route name" in result.output


def test_list_shows_broken_files_and_an_empty_directory(tmp_path: Path) -> None:
    assert (
        _invoke("list", "--dir", tmp_path / "none").output == f"no routes in {tmp_path / 'none'}\n"
    )
    (tmp_path / "broken.geojson").write_text("[]", encoding="utf-8")
    result = _invoke("list", "--dir", tmp_path)
    assert result.exit_code == 0
    assert "broken" in result.output and "not an array" in result.output


def test_show_draws_a_file_in_a_given_frame(tmp_path: Path) -> None:
    path = tmp_path / "local.geojson"
    line = LocalLine(np.array([0.0, 10.0, 10.0]), np.array([0.0, 0.0, 10.0]), FRAME)
    path.write_text(dumps_route(Route("local", line)), encoding="utf-8")
    png = tmp_path / "out.png"
    result = _invoke(
        "show", path, "--output", png, "--origin-lat-deg", "52.2", "--origin-lon-deg", "9.3"
    )
    assert result.exit_code == 0, result.output
    assert "drawn in the given origin (origin lat 52.2000000, lon 9.3000000)" in result.output
    assert png.read_bytes()[:8] == PNG_SIGNATURE


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("show", "missing"), "no route 'missing'"),
        (("show", ".."), "is not a route name"),
        (
            ("show", "r", "--vehicle-east-m", "1"),
            "give both --vehicle-east-m and --vehicle-north-m",
        ),
        (("show", "r", "--origin-lat-deg", "1"), "give both --origin-lat-deg and --origin-lon-deg"),
        (
            ("show", "r", "--origin-lat-deg", "95", "--origin-lon-deg", "9"),
            "latitude must be within",
        ),
    ],
)
def test_show_errors_are_one_line(tmp_path: Path, args: tuple[str, ...], message: str) -> None:
    line = LocalLine(np.array([0.0, 10.0]), np.array([0.0, 0.0]), FRAME)
    write_route_file(tmp_path / "r.geojson", Route("r", line))
    result = _invoke(*args, "--dir", tmp_path, "--output", tmp_path / "o.png")
    assert result.exit_code == 2
    assert result.output.count("\n") == 1 and message in result.output
    assert not (tmp_path / "o.png").exists()


def test_the_file_written_by_import_is_json(tmp_path: Path) -> None:
    _invoke("import", _course_file(tmp_path, 20.0, name="j"), "--dir", tmp_path / "s")
    document = json.loads((tmp_path / "s" / "j.geojson").read_text(encoding="utf-8"))
    assert document["properties"]["name"] == "j"
