"""Routes as files: GeoJSON LineStrings the autopilot follows (Stanley et al.'s route files).

`route` is the model, `geojson` reads and writes the files (RFC 7946 lon/lat, or local
east-north metres with a declared frame; docs/routes.md), `check` says whether a vehicle can
drive one (turning radius, self-overlaps, gaps), `store` keeps them in the vehicle's state
directory, `recording` turns a driven track into one. Pure except `geojson`'s and `store`'s
file reading and writing; the vehicle's frame comes in as a `LocalFrame`.
"""

from appliance.routes.check import (
    CheckParams,
    CheckReport,
    Place,
    Problem,
    ProblemKind,
    Severity,
    check_route,
    min_turn_radius_m,
)
from appliance.routes.geojson import (
    RouteFileError,
    dumps_route,
    parse_route,
    read_route_file,
    write_route_file,
)
from appliance.routes.recording import (
    RecorderParams,
    RecordingError,
    RecordingSummary,
    RouteRecorder,
)
from appliance.routes.route import Directions, GeodeticLine, LocalLine, Route
from appliance.routes.store import RouteStore, StoredRoute, routes_dir

__all__ = [
    "CheckParams",
    "CheckReport",
    "Directions",
    "GeodeticLine",
    "LocalLine",
    "Place",
    "Problem",
    "ProblemKind",
    "RecorderParams",
    "RecordingError",
    "RecordingSummary",
    "Route",
    "RouteFileError",
    "RouteRecorder",
    "RouteStore",
    "Severity",
    "StoredRoute",
    "check_route",
    "dumps_route",
    "min_turn_radius_m",
    "parse_route",
    "read_route_file",
    "routes_dir",
    "write_route_file",
]
