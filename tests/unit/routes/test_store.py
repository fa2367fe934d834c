"""The route directory: names that cannot leave it, atomic saves, listing and loading."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from appliance.config import VehicleConfig, load_config
from appliance.localization.local_frame import LocalFrame
from appliance.routes.geojson import RouteFileError, dumps_route
from appliance.routes.route import Directions, LocalLine, Route
from appliance.routes.store import BUILTIN_ROUTES, RouteStore, routes_dir

FRAME = LocalFrame(52.2, 9.3)


def _route(name: str, length_m: float = 10.0) -> Route:
    line = LocalLine(np.array([0.0, length_m]), np.array([0.0, 0.0]), FRAME)
    return Route(name, line, Directions.REVERSE, 1.5)


def test_the_default_directory_is_in_the_state_dir() -> None:
    assert routes_dir(load_config("husky")) == Path("/var/lib/dbw/routes")


@pytest.mark.parametrize(
    "name",
    ["..", ".", "../x", "a/b", "/etc/passwd", ".hidden", "", "x" * 65, "a b", "ä", "a\x00b", "-x"],
)
def test_names_that_are_not_route_names_are_refused(name: str, tmp_path: Path) -> None:
    store = RouteStore(tmp_path / "routes")
    with pytest.raises(RouteFileError, match="is not a route name"):
        store.path_for(name)
    with pytest.raises(RouteFileError):
        store.load(name)
    assert not (tmp_path / "routes").exists()


@pytest.mark.parametrize("name", ["a", "A-1_b.c", "x" * 64, "0..1"])
def test_route_names_stay_in_the_directory(name: str, tmp_path: Path) -> None:
    path = RouteStore(tmp_path).path_for(name)
    assert path.parent == tmp_path and path.name == f"{name}.geojson"


def test_save_load_and_list(tmp_path: Path) -> None:
    store = RouteStore(tmp_path / "routes")
    assert store.list() == []  # no directory yet: no routes
    path = store.save(_route("b-route", 12.5))
    store.save(_route("a-route"))
    assert path == tmp_path / "routes" / "b-route.geojson"
    assert path.read_text(encoding="utf-8") == dumps_route(_route("b-route", 12.5))
    # No temporary files left behind.
    assert sorted(p.name for p in (tmp_path / "routes").iterdir()) == [
        "a-route.geojson",
        "b-route.geojson",
    ]
    loaded = store.load("b-route")
    assert loaded.name == "b-route" and loaded.length_m == 12.5
    listed = store.list()
    rows = [(e.name, e.length_m, e.point_count, e.directions, e.speed_limit_mps) for e in listed]
    assert rows == [
        ("a-route", 10.0, 2, Directions.REVERSE, 1.5),
        ("b-route", 12.5, 2, Directions.REVERSE, 1.5),
    ]
    assert all(e.error is None for e in listed)


def test_an_existing_route_is_replaced_only_when_asked(tmp_path: Path) -> None:
    store = RouteStore(tmp_path)
    store.save(_route("r", 10.0))
    with pytest.raises(RouteFileError, match="exists already"):
        store.save(_route("r", 20.0))
    assert store.load("r").length_m == 10.0
    store.save(_route("r", 20.0), overwrite=True)
    assert store.load("r").length_m == 20.0


def test_a_file_naming_another_route_or_broken_is_listed_with_its_error(tmp_path: Path) -> None:
    store = RouteStore(tmp_path)
    (tmp_path / "mislabelled.geojson").write_text(dumps_route(_route("other")), encoding="utf-8")
    (tmp_path / "broken.geojson").write_text("{", encoding="utf-8")
    (tmp_path / "bad name.geojson").write_text(dumps_route(_route("x")), encoding="utf-8")
    (tmp_path / ".tmp.geojson").write_text("{", encoding="utf-8")
    with pytest.raises(RouteFileError, match=r"properties\.name is 'other', not the file's name"):
        store.load("mislabelled")
    with pytest.raises(RouteFileError, match="no route 'missing'"):
        store.load("missing")
    errors = {entry.name: entry.error for entry in store.list()}
    assert set(errors) == {"bad name", "broken", "mislabelled"}
    assert "is not a route name" in str(errors["bad name"])
    assert "not JSON" in str(errors["broken"])
    assert "not the file's name" in str(errors["mislabelled"])


def test_an_unwritable_directory_is_a_route_file_error(tmp_path: Path) -> None:
    (tmp_path / "routes").write_text("a file, not a directory", encoding="utf-8")
    with pytest.raises(RouteFileError, match="cannot write"):
        RouteStore(tmp_path / "routes").save(_route("r"))


def test_the_builtin_routes_are_listed_and_loaded_but_never_written() -> None:
    data = load_config("husky").model_dump(exclude_unset=True)
    data["route"] = {"routes_dir": BUILTIN_ROUTES}
    config = VehicleConfig.model_validate(data)
    store = RouteStore(routes_dir(config))
    names = [entry.name for entry in store.list() if entry.error is None]
    assert "offroad-mile" in names
    route = store.load("offroad-mile")
    assert 1600.0 < route.length_m < 1620.0  # the simulator's off-road mile, every 2 m
    with pytest.raises(RouteFileError, match="built-in example routes"):
        store.save(route, overwrite=True)
