"""Route files: written and read back bit for bit, converted into the vehicle's frame as
`LocalFrame` converts each point, and every malformed file refused with RouteFileError
naming the file and the member at fault (and never any other exception)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from appliance.localization.local_frame import LocalFrame
from appliance.routes.geojson import (
    MAX_FILE_BYTES,
    MAX_POINTS,
    RouteFileError,
    dumps_route,
    parse_route,
    read_route_file,
    write_route_file,
)
from appliance.routes.route import Directions, GeodeticLine, LocalLine, Route

FRAME = LocalFrame(52.2, 9.3, 80.0)


def _same(a: Route, b: Route) -> None:
    for key in ("name", "directions", "speed_limit_mps", "description", "recorded", "vehicle"):
        assert getattr(a, key) == getattr(b, key), key
    assert type(a.line) is type(b.line)
    if isinstance(a.line, GeodeticLine) and isinstance(b.line, GeodeticLine):
        np.testing.assert_array_equal(a.line.lon_deg, b.line.lon_deg)
        np.testing.assert_array_equal(a.line.lat_deg, b.line.lat_deg)
        assert (a.line.alt_m is None) == (b.line.alt_m is None)
        if a.line.alt_m is not None and b.line.alt_m is not None:
            np.testing.assert_array_equal(a.line.alt_m, b.line.alt_m)
    elif isinstance(a.line, LocalLine) and isinstance(b.line, LocalLine):
        np.testing.assert_array_equal(a.line.east_m, b.line.east_m)
        np.testing.assert_array_equal(a.line.north_m, b.line.north_m)
        assert a.line.origin == b.line.origin


def _geodetic_route(with_alt: bool = True) -> Route:
    lon = np.array([9.3, 9.30001, 9.30003, 9.3001])
    lat = np.array([52.2, 52.20002, 52.20001, 52.2])
    alt = np.array([80.0, 80.5, 81.25, 79.0]) if with_alt else None
    return Route(
        "north-field_2.v1",
        GeodeticLine(lon, lat, alt),
        Directions.FORWARD,
        2.5,
        description="along the hedge, ümlaut",
        recorded="2024-05-01",
        vehicle="husky",
    )


def _local_route() -> Route:
    east = np.array([0.0, 3.0, 3.0, 10.5])
    north = np.array([0.0, 4.0, 10.0, 10.0])
    return Route("yard", LocalLine(east, north, FRAME), recorded="2024-05-01T10:20:30+02:00")


@pytest.mark.parametrize("route", [_geodetic_route(), _geodetic_route(False), _local_route()])
def test_a_route_is_read_back_as_written(route: Route, tmp_path: Path) -> None:
    path = tmp_path / "a.geojson"
    write_route_file(path, route)
    _same(read_route_file(path), route)
    assert dumps_route(read_route_file(path)) == path.read_text(encoding="utf-8")


def test_the_file_is_rfc_7946_geojson() -> None:
    document = json.loads(dumps_route(_geodetic_route()))
    assert document["type"] == "Feature"
    assert document["geometry"]["type"] == "LineString"
    assert document["geometry"]["coordinates"][1] == [9.30001, 52.20002, 80.5]  # lon, lat, alt
    assert document["properties"] == {
        "name": "north-field_2.v1",
        "directions": "forward",
        "speed_limit_mps": 2.5,
        "description": "along the hedge, ümlaut",
        "recorded": "2024-05-01",
        "vehicle": "husky",
    }
    local = json.loads(dumps_route(_local_route()))
    assert local["properties"]["frame"] == {
        "kind": "local_enu",
        "origin": {"lat_deg": 52.2, "lon_deg": 9.3, "alt_m": 80.0},
    }
    assert local["geometry"]["coordinates"][1] == [3.0, 4.0]


finite = st.floats(allow_nan=False, allow_infinity=False)


@st.composite
def routes(draw: st.DrawFn) -> Route:
    count = draw(st.integers(2, 30))
    if draw(st.booleans()):
        origin = LocalFrame(
            draw(st.floats(-90, 90)), draw(st.floats(-180, 180)), draw(st.floats(-1000, 10_000))
        )
        coord = st.floats(-70_000.0, 70_000.0)
        east = draw(st.lists(coord, min_size=count, max_size=count))
        north = draw(st.lists(coord, min_size=count, max_size=count))
        assume(len(set(zip(east, north, strict=True))) > 1)
        line: GeodeticLine | LocalLine = LocalLine(np.array(east), np.array(north), origin)
    else:
        lon = draw(st.lists(st.floats(-180, 180), min_size=count, max_size=count))
        lat = draw(st.lists(st.floats(-90, 90), min_size=count, max_size=count))
        assume(len(set(zip(lon, lat, strict=True))) > 1)
        alt = draw(st.none() | st.lists(st.floats(-1000, 10_000), min_size=count, max_size=count))
        line = GeodeticLine(np.array(lon), np.array(lat), None if alt is None else np.array(alt))
    return Route(
        draw(st.from_regex(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", fullmatch=True)),
        line,
        draw(st.sampled_from(Directions)),
        draw(st.none() | st.floats(0.0, 30.0, exclude_min=True)),
        draw(st.none() | st.text(max_size=50)),
        draw(st.none() | st.dates().map(str)),
        draw(st.none() | st.text(max_size=64)),
    )


@given(routes())
@settings(
    max_examples=50, suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow]
)
def test_any_route_round_trips_exactly(route: Route) -> None:
    _same(parse_route(dumps_route(route), "x"), route)


def test_geodetic_points_go_into_the_vehicle_frame_as_local_frame_puts_each() -> None:
    route = _geodetic_route()
    line = route.line
    assert isinstance(line, GeodeticLine) and line.alt_m is not None
    expected = [
        FRAME.to_local(la, lo, al)[:2]
        for lo, la, al in zip(line.lon_deg, line.lat_deg, line.alt_m, strict=True)
    ]
    np.testing.assert_allclose(route.points_enu_m(FRAME), expected, atol=1e-9)
    flat = _geodetic_route(with_alt=False)
    flat_line = flat.line
    assert isinstance(flat_line, GeodeticLine)
    # Without altitudes the route lies at the frame origin's altitude (80 m here).
    expected = [
        FRAME.to_local(la, lo, 80.0)[:2]
        for lo, la in zip(flat_line.lon_deg, flat_line.lat_deg, strict=True)
    ]
    np.testing.assert_allclose(flat.points_enu_m(FRAME), expected, atol=1e-9)


def test_local_points_are_used_as_they_are_in_their_own_frame() -> None:
    route = _local_route()
    np.testing.assert_array_equal(route.points_enu_m(FRAME), [[0, 0], [3, 4], [3, 10], [10.5, 10]])
    assert route.length_m == pytest.approx(5.0 + 6.0 + 7.5, abs=1e-12)


def test_local_points_with_another_origin_go_through_geodetic() -> None:
    route = _local_route()
    other = LocalFrame(52.201, 9.302, 60.0)
    expected = []
    for east, north in route.points_enu_m(FRAME):
        lat, lon, alt = FRAME.to_geodetic(east, north, 0.0)
        expected.append(other.to_local(lat, lon, alt)[:2])
    got = route.points_enu_m(other)
    np.testing.assert_allclose(got, expected, atol=1e-6)
    assert np.hypot(*np.diff(got, axis=0).T).sum() == pytest.approx(18.5, abs=1e-4)


def test_a_bare_linestring_and_a_feature_collection_are_routes() -> None:
    coordinates = [[9.3, 52.2], [9.3001, 52.2]]
    bare = parse_route(
        json.dumps({"type": "LineString", "coordinates": coordinates}), "b", name="b"
    )
    assert bare.name == "b" and bare.directions is Directions.BOTH
    collection = {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "properties": {"name": "c", "stroke": "#ff0000"},
                "geometry": {"type": "LineString", "coordinates": coordinates},
            }
        ],
    }
    assert parse_route(json.dumps(collection), "c").name == "c"
    assert parse_route(json.dumps(collection), "c", name="renamed").name == "renamed"


# ---- refusals ------------------------------------------------------------------------
def _valid() -> Any:
    return json.loads(dumps_route(_geodetic_route()))


def _with(path: str, value: Any) -> str:
    """The valid document with the member at ``path`` (dots, [i]) replaced; ``...``
    deletes it."""
    document = _valid()
    keys = [
        int(k) if k.isdigit() else k for k in path.replace("[", ".").replace("]", "").split(".")
    ]
    target: Any = document
    for key in keys[:-1]:
        target = target[key]
    if value is ...:
        del target[keys[-1]]
    else:
        target[keys[-1]] = value
    return json.dumps(document)


LOCAL_FRAME = {"kind": "local_enu", "origin": {"lat_deg": 52.0, "lon_deg": 9.0}}


def _local(coordinates: list[list[float]]) -> str:
    """A local route with these positions."""
    geometry = {"type": "LineString", "coordinates": coordinates}
    properties = {"name": "a", "frame": LOCAL_FRAME}
    return json.dumps({"type": "Feature", "properties": properties, "geometry": geometry})


BAD_DOCUMENTS = [
    # (document text, what the message must name)
    ("", "not JSON"),
    ("{", "not JSON"),
    ('{"type": "Feature", "x": NaN}', "NaN"),
    ('{"type": "Feature", "x": Infinity}', "Infinity"),
    ('{"type": "Feature", "x": -Infinity}', "Infinity"),
    ('{"type": "Feature", "type": "Feature"}', "duplicate key 'type'"),
    ("[" * 100_000 + "]" * 100_000, "JSON"),
    ('{"type": "Feature", "x": 1' + "0" * 5000 + "}", "not accepted as JSON"),
    ("[]", "not an array"),
    ('"Feature"', "not a string"),
    ('{"type": "Point"}', "type: must be 'Feature'"),
    (
        '{"type": "FeatureCollection", "features": []}',
        "features: must hold exactly one route Feature, got 0",
    ),
    ('{"type": "FeatureCollection", "features": [1]}', "features[0]: must be a GeoJSON Feature"),
    (_with("type", "Topology"), "type: must be 'Feature'"),
    (_with("properties", []), "properties: must be an object or null"),
    (_with("properties.name", ...), "properties.name: missing"),
    (_with("properties.name", "../etc"), "properties.name: '../etc' is not a route name"),
    (_with("properties.name", ".hidden"), "properties.name: '.hidden' is not a route name"),
    (_with("properties.name", "x" * 65), "properties.name"),
    (_with("properties.name", 7), "properties.name: must be a string"),
    (_with("properties.directions", "sideways"), "properties.directions: must be 'forward'"),
    (_with("properties.speed_limit_mps", 0), "properties.speed_limit_mps: must be above 0"),
    (_with("properties.speed_limit_mps", 30.5), "properties.speed_limit_mps: must be above 0"),
    (_with("properties.speed_limit_mps", "3"), "properties.speed_limit_mps: must be a number"),
    (_with("properties.speed_limit_mps", True), "properties.speed_limit_mps: must be a number"),
    (_with("properties.speed_limit_mps", 10**400), "properties.speed_limit_mps: must be above 0"),
    (_with("properties.recorded", "yesterday"), "properties.recorded: 'yesterday' is not"),
    (_with("properties.recorded", 20240501), "properties.recorded: must be an ISO 8601"),
    (_with("properties.description", "x" * 2001), "properties.description: must be a string"),
    (_with("properties.vehicle", ["husky"]), "properties.vehicle: must be a string"),
    (
        _with("properties.speed_limit", 3.0),
        "properties.speed_limit: unknown property; did you mean 'speed_limit_mps'?",
    ),
    (_with("properties.Name", "x"), "properties.Name: unknown property; did you mean 'name'?"),
    (_with("properties.direction", "both"), "did you mean 'directions'?"),
    (_with("properties.frame", "local"), "properties.frame: must be an object"),
    (_with("properties.frame", {"kind": "utm"}), "properties.frame.kind: must be 'local_enu'"),
    (
        _with("properties.frame", {"kind": "local_enu"}),
        "properties.frame.origin: must be an object",
    ),
    (
        _with("properties.frame", {"kind": "local_enu", "origin": {"lat_deg": 91, "lon_deg": 9}}),
        "properties.frame.origin: lat 91.0",
    ),
    (
        _with("properties.frame", {"kind": "local_enu", "origin": {"lon_deg": 9}}),
        "properties.frame.origin.lat_deg: latitude must be a number, got null",
    ),
    (_with("crs", {"type": "name", "properties": {"name": "EPSG:3857"}}), "crs: only WGS84"),
    (_with("crs", {"type": "name", "properties": []}), "crs: only WGS84"),
    (_with("geometry", None), "geometry: must be a LineString object, got null"),
    (
        _with("geometry.type", "MultiLineString"),
        "geometry.type: must be 'LineString', got 'MultiLineString'",
    ),
    (_with("geometry.coordinates", {}), "geometry.coordinates: must be an array of positions"),
    (
        _with("geometry.coordinates", [[9.3, 52.2]]),
        "geometry.coordinates: a route needs at least 2 positions, got 1",
    ),
    (_with("geometry.coordinates", [[9.3, 52.2]] * 3), "at least 2 distinct positions"),
    (
        _with("geometry.coordinates[2]", [9.3, 52.2, 1.0, 2.0]),
        "geometry.coordinates[2]: must be [lon, lat] or [lon, lat, alt], got an array",
    ),
    (
        _with("geometry.coordinates[2]", [9.3, 52.2]),
        "geometry.coordinates[2]: has 2 numbers, position 0 has 3",
    ),
    (_with("geometry.coordinates[2]", "9.3,52.2"), "geometry.coordinates[2]: must be [lon, lat]"),
    (
        _with("geometry.coordinates[3][0]", 181.0),
        "geometry.coordinates[3][0]: longitude 181.0 outside ±180°",
    ),
    (
        _with("geometry.coordinates[3][1]", -90.5),
        "geometry.coordinates[3][1]: latitude -90.5 outside ±90°",
    ),
    (
        _with("geometry.coordinates[1][2]", 12_000.0),
        "geometry.coordinates[1][2]: altitude 12000.0 m",
    ),
    (
        _with("geometry.coordinates[1][1]", None),
        "geometry.coordinates[1][1]: a coordinate must be a number, got null",
    ),
    (
        _with("geometry.coordinates[1][0]", False),
        "geometry.coordinates[1][0]: a coordinate must be a number, got a boolean",
    ),
    (
        _with("geometry.coordinates[1][0]", 10**400),
        "geometry.coordinates[1][0]: a coordinate must be finite",
    ),
    (
        _local([[0, 0], [1, 2, 3]]),
        "geometry.coordinates[1]: must be [east_m, north_m]",
    ),
    (
        _local([[0, 0], [100001, 0]]),
        "geometry.coordinates[1]: more than 100 km from the frame origin",
    ),
]


@pytest.mark.parametrize(("text", "named"), BAD_DOCUMENTS)
def test_a_bad_file_is_refused_naming_where(text: str, named: str) -> None:
    with pytest.raises(RouteFileError) as raised:
        parse_route(text, "routes/bad.geojson")
    message = str(raised.value)
    assert message.startswith("routes/bad.geojson: ")
    assert named in message
    assert "\n" not in message


def test_too_many_points_and_too_many_bytes_are_refused() -> None:
    coordinates = "[" + ",".join(["[9.3,52.2]"] * (MAX_POINTS + 1)) + "]"
    text = '{"type": "LineString", "coordinates": ' + coordinates + "}"
    with pytest.raises(RouteFileError, match=f"geometry.coordinates: {MAX_POINTS + 1} positions"):
        parse_route(text, "big", name="big")
    with pytest.raises(RouteFileError, match="big: larger than 20 MB"):
        parse_route(b" " * (MAX_FILE_BYTES + 1), "big")


def test_unreadable_files_are_refused(tmp_path: Path) -> None:
    with pytest.raises(RouteFileError, match=r"missing\.geojson: cannot read"):
        read_route_file(tmp_path / "missing.geojson")
    with pytest.raises(RouteFileError, match="cannot read"):
        read_route_file(tmp_path)
    (tmp_path / "latin1.geojson").write_bytes(b'{"name": "\xe9"}')
    with pytest.raises(RouteFileError, match=r"not UTF-8 text \(byte 10\)"):
        read_route_file(tmp_path / "latin1.geojson")


# ---- fuzz: a Route or RouteFileError, never anything else -----------------------------
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=5)
    ),
    max_leaves=30,
)
MEMBERS = [
    "type",
    "properties",
    "properties.name",
    "properties.directions",
    "properties.speed_limit_mps",
    "properties.recorded",
    "properties.description",
    "properties.vehicle",
    "properties.frame",
    "geometry",
    "geometry.type",
    "geometry.coordinates",
    "geometry.coordinates[0]",
    "geometry.coordinates[1][0]",
    "geometry.coordinates[2][1]",
    "geometry.coordinates[3][2]",
    "crs",
]


def _parse_or_refuse(text: str | bytes) -> None:
    try:
        route = parse_route(text, "fuzz")
    except RouteFileError:
        return
    assert isinstance(route, Route)
    assert np.all(np.isfinite(route.own_points_m))


@given(json_values)
def test_any_json_document_is_a_route_or_refused(value: Any) -> None:
    _parse_or_refuse(json.dumps(value))  # NaN and Infinity included: json.dumps writes them


@given(st.sampled_from(MEMBERS), json_values)
def test_any_value_in_any_member_is_a_route_or_refused(member: str, value: Any) -> None:
    _parse_or_refuse(_with(member, value))


@given(st.sampled_from(MEMBERS), json_values)
def test_any_value_in_a_local_route_is_a_route_or_refused(member: str, value: Any) -> None:
    document = json.loads(_with(member, value))
    if isinstance(document.get("properties"), dict) and member != "properties.frame":
        document["properties"]["frame"] = LOCAL_FRAME
    _parse_or_refuse(json.dumps(document))


@given(st.binary(max_size=200))
def test_any_bytes_are_a_route_or_refused(data: bytes) -> None:
    _parse_or_refuse(data)


@given(st.integers(0, 400), st.binary(min_size=1, max_size=3))
def test_a_valid_file_with_bytes_changed_is_a_route_or_refused(at: int, junk: bytes) -> None:
    data = dumps_route(_geodetic_route()).encode()
    at = at % len(data)
    _parse_or_refuse(data[:at] + junk + data[at + len(junk) :])


def test_geodetic_lines_refuse_bad_arrays_in_code_too() -> None:
    with pytest.raises(ValueError, match="finite"):
        GeodeticLine(np.array([9.0, math.nan]), np.array([52.0, 52.0]))
    with pytest.raises(ValueError, match="at least 2 distinct"):
        LocalLine(np.zeros(3), np.zeros(3), FRAME)
    with pytest.raises(ValueError, match="name"):
        Route("../x", LocalLine(np.array([0.0, 1.0]), np.zeros(2), FRAME))
