"""A route as the vehicle's autopilot follows it: a named line, its allowed directions and
speed limit, with the geometry kept exactly as the file gave it.

Two kinds of geometry, because the two kinds of source differ: a route drawn on a map or
exported by GIS software is geodetic (RFC 7946: lon, lat[, alt] on WGS84), a route
recorded on a site surveyed in metres is local east-north metres around a declared origin.
Keeping the geometry as given (not converting at load time) means a file written back is
the file read, to the last bit, and that the conversion into the vehicle's frame happens
once, in `points_enu_m`, against whichever origin the vehicle is configured with.

The Route validates itself on construction (``ValueError``): routes built in code (the
recorder's) obey the same rules as routes read from files; `appliance.routes.geojson`
checks a file first so that its errors can name the position or property at fault.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, replace
from datetime import date, datetime
from enum import StrEnum
from functools import cached_property
from typing import Any

import numpy as np
import pymap3d
from numpy.typing import NDArray

from appliance.localization.local_frame import LocalFrame

FloatArray = NDArray[np.float64]

# A name is also a file name in the route store: it must not be able to leave that directory
# ("..", "/"), hide ("."-prefixed: the store's temporary files), or be empty.
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
MAX_SPEED_LIMIT_MPS = 30.0
MAX_TEXT_CHARS = 2000  # description
MAX_VEHICLE_CHARS = 64
# Local positions further than this from their declared origin are refused: a tangent plane
# 100 km out is 785 m above the ground, and such numbers are typos, not routes.
MAX_LOCAL_OFFSET_M = 100_000.0
# Ground vehicles: anything outside this is a unit mistake (feet, millimetres).
MIN_ALT_M = -1_000.0
MAX_ALT_M = 10_000.0
LOCAL_FRAME_KIND = "local_enu"


class Directions(StrEnum):
    """Which way the route may be driven: along the order of its points, against it, or both
    (Stanley et al.'s planner picks the direction from the vehicle's heading, Fig. 5)."""

    FORWARD = "forward"
    REVERSE = "reverse"
    BOTH = "both"


def name_problem(name: object) -> str | None:
    """Why ``name`` cannot name a route (and a file), or None when it can."""
    if not isinstance(name, str):
        return f"must be a string, got {type(name).__name__}"
    if NAME_PATTERN.fullmatch(name) is None:
        return (
            f"{name[:80]!r} is not a route name: 1 to 64 letters, digits, '-', '_' or '.', "
            "starting with a letter or digit"
        )
    return None


def speed_limit_problem(speed_mps: object) -> str | None:
    """Why ``speed_mps`` cannot be a speed limit, or None when it can (None itself can)."""
    if speed_mps is None:
        return None
    if isinstance(speed_mps, bool) or not isinstance(speed_mps, int | float):
        return f"must be a number, got {type(speed_mps).__name__}"
    if not 0.0 < speed_mps <= MAX_SPEED_LIMIT_MPS:  # NaN fails too; ints of any size compare
        return f"must be above 0 and at most {MAX_SPEED_LIMIT_MPS:g} m/s, got {speed_mps!r}"
    return None


def recorded_problem(recorded: object) -> str | None:
    """Why ``recorded`` is not an ISO 8601 date or date-time, or None when it is."""
    if recorded is None:
        return None
    if not isinstance(recorded, str):
        return f"must be an ISO 8601 date string, got {type(recorded).__name__}"
    if len(recorded) > 40:
        return "must be an ISO 8601 date (YYYY-MM-DD) or date-time, at most 40 characters"
    try:
        date.fromisoformat(recorded)
    except ValueError:
        try:
            datetime.fromisoformat(recorded)
        except ValueError:
            return f"{recorded!r} is not an ISO 8601 date (YYYY-MM-DD) or date-time"
    return None


def _frozen(values: Any, what: str) -> FloatArray:
    array = np.array(values, dtype=np.float64)  # a copy: the caller's array may change
    if array.ndim != 1:
        raise ValueError(f"{what} must be one-dimensional, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what} must be finite")
    array.setflags(write=False)
    return array


def _two_distinct(first: FloatArray, second: FloatArray) -> None:
    if len(first) < 2:
        raise ValueError(f"a route needs at least 2 positions, got {len(first)}")
    if np.all(first == first[0]) and np.all(second == second[0]):
        raise ValueError("a route needs at least 2 distinct positions; all are the same")


@dataclass(frozen=True, eq=False)
class GeodeticLine:
    """RFC 7946 positions on WGS84: degrees, and metres above the ellipsoid when given."""

    lon_deg: FloatArray
    lat_deg: FloatArray
    alt_m: FloatArray | None = None

    def __post_init__(self) -> None:
        lon = _frozen(self.lon_deg, "longitudes")
        lat = _frozen(self.lat_deg, "latitudes")
        if len(lon) != len(lat):
            raise ValueError(f"{len(lon)} longitudes but {len(lat)} latitudes")
        if np.any(np.abs(lon) > 180.0) or np.any(np.abs(lat) > 90.0):
            raise ValueError("longitudes must be within ±180° and latitudes within ±90°")
        _two_distinct(lon, lat)
        object.__setattr__(self, "lon_deg", lon)
        object.__setattr__(self, "lat_deg", lat)
        if self.alt_m is not None:
            alt = _frozen(self.alt_m, "altitudes")
            if len(alt) != len(lon):
                raise ValueError(f"{len(lon)} positions but {len(alt)} altitudes")
            if np.any(alt < MIN_ALT_M) or np.any(alt > MAX_ALT_M):
                raise ValueError(f"altitudes must be within {MIN_ALT_M:g}..{MAX_ALT_M:g} m")
            object.__setattr__(self, "alt_m", alt)


@dataclass(frozen=True, eq=False)
class LocalLine:
    """East-north metres around a declared origin (a surveyed site, a recorded track)."""

    east_m: FloatArray
    north_m: FloatArray
    origin: LocalFrame

    def __post_init__(self) -> None:
        east = _frozen(self.east_m, "east positions")
        north = _frozen(self.north_m, "north positions")
        if len(east) != len(north):
            raise ValueError(f"{len(east)} east positions but {len(north)} north positions")
        if np.any(np.hypot(east, north) > MAX_LOCAL_OFFSET_M):
            raise ValueError(
                f"local positions must be within {MAX_LOCAL_OFFSET_M / 1000:g} km of the origin"
            )
        _two_distinct(east, north)
        object.__setattr__(self, "east_m", east)
        object.__setattr__(self, "north_m", north)


@dataclass(frozen=True, eq=False)
class Route:
    """A named line the autopilot may follow; see the module docstring and docs/routes.md.

    Equality is identity (numpy arrays do not compare as a bool); compare the fields."""

    name: str
    line: GeodeticLine | LocalLine
    directions: Directions = Directions.BOTH
    speed_limit_mps: float | None = None
    description: str | None = None
    recorded: str | None = None  # ISO 8601 date or date-time, as written
    vehicle: str | None = None  # the vehicle it was recorded with

    def __post_init__(self) -> None:
        problems = {
            "name": name_problem(self.name),
            "speed_limit_mps": speed_limit_problem(self.speed_limit_mps),
            "recorded": recorded_problem(self.recorded),
        }
        for key, problem in problems.items():
            if problem is not None:
                raise ValueError(f"{key} {problem}")
        object.__setattr__(self, "directions", Directions(self.directions))
        for key, text, limit in (
            ("description", self.description, MAX_TEXT_CHARS),
            ("vehicle", self.vehicle, MAX_VEHICLE_CHARS),
        ):
            if text is not None and (not isinstance(text, str) or len(text) > limit):
                raise ValueError(f"{key} must be a string of at most {limit} characters")

    @property
    def point_count(self) -> int:
        line = self.line
        return len(line.lon_deg) if isinstance(line, GeodeticLine) else len(line.east_m)

    @property
    def own_frame(self) -> LocalFrame:
        """The frame the route is naturally drawn in: its declared origin, or (geodetic) a
        frame at its first position, so that a route can be checked and drawn without the
        vehicle's configured origin."""
        line = self.line
        if isinstance(line, LocalLine):
            return line.origin
        alt_m = 0.0 if line.alt_m is None else float(line.alt_m[0])
        return LocalFrame(float(line.lat_deg[0]), float(line.lon_deg[0]), alt_m)

    def points_enu_m(self, frame: LocalFrame) -> FloatArray:
        """(N, 2) east, north metres in ``frame``: the vehicle's configured frame.

        Geodetic positions go through pymap3d as `LocalFrame.to_local` does (vectorised: a
        route holds up to 200 000 points), without an altitude at the frame origin's
        altitude (the route is on the ground near it; assuming 0 m would shift positions 1 km
        away by ~8 cm per 500 m of elevation). A local route with another origin goes
        through geodetic; with the same origin its points are used as they are."""
        line = self.line
        if isinstance(line, LocalLine):
            if line.origin == frame:
                return np.column_stack((line.east_m, line.north_m))
            lat, lon, alt = pymap3d.enu2geodetic(
                line.east_m, line.north_m, np.zeros_like(line.east_m), *_origin(line.origin)
            )
        else:
            lat, lon = line.lat_deg, line.lon_deg
            alt = np.full_like(lat, frame.origin_alt_m) if line.alt_m is None else line.alt_m
        east, north, _up = pymap3d.geodetic2enu(lat, lon, alt, *_origin(frame))
        return np.column_stack((np.asarray(east, np.float64), np.asarray(north, np.float64)))

    @cached_property
    def own_points_m(self) -> FloatArray:
        """(N, 2) in `own_frame`, computed once (the route is immutable)."""
        points = self.points_enu_m(self.own_frame)
        points.setflags(write=False)
        return points

    @property
    def length_m(self) -> float:
        """Along the line, in `own_frame` (a tangent plane: its scale error at 10 km from the
        origin is below 1e-5, a tenth of a metre over the 10 km)."""
        steps_m = np.diff(self.own_points_m, axis=0)
        return float(np.sum(np.hypot(steps_m[:, 0], steps_m[:, 1])))

    def renamed(self, name: str) -> Route:
        return replace(self, name=name)

    def to_geojson(self) -> dict[str, Any]:
        """The RFC 7946 Feature that `appliance.routes.geojson` reads back to this route."""
        properties: dict[str, Any] = {"name": self.name, "directions": self.directions.value}
        for key in ("speed_limit_mps", "description", "recorded", "vehicle"):
            value = getattr(self, key)
            if value is not None:
                properties[key] = value
        line = self.line
        coordinates: list[list[float]]
        if isinstance(line, LocalLine):
            origin = line.origin
            properties["frame"] = {
                "kind": LOCAL_FRAME_KIND,
                "origin": {
                    "lat_deg": origin.origin_lat_deg,
                    "lon_deg": origin.origin_lon_deg,
                    "alt_m": origin.origin_alt_m,
                },
            }
            coordinates = np.column_stack((line.east_m, line.north_m)).tolist()
        elif line.alt_m is None:
            coordinates = np.column_stack((line.lon_deg, line.lat_deg)).tolist()
        else:
            coordinates = np.column_stack((line.lon_deg, line.lat_deg, line.alt_m)).tolist()
        return {
            "type": "Feature",
            "properties": properties,
            "geometry": {"type": "LineString", "coordinates": coordinates},
        }

    @classmethod
    def from_enu(
        cls,
        name: str,
        points_enu_m: FloatArray,
        frame: LocalFrame,
        *,
        geodetic: bool = True,
        **properties: Any,
    ) -> Route:
        """A route from (N, 2) metres in ``frame``: as RFC 7946 lon/lat without altitudes
        (any map shows it) or, with ``geodetic=False``, as local metres declaring ``frame``
        (no conversion)."""
        points = np.asarray(points_enu_m, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 2:
            raise ValueError(f"points must be (N, 2) east, north metres, got {points.shape}")
        if not geodetic:
            return cls(name, LocalLine(points[:, 0], points[:, 1], frame), **properties)
        lat, lon, _alt = pymap3d.enu2geodetic(
            points[:, 0], points[:, 1], np.zeros(len(points)), *_origin(frame)
        )
        # No altitudes: the points are known in east and north only, and without altitudes
        # `points_enu_m` puts them at the frame origin's (a millimetre's difference at 1 km
        # from the tangent plane's height there).
        return cls(name, GeodeticLine(np.asarray(lon), np.asarray(lat)), **properties)


def _origin(frame: LocalFrame) -> tuple[float, float, float]:
    return frame.origin_lat_deg, frame.origin_lon_deg, frame.origin_alt_m
