"""`dbw route ...`: the routes the autopilot follows (Stanley et al.'s route files).

`list` shows the vehicle's routes (``<paths.state_dir>/routes``, or ``--dir``), `show` draws
one, `check` says whether the vehicle can drive a file (exit 0: yes, 1: refused, with every
problem and where it is), `import` checks a file and stores it. `select` and `record`
(:mod:`appliance.cli.route_record`) talk to the running daemon.

A bad file, name or option is one line on stderr and exit 2, never a traceback.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import click

from appliance.cli.common import CONFIG_OPTION, bad_input, draw_png, load_or_exit
from appliance.cli.lazy import LazyGroup
from appliance.config import VehicleConfig
from appliance.localization.local_frame import LocalFrame
from appliance.routes import (
    CheckParams,
    CheckReport,
    Directions,
    LocalLine,
    Route,
    RouteFileError,
    RouteStore,
    Severity,
    check_route,
    min_turn_radius_m,
    read_route_file,
    routes_dir,
)

EXIT_REFUSED = 1
_ARROWS_PER_ROUTE = 8

DIR_OPTION = click.option(
    "--dir",
    "directory",
    metavar="DIR",
    help="The route directory. Default: routes/ in the vehicle's paths.state_dir.",
)


def _store(directory: str | None, config: VehicleConfig) -> RouteStore:
    return RouteStore(directory if directory is not None else routes_dir(config))


def _limit(speed_mps: float | None) -> str:
    return "-" if speed_mps is None else f"{speed_mps:g}"


def _describe(route: Route) -> str:
    limit = "none" if route.speed_limit_mps is None else f"{route.speed_limit_mps:g} m/s"
    kind = "local metres" if isinstance(route.line, LocalLine) else "lon/lat"
    return (
        f"route {route.name!r}: {route.point_count} points ({kind}), {route.length_m:.1f} m, "
        f"directions {route.directions.value}, speed limit {limit}"
    )


@click.group(cls=LazyGroup, lazy_subcommands={"record": "appliance.cli.route_record:route_record"})
def route() -> None:
    """List, show, check and import the routes the autopilot follows (GeoJSON)."""


@route.command("list")
@CONFIG_OPTION
@DIR_OPTION
def route_list(config_name: str | None, directory: str | None) -> None:
    """Print the vehicle's routes as a table (unreadable files with their error)."""
    store = _store(directory, load_or_exit(config_name))
    entries = store.list()
    if not entries:
        click.echo(f"no routes in {store.directory}")
        return
    header = ("NAME", "LENGTH_M", "POINTS", "DIRECTIONS", "LIMIT_MPS", "FILE")
    rows = [header]
    for entry in entries:
        if entry.error is not None:
            rows.append((entry.name, "-", "-", "-", "-", f"{entry.path}  ({entry.error})"))
            continue
        rows.append((
            entry.name,
            f"{entry.length_m:.1f}",
            str(entry.point_count),
            entry.directions.value if entry.directions else "-",
            _limit(entry.speed_limit_mps),
            str(entry.path),
        ))  # fmt: skip
    widths = [max(len(row[k]) for row in rows) for k in range(len(header) - 1)]
    for row in rows:
        cells = [cell.ljust(width) for cell, width in zip(row[:-1], widths, strict=True)]
        click.echo("  ".join([*cells, row[-1]]))


def _load(name_or_file: str, store: RouteStore) -> Route:
    """A stored route by name, or a file when the argument looks like a path."""
    try:
        if "/" in name_or_file or name_or_file.endswith((".geojson", ".json")):
            return read_route_file(name_or_file)
        return store.load(name_or_file)
    except RouteFileError as exc:
        bad_input(str(exc))


@route.command("show")
@click.argument("name")
@CONFIG_OPTION
@DIR_OPTION
@click.option("--output", "output", metavar="FILE.png", help="Where to draw it. Default: NAME.png.")
@click.option("--vehicle-east-m", type=float, help="Draw the vehicle at this east, metres.")
@click.option("--vehicle-north-m", type=float, help="The vehicle's north position, metres.")
@click.option("--origin-lat-deg", type=float, help="Draw in the frame around this origin.")
@click.option("--origin-lon-deg", type=float, help="The origin's longitude.")
@click.option("--origin-alt-m", type=float, default=0.0, show_default=True, help="Its altitude.")
def route_show(
    name: str,
    config_name: str | None,
    directory: str | None,
    output: str | None,
    vehicle_east_m: float | None,
    vehicle_north_m: float | None,
    origin_lat_deg: float | None,
    origin_lon_deg: float | None,
    origin_alt_m: float,
) -> None:
    """Draw route NAME (a stored route, or a .geojson file) in east/north metres: start and
    end marked, arrows for the allowed directions, the vehicle where given.

    The frame is the one given by --origin-*, else the route's declared origin, else a frame
    at the route's first point; --vehicle-* are metres in that frame."""
    chosen = _load(name, _store(directory, load_or_exit(config_name)))
    if (vehicle_east_m is None) != (vehicle_north_m is None):
        bad_input("give both --vehicle-east-m and --vehicle-north-m, or neither")
    if (origin_lat_deg is None) != (origin_lon_deg is None):
        bad_input("give both --origin-lat-deg and --origin-lon-deg, or neither")
    frame, frame_text = chosen.own_frame, "the route's own frame"
    if origin_lat_deg is not None and origin_lon_deg is not None:
        try:
            frame = LocalFrame(origin_lat_deg, origin_lon_deg, origin_alt_m)
        except ValueError as exc:
            bad_input(str(exc))
        frame_text = "the given origin"
    frame_text += f" (origin lat {frame.origin_lat_deg:.7f}, lon {frame.origin_lon_deg:.7f})"
    vehicle = None
    if vehicle_east_m is not None and vehicle_north_m is not None:
        vehicle = (vehicle_east_m, vehicle_north_m)
    path = output if output is not None else f"{chosen.name}.png"
    click.echo(_describe(chosen))
    note = draw_png(path, lambda plt: _draw(plt, chosen, frame, frame_text, vehicle))
    if note is not None:
        click.echo(f"{path}: {note}", err=True)
    else:
        click.echo(f"drawn in {frame_text}: {path}")


def _check_or_exit(
    chosen: Route, config: VehicleConfig, source: str, min_radius_m: float | None
) -> CheckReport:
    """Check ``chosen`` for the vehicle and print the findings; exit 1 when refused."""
    report = report_check(chosen, config, source, min_radius_m)
    if report.refused:
        sys.exit(EXIT_REFUSED)
    return report


def report_check(
    chosen: Route, config: VehicleConfig, source: str, min_radius_m: float | None
) -> CheckReport:
    """Check ``chosen`` for the vehicle and print the findings and the verdict."""
    needed_m = min_radius_m if min_radius_m is not None else min_turn_radius_m(config)
    report = check_route(chosen.own_points_m, needed_m, CheckParams(), chosen.own_frame)
    click.echo(f"{source}: {_describe(chosen)}")
    if chosen.vehicle is not None and chosen.vehicle != config.name:
        click.echo(f"note: recorded with vehicle {chosen.vehicle!r}, checked for {config.name!r}")
    tightest = report.min_radius_found_m
    click.echo(
        f"vehicle {config.name!r}: turns down to {needed_m:.2f} m radius; the route's tightest "
        f"is {'none (straight)' if math.isinf(tightest) else f'{tightest:.2f} m'} "
        f"(circles over {report.curvature_span_m:g} m of the route)"
    )
    for problem in report.problems:
        click.echo(f"{problem.severity.value}: {problem.message}")
    if report.problems_not_listed:
        click.echo(f"... and {report.problems_not_listed} more")
    counts = {s: sum(p.severity is s for p in report.problems) for s in Severity}
    refusals, warnings = counts[Severity.REFUSE], counts[Severity.WARN]
    if report.refused:
        click.echo(f"{source}: REFUSED ({refusals} refusal(s), {warnings} warning(s))")
    else:
        click.echo(f"{source}: OK ({warnings} warning(s))")
    return report


MIN_RADIUS_OPTION = click.option(
    "--min-radius-m",
    type=click.FloatRange(min=0.0, min_open=True),
    help="Check against this turning radius instead of the vehicle's (full steer, kinematic).",
)


@route.command("check")
@click.argument("file")
@CONFIG_OPTION
@MIN_RADIUS_OPTION
def route_check(file: str, config_name: str | None, min_radius_m: float | None) -> None:
    """Can the vehicle drive FILE? Exit 0 yes (warnings allowed), 1 refused, 2 bad file.

    Refused: turns tighter than the vehicle can make. Warned: places where the route comes
    back near itself, long gaps between points, repeated points. Each names where."""
    config = load_or_exit(config_name)
    try:
        chosen = read_route_file(file)
    except RouteFileError as exc:
        bad_input(str(exc))
    _check_or_exit(chosen, config, file, min_radius_m)


@route.command("import")
@click.argument("file")
@click.option("--name", help="Store it under this name (default: the file's properties.name).")
@click.option("--force", is_flag=True, help="Replace a stored route of the same name.")
@CONFIG_OPTION
@DIR_OPTION
@MIN_RADIUS_OPTION
def route_import(
    file: str,
    name: str | None,
    force: bool,
    config_name: str | None,
    directory: str | None,
    min_radius_m: float | None,
) -> None:
    """Check FILE for the vehicle and store it; a refused route is not stored (exit 1)."""
    config = load_or_exit(config_name)
    store = _store(directory, config)
    try:
        chosen = read_route_file(file, name=name)
        store.path_for(chosen.name)
        if store.exists(chosen.name) and not force:
            bad_input(f"route {chosen.name!r} exists in {store.directory}; --force replaces it")
    except RouteFileError as exc:
        bad_input(str(exc))
    _check_or_exit(chosen, config, file, min_radius_m)
    try:
        path = store.save(chosen, overwrite=force)
    except RouteFileError as exc:
        bad_input(str(exc))
    click.echo(f"stored route {chosen.name!r} as {path}")


# ---- drawing -------------------------------------------------------------------------
def _draw(
    plt: Any,
    chosen: Route,
    frame: LocalFrame,
    frame_text: str,
    vehicle: tuple[float, float] | None,
) -> Any:
    """The route in east/north metres: the line, start (green) and end (red), arrows for
    the directions it may be driven, and the vehicle."""
    import numpy as np

    points = chosen.points_enu_m(frame)
    figure, axes = plt.subplots(figsize=(9, 8))
    axes.plot(points[:, 0], points[:, 1], color="tab:blue", linewidth=1.5, zorder=2)
    axes.plot(*points[0], marker="o", color="tab:green", markersize=9, zorder=4, label="start")
    axes.plot(*points[-1], marker="s", color="tab:red", markersize=8, zorder=4, label="end")
    steps = np.hypot(*np.diff(points, axis=0).T)
    s_m = np.concatenate(([0.0], np.cumsum(steps)))
    style = {Directions.FORWARD: "-|>", Directions.REVERSE: "<|-", Directions.BOTH: "<|-|>"}
    # Arrowheads only: a short tail and head straddling the point give the direction there.
    arrow_m = min(0.25, s_m[-1] / 100.0)
    for k in range(1, _ARROWS_PER_ROUTE + 1):
        at_m = s_m[-1] * k / (_ARROWS_PER_ROUTE + 1)
        tail = [np.interp(at_m - arrow_m, s_m, points[:, i]) for i in (0, 1)]
        head = [np.interp(at_m + arrow_m, s_m, points[:, i]) for i in (0, 1)]
        axes.annotate(
            "", xy=head, xytext=tail, zorder=3,
            arrowprops={
                "arrowstyle": style[chosen.directions], "color": "tab:blue",
                "mutation_scale": 22, "shrinkA": 0, "shrinkB": 0,
            },
        )  # fmt: skip
    if vehicle is not None:
        axes.plot(*vehicle, marker="^", color="black", markersize=10, zorder=5, label="vehicle")
    limit = "no limit" if chosen.speed_limit_mps is None else f"{chosen.speed_limit_mps:g} m/s"
    axes.set_title(
        f"{chosen.name}: {s_m[-1]:.1f} m, {chosen.directions.value}, {limit}\n{frame_text}",
        fontsize=10,
    )
    axes.set_xlabel("east [m]")
    axes.set_ylabel("north [m]")
    axes.set_aspect("equal", adjustable="datalim")
    axes.grid(True, linewidth=0.3)
    axes.legend(loc="best")
    return figure


@route.command("select")
@click.argument("name")
@click.option(
    "--socket", "socket_path", metavar="PATH", default=None, help="The daemon's control socket."
)
@CONFIG_OPTION
def route_select(name: str, socket_path: str | None, config_name: str | None) -> None:
    """Ask the running daemon to follow route NAME from the next engagement (the vehicle
    must not be under automatic control). Exit 0 selected, 1 refused (the reason is
    printed), 2 no daemon."""
    from appliance.cli.control import _fail, _socket_path
    from appliance.control_client import query_sync
    from appliance.control_protocol import ControlSocketError

    path = _socket_path(socket_path, config_name)
    try:
        reply = query_sync(path, {"op": "route", "select": name})
    except ControlSocketError as exc:
        _fail(exc)
    if not reply.get("ok"):
        click.echo(f"dbw: the daemon answered: {reply.get('error', '?')}", err=True)
        sys.exit(1)
    click.echo(str(reply.get("message", "")))
    sys.exit(0 if reply.get("accepted") else 1)
