"""Route files: GeoJSON (RFC 7946) read strictly, written canonically.

A route file is a Feature, or a FeatureCollection holding exactly one Feature, whose
geometry is a LineString (a bare LineString is read too, when the caller supplies the name).
Its positions are one of two kinds:

* geodetic, as RFC 7946 says: ``[lon, lat]`` or ``[lon, lat, alt]`` in degrees on WGS84 and
  metres above the ellipsoid; any map or GIS tool reads these.
* local east-north metres, ``[east_m, north_m]``, around an origin the file declares. RFC 7946
  removed ``crs``, so the declaration is a property, where GIS tools keep it when they edit a
  file (foreign members are often dropped)::

      "properties": {"name": "north-field", "frame": {"kind": "local_enu",
                     "origin": {"lat_deg": 52.1, "lon_deg": 9.3, "alt_m": 80.0}}}

  A tool that knows nothing of ``frame`` will show such a route as lon/lat near 0°, 0°.

Properties: ``name`` (required), ``directions`` (forward|reverse|both, default both),
``speed_limit_mps``, ``description``, ``recorded`` (ISO 8601), ``vehicle``, ``frame``; null
means absent. Other properties (a map editor's ``stroke``, ``fill``) are ignored and not
written back, except a key that is one of ours in another case or close to one
(``speed_limit``, ``Name``, ``direction``): that is refused, because a misspelt speed limit
silently ignored is a route driven faster than its author meant.

Reading is hostile-input safe: at most `MAX_FILE_BYTES` and `MAX_POINTS` positions, no
NaN/Infinity literals (Python's json accepts them), no duplicate keys, bounded nesting; every
problem raises `RouteFileError` (and nothing else) with a message naming the file and the
member at fault, e.g. ``a.geojson: geometry.coordinates[17][1]: latitude 95.0 outside ±90°``.
"""

from __future__ import annotations

import difflib
import json
import math
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from appliance.config.atomic import write_text_atomic
from appliance.localization.local_frame import LocalFrame
from appliance.routes.route import (
    LOCAL_FRAME_KIND,
    MAX_ALT_M,
    MAX_LOCAL_OFFSET_M,
    MAX_TEXT_CHARS,
    MAX_VEHICLE_CHARS,
    MIN_ALT_M,
    Directions,
    GeodeticLine,
    LocalLine,
    Route,
    name_problem,
    recorded_problem,
    speed_limit_problem,
)

MAX_FILE_BYTES = 20 * 1024 * 1024
MAX_POINTS = 200_000  # 100 km at the recorder's 0.5 m
KNOWN_PROPERTIES = (
    "name", "directions", "speed_limit_mps", "description", "recorded", "vehicle", "frame"
)  # fmt: skip
# The old (2008) GeoJSON crs member is accepted only when it names WGS84 lon/lat.
_WGS84_CRS_NAMES = {
    "urn:ogc:def:crs:OGC:1.3:CRS84",
    "urn:ogc:def:crs:OGC::CRS84",
    "EPSG:4326",
    "urn:ogc:def:crs:EPSG::4326",
}


class RouteFileError(ValueError):
    """A route file (or name) that cannot be used; the message says where and why."""


def _fail(source: str, where: str, what: str) -> NoReturn:
    raise RouteFileError(f"{source}: {where}: {what}" if where else f"{source}: {what}")


def _no_constants(literal: str) -> NoReturn:
    raise ValueError(f"{literal} is not JSON (RFC 8259 has no NaN or Infinity)")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    result: dict[str, Any] = {}
    for key, value in pairs:
        if key in result:
            raise ValueError(f"duplicate key {key[:40]!r}")
        result[key] = value
    return result


def loads_document(data: bytes | str, source: str) -> Any:
    """The JSON value in ``data``, or RouteFileError (size, encoding, syntax, constants)."""
    if len(data) > MAX_FILE_BYTES:
        _fail(source, "", f"larger than {MAX_FILE_BYTES // (1024 * 1024)} MB")
    try:
        text = data.decode("utf-8-sig") if isinstance(data, bytes) else data
        return json.loads(text, parse_constant=_no_constants, object_pairs_hook=_unique_keys)
    except UnicodeDecodeError as exc:
        _fail(source, "", f"not UTF-8 text (byte {exc.start})")
    except json.JSONDecodeError as exc:
        _fail(source, "", f"not JSON: {exc.msg} at line {exc.lineno} column {exc.colno}")
    except RecursionError:
        _fail(source, "", "not a route: JSON nested too deeply")
    except ValueError as exc:  # NaN/Infinity, duplicate keys, integers of >4300 digits
        _fail(source, "", f"not accepted as JSON: {exc}")


def parse_route(data: bytes | str, source: str, *, name: str | None = None) -> Route:
    """The route in a file's contents; ``name`` (when given) replaces properties.name."""
    return route_from_document(loads_document(data, source), source, name=name)


def read_route_file(path: str | Path, *, name: str | None = None) -> Route:
    """Read and parse ``path`` (at most `MAX_FILE_BYTES` are read, whatever the file is)."""
    source = str(path)
    try:
        with open(path, "rb") as handle:
            data = handle.read(MAX_FILE_BYTES + 1)
    except OSError as exc:
        _fail(source, "", f"cannot read: {exc.strerror or exc}")
    return parse_route(data, source, name=name)


def dumps_route(route: Route) -> str:
    """The route as GeoJSON text: properties indented, one position per line (diffs read
    well), floats as Python's shortest repr (read back bit for bit)."""
    feature = route.to_geojson()
    head = json.dumps(
        {"type": "Feature", "properties": feature["properties"]},
        indent=2,
        ensure_ascii=False,
        allow_nan=False,
    )
    positions = ",\n".join(
        "      " + json.dumps(position, allow_nan=False)
        for position in feature["geometry"]["coordinates"]
    )
    return (
        head[: -len("\n}")]
        + ',\n  "geometry": {\n    "type": "LineString",\n    "coordinates": [\n'
        + positions
        + "\n    ]\n  }\n}\n"
    )


def write_route_file(path: str | Path, route: Route) -> None:
    """Replace ``path`` atomically by the route (a reader sees the old file or the new)."""
    write_text_atomic(path, dumps_route(route))


# ---- the document --------------------------------------------------------------------
def route_from_document(document: Any, source: str, *, name: str | None = None) -> Route:
    """Validate a parsed JSON value as a route file; RouteFileError naming where, if not."""
    feature, where = _the_feature(document, source)
    properties = feature.get("properties")
    if properties is None:
        properties = {}
    elif not isinstance(properties, dict):
        _fail(source, f"{where}properties", f"must be an object or null, got {_kind(properties)}")
    _check_crs(feature, source, where)
    props_where = f"{where}properties"
    _refuse_misspellings(properties, source, props_where)
    chosen_name = properties.get("name") if name is None else name
    if chosen_name is None:
        _fail(source, f"{props_where}.name", "missing: a route needs a name (or give --name)")
    _check(source, f"{props_where}.name", name_problem(chosen_name))
    directions = properties.get("directions")
    if directions is None:
        directions = Directions.BOTH.value
    if not isinstance(directions, str) or directions not in {d.value for d in Directions}:
        _fail(
            source,
            f"{props_where}.directions",
            f"must be 'forward', 'reverse' or 'both', got {_short(directions)}",
        )
    speed = properties.get("speed_limit_mps")
    _check(source, f"{props_where}.speed_limit_mps", speed_limit_problem(speed))
    recorded = properties.get("recorded")
    _check(source, f"{props_where}.recorded", recorded_problem(recorded))
    description = _text(properties, "description", MAX_TEXT_CHARS, source, props_where)
    vehicle = _text(properties, "vehicle", MAX_VEHICLE_CHARS, source, props_where)
    origin = _frame(properties.get("frame"), source, f"{props_where}.frame")
    line = _line(feature.get("geometry"), origin, source, f"{where}geometry")
    try:
        return Route(
            name=chosen_name,
            line=line,
            directions=Directions(directions),
            speed_limit_mps=None if speed is None else float(speed),
            description=description,
            recorded=recorded,
            vehicle=vehicle,
        )
    except ValueError as exc:  # the checks above should have said it; never leak another type
        _fail(source, where.rstrip("."), str(exc))


def _short(value: Any) -> str:
    """A value for a message: a string quoted and cut, anything else by its kind."""
    return repr(value[:40]) if isinstance(value, str) else _kind(value)


def _kind(value: Any) -> str:
    if value is None:
        return "null"
    return {dict: "an object", list: "an array", str: "a string", bool: "a boolean"}.get(
        type(value), "a number"
    )


def _check(source: str, where: str, problem: str | None) -> None:
    if problem is not None:
        _fail(source, where, problem)


def _the_feature(document: Any, source: str) -> tuple[dict[str, Any], str]:
    if not isinstance(document, dict):
        _fail(source, "", f"a route file holds a GeoJSON object, not {_kind(document)}")
    kind = document.get("type")
    if kind == "Feature":
        return document, ""
    if kind == "LineString":  # a bare geometry: no properties, so the name must be given
        return {"type": "Feature", "geometry": document, "properties": None}, ""
    if kind == "FeatureCollection":
        _check_crs(document, source, "")
        features = document.get("features")
        if not isinstance(features, list) or len(features) != 1:
            count = len(features) if isinstance(features, list) else _kind(features)
            _fail(source, "features", f"must hold exactly one route Feature, got {count}")
        feature = features[0]
        if not isinstance(feature, dict) or feature.get("type") != "Feature":
            _fail(source, "features[0]", "must be a GeoJSON Feature")
        return feature, "features[0]."
    _fail(
        source,
        "type",
        f"must be 'Feature', 'FeatureCollection' or 'LineString', got {_short(kind)}",
    )


def _check_crs(member: dict[str, Any], source: str, where: str) -> None:
    crs = member.get("crs")
    if crs is None:
        return
    crs_properties = crs.get("properties") if isinstance(crs, dict) else None
    crs_name = crs_properties.get("name") if isinstance(crs_properties, dict) else None
    if not (isinstance(crs_name, str) and crs_name in _WGS84_CRS_NAMES):
        _fail(
            source,
            f"{where}crs",
            "only WGS84 lon/lat is supported (RFC 7946 has no crs); declare local metres "
            "with properties.frame",
        )


def _refuse_misspellings(properties: dict[str, Any], source: str, where: str) -> None:
    for key in properties:
        if key in KNOWN_PROPERTIES:
            continue
        folded = key.lower().replace("-", "_").replace(" ", "_")
        close = difflib.get_close_matches(folded, KNOWN_PROPERTIES, n=1, cutoff=0.8)
        if close:
            _fail(source, f"{where}.{key[:40]}", f"unknown property; did you mean {close[0]!r}?")


def _text(properties: dict[str, Any], key: str, limit: int, source: str, where: str) -> str | None:
    value = properties.get(key)
    if value is not None and (not isinstance(value, str) or len(value) > limit):
        _fail(source, f"{where}.{key}", f"must be a string of at most {limit} characters")
    return value


def _number(value: Any, source: str, where: str, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        _fail(source, where, f"{what} must be a number, got {_kind(value)}")
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        _fail(source, where, f"{what} must be finite")
    return number


def _frame(frame: Any, source: str, where: str) -> LocalFrame | None:
    if frame is None:
        return None
    if not isinstance(frame, dict):
        _fail(source, where, f"must be an object, got {_kind(frame)}")
    if frame.get("kind") != LOCAL_FRAME_KIND:
        _fail(source, f"{where}.kind", f"must be {LOCAL_FRAME_KIND!r} (or leave frame out)")
    origin = frame.get("origin")
    if not isinstance(origin, dict):
        _fail(source, f"{where}.origin", "must be an object with lat_deg, lon_deg[, alt_m]")
    lat = _number(origin.get("lat_deg"), source, f"{where}.origin.lat_deg", "latitude")
    lon = _number(origin.get("lon_deg"), source, f"{where}.origin.lon_deg", "longitude")
    alt_value = origin.get("alt_m")
    alt = 0.0 if alt_value is None else _number(alt_value, source, f"{where}.origin.alt_m", "alt")
    if abs(lat) > 90.0 or abs(lon) > 180.0:
        _fail(source, f"{where}.origin", f"lat {lat} / lon {lon} outside ±90° / ±180°")
    if not MIN_ALT_M <= alt <= MAX_ALT_M:
        _fail(source, f"{where}.origin.alt_m", f"{alt} outside {MIN_ALT_M:g}..{MAX_ALT_M:g} m")
    return LocalFrame(lat, lon, alt)


def _line(
    geometry: Any, origin: LocalFrame | None, source: str, where: str
) -> GeodeticLine | LocalLine:
    if not isinstance(geometry, dict):
        _fail(source, where, f"must be a LineString object, got {_kind(geometry)}")
    if geometry.get("type") != "LineString":
        _fail(source, f"{where}.type", f"must be 'LineString', got {_short(geometry.get('type'))}")
    positions = geometry.get("coordinates")
    where = f"{where}.coordinates"
    if not isinstance(positions, list):
        _fail(source, where, f"must be an array of positions, got {_kind(positions)}")
    if len(positions) > MAX_POINTS:
        _fail(source, where, f"{len(positions)} positions; a route holds at most {MAX_POINTS}")
    if len(positions) < 2:
        _fail(source, where, f"a route needs at least 2 positions, got {len(positions)}")
    sizes = (2,) if origin is not None else (2, 3)
    columns: list[list[float]] = [[], [], []]
    first_size = None
    for index, position in enumerate(positions):
        at = f"{where}[{index}]"
        if not isinstance(position, list) or len(position) not in sizes:
            expected = (
                "[east_m, north_m]" if origin is not None else "[lon, lat] or [lon, lat, alt]"
            )
            _fail(source, at, f"must be {expected}, got {_kind(position)}")
        if first_size is None:
            first_size = len(position)
        elif len(position) != first_size:
            _fail(source, at, f"has {len(position)} numbers, position 0 has {first_size}")
        for axis, value in enumerate(position):
            columns[axis].append(_number(value, source, f"{at}[{axis}]", "a coordinate"))
        _check_position(columns, origin, source, at)
    first, second, third = columns
    if all(v == first[0] for v in first) and all(v == second[0] for v in second):
        _fail(source, where, "a route needs at least 2 distinct positions; all are the same")
    if origin is not None:
        return LocalLine(np.array(first), np.array(second), origin)
    return GeodeticLine(np.array(first), np.array(second), np.array(third) if third else None)


def _check_position(
    columns: list[list[float]], origin: LocalFrame | None, source: str, at: str
) -> None:
    first, second = columns[0][-1], columns[1][-1]
    if origin is not None:
        if math.hypot(first, second) > MAX_LOCAL_OFFSET_M:
            _fail(source, at, f"more than {MAX_LOCAL_OFFSET_M / 1000:g} km from the frame origin")
        return
    if abs(first) > 180.0:
        _fail(source, f"{at}[0]", f"longitude {first} outside ±180° (positions are lon, lat)")
    if abs(second) > 90.0:
        _fail(source, f"{at}[1]", f"latitude {second} outside ±90° (positions are lon, lat)")
    if len(columns[2]) and len(columns[2]) == len(columns[0]):
        alt = columns[2][-1]
        if not MIN_ALT_M <= alt <= MAX_ALT_M:
            _fail(source, f"{at}[2]", f"altitude {alt} m outside {MIN_ALT_M:g}..{MAX_ALT_M:g} m")
