"""The vehicle's routes: a directory of ``NAME.geojson`` files, by default
``<paths.state_dir>/routes``.

A plain directory (not a database) so that routes can be copied on and off the vehicle,
diffed and edited with any tool; the file name is the route's name, so a name is checked
before it becomes a path (no ``..``, no ``/``, no hidden files: the atomic writer's temporary
files start with a dot) and a file whose inside names another route is refused rather than
selected under the wrong name.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from appliance.config.models import VehicleConfig
from appliance.routes.geojson import RouteFileError, read_route_file, write_route_file
from appliance.routes.route import Directions, Route, name_problem

ROUTE_SUFFIX = ".geojson"
# The example routes shipped with the package (the simulated Husky's off-road mile): a
# simulated vehicle can drive one without anything installed; they cannot be written.
BUILTIN_ROUTES = "builtin:routes"


def builtin_routes_dir() -> Path:
    return Path(str(resources.files("appliance.config").joinpath("routes")))


def routes_dir(config: VehicleConfig) -> Path:
    """Where ``config``'s vehicle keeps its routes (``route.routes_dir``, by default
    ``<paths.state_dir>/routes``; ``builtin:routes``: the shipped examples)."""
    if config.route.routes_dir == BUILTIN_ROUTES:
        return builtin_routes_dir()
    if config.route.routes_dir:
        return Path(config.route.routes_dir)
    return Path(config.paths.state_dir) / "routes"


@dataclass(frozen=True)
class StoredRoute:
    """One line of `dbw route list`: what a file holds, or why it cannot be used."""

    name: str
    path: Path
    length_m: float | None = None
    point_count: int | None = None
    directions: Directions | None = None
    speed_limit_mps: float | None = None
    error: str | None = None


class RouteStore:
    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)

    def path_for(self, name: str) -> Path:
        """The file of route ``name``; RouteFileError for a name that is not one (and so
        could name a file outside the directory)."""
        problem = name_problem(name)
        if problem is not None:
            raise RouteFileError(f"route name {problem}")
        path = self.directory / f"{name}{ROUTE_SUFFIX}"
        # Belt and braces: the pattern admits no separator, but say so in code too.
        if path.parent != self.directory or path.name != f"{name}{ROUTE_SUFFIX}":
            raise RouteFileError(f"route name {name!r} would leave {self.directory}")
        return path

    def exists(self, name: str) -> bool:
        return self.path_for(name).is_file()

    def load(self, name: str) -> Route:
        path = self.path_for(name)
        if not path.is_file():
            raise RouteFileError(f"no route {name!r} in {self.directory}")
        route = read_route_file(path)
        if route.name != name:
            raise RouteFileError(
                f"{path}: properties.name is {route.name!r}, not the file's name {name!r}; "
                "rename one of them"
            )
        return route

    def read_only_problem(self) -> str | None:
        """Why routes cannot be stored here, or None: known before a route is recorded."""
        if self.directory == builtin_routes_dir():
            return (
                f"{self.directory} holds the built-in example routes, which are not written: "
                "set route.routes_dir to a directory of your own (or give --dir)"
            )
        return None

    def save(self, route: Route, *, overwrite: bool = False) -> Path:
        """Write ``route`` as ``NAME.geojson``, atomically; an existing route is replaced
        only with ``overwrite``."""
        problem = self.read_only_problem()
        if problem is not None:
            raise RouteFileError(problem)
        path = self.path_for(route.name)
        if path.exists() and not overwrite:
            raise RouteFileError(f"{path}: route {route.name!r} exists already")
        try:
            write_route_file(path, route)
        except OSError as exc:
            raise RouteFileError(f"{path}: cannot write: {exc.strerror or exc}") from exc
        return path

    def list(self) -> list[StoredRoute]:
        """Every ``*.geojson`` in the directory, by name; unreadable ones with their error.
        A missing directory holds no routes."""
        try:
            paths = sorted(
                self.directory.glob(f"*{ROUTE_SUFFIX}"), key=lambda p: p.name[: -len(ROUTE_SUFFIX)]
            )
        except OSError:
            return []
        entries = []
        for path in paths:
            name = path.name[: -len(ROUTE_SUFFIX)]
            if name.startswith("."):
                continue  # the atomic writer's temporary files
            try:
                route = self.load(name)
            except RouteFileError as exc:
                entries.append(StoredRoute(name, path, error=str(exc)))
                continue
            entries.append(
                StoredRoute(
                    name,
                    path,
                    length_m=route.length_m,
                    point_count=route.point_count,
                    directions=route.directions,
                    speed_limit_mps=route.speed_limit_mps,
                )
            )
        return entries
