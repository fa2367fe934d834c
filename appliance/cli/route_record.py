"""`dbw route record NAME`: the path the operator drives, as a route (Stanley et al.).

Why through the daemon: on the vehicle the daemon owns the receiver's serial port, so the
recorder asks the daemon's control socket for its latest GNSS/INS epoch (``gnss`` in the
status document) at twice the receiver's rate and takes each epoch once, by its
measurement time. What is recorded is the path of the pure pursuit anchor (the forward
array, ``geometry.anchor_point_forward_m``), not the antenna: the tracker steers the anchor
onto the route, so a route recorded at the anchor is driven again where it was driven.

Epochs without a fix, without a heading (the anchor needs one) or with σ above
``positioning.max_sigma_m`` are not taken and are counted. Ctrl-C (or ``--duration``)
ends the recording; the route is smoothed (:mod:`appliance.routes.recording`), checked
for the vehicle and stored. A route the check refuses, or one that cannot be stored, is
written next to where the command ran, never thrown away. A daemon that goes away
mid-recording ends it the same way, with what was recorded.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import click

from appliance.cli.common import CONFIG_OPTION, bad_input, load_or_exit
from appliance.cli.route import DIR_OPTION, EXIT_REFUSED, _store, report_check
from appliance.config import VehicleConfig
from appliance.localization.local_frame import LocalFrame
from appliance.routes import Directions, Route, RouteFileError, write_route_file
from appliance.routes.recording import RecorderParams, RecordingError, RouteRecorder

POLL_S = 0.05  # twice a 10 Hz receiver's rate: every epoch is seen at least once
PROGRESS_EVERY_S = 5.0


@dataclass
class EpochFilter:
    """Which of the daemon's ``gnss`` status entries become recorded anchor positions.

    Pure: a status entry in, the anchor's (east, north, measurement time) or None out,
    with the reason counted."""

    anchor_forward_m: float
    antenna_forward_m: float
    antenna_left_m: float
    max_sigma_m: float
    last_time_s: float | None = None
    skipped: dict[str, int] = field(default_factory=dict)

    def update(self, entry: object) -> tuple[float, float, float] | None:
        if not isinstance(entry, dict):
            return self._skip("no receiver or no epoch yet")
        when = entry.get("measurement_time_s")
        if not isinstance(when, int | float) or not math.isfinite(when):
            return self._skip("no measurement time")
        if self.last_time_s is not None and when <= self.last_time_s:
            return None  # the same epoch seen again: not a skip
        self.last_time_s = float(when)
        if entry.get("fix") is not True:
            return self._skip("no fix")
        values = [entry.get(key) for key in ("east_m", "north_m", "yaw_deg")]
        if not all(isinstance(v, int | float) and math.isfinite(v) for v in values):
            return self._skip("no position or heading")
        sigma = entry.get("sigma_m")
        if isinstance(sigma, int | float) and sigma > self.max_sigma_m:
            return self._skip(f"sigma above {self.max_sigma_m:g} m")
        east, north, yaw_deg = (float(v) for v in values)  # type: ignore[arg-type]
        yaw = math.radians(yaw_deg)
        forward_m = self.anchor_forward_m - self.antenna_forward_m
        left_m = -self.antenna_left_m
        return (
            east + forward_m * math.cos(yaw) - left_m * math.sin(yaw),
            north + forward_m * math.sin(yaw) + left_m * math.cos(yaw),
            float(when),
        )

    def _skip(self, why: str) -> tuple[float, float, float] | None:
        self.skipped[why] = self.skipped.get(why, 0) + 1
        return None


def epoch_filter(config: VehicleConfig) -> EpochFilter:
    positioning = config.positioning
    return EpochFilter(
        anchor_forward_m=config.geometry.anchor_point_forward_m,
        antenna_forward_m=positioning.antenna_forward_m,
        antenna_left_m=positioning.antenna_left_m,
        max_sigma_m=positioning.max_sigma_m,
    )


@click.command("record")
@click.argument("name")
@click.option(
    "--duration",
    "duration_s",
    type=click.FloatRange(min=0.0, min_open=True),
    help="Stop after this many seconds (default: at Ctrl-C).",
)
@click.option(
    "--spacing-m",
    type=click.FloatRange(min=0.05, max=10.0),
    default=RecorderParams().spacing_m,
    show_default=True,
    help="Keep a point when it is this far from the last one kept.",
)
@click.option(
    "--directions",
    type=click.Choice([d.value for d in Directions]),
    default=Directions.BOTH.value,
    show_default=True,
    help="The directions the route may be driven in.",
)
@click.option(
    "--speed-limit-mps", type=click.FloatRange(min=0.0, min_open=True), help="Speed limit."
)
@click.option("--description", help="A line about the route, stored with it.")
@click.option("--force", is_flag=True, help="Replace a stored route of the same name.")
@click.option(
    "--socket", "socket_path", metavar="PATH", default=None, help="The daemon's control socket."
)
@CONFIG_OPTION
@DIR_OPTION
def route_record(
    name: str,
    duration_s: float | None,
    spacing_m: float,
    directions: str,
    speed_limit_mps: float | None,
    description: str | None,
    force: bool,
    socket_path: str | None,
    config_name: str | None,
    directory: str | None,
) -> None:
    """Record the path driven from now until Ctrl-C (or --duration) as route NAME.

    Exit 0 stored; 1 refused by the check (then kept as ./NAME.geojson to edit and
    import), nothing recorded, or ended by a lost daemon; 2 bad input or no daemon."""
    from appliance.cli.control import _fail, _socket_path, running_config_name
    from appliance.control_client import query_sync
    from appliance.control_protocol import ControlSocketError

    config = load_or_exit(running_config_name(config_name))  # the daemon's vehicle
    origin = config.positioning.origin
    if origin is None:
        bad_input("positioning.origin is not set: routes are stored in lon/lat around it")
    frame = LocalFrame(origin.lat_deg, origin.lon_deg, origin.alt_m)
    store = _store(directory, config)
    read_only = store.read_only_problem()
    if read_only is not None:
        bad_input(read_only)
    try:
        store.path_for(name)
        if store.exists(name) and not force:
            bad_input(f"route {name!r} exists in {store.directory}; --force replaces it")
    except RouteFileError as exc:
        bad_input(str(exc))
    path = _socket_path(socket_path, config_name)
    try:
        query_sync(path, {"op": "status"})
    except ControlSocketError as exc:
        _fail(exc)

    recorder = RouteRecorder(RecorderParams(spacing_m=spacing_m))
    feed = epoch_filter(config)
    click.echo(f"recording {name!r}: drive the route; Ctrl-C ends it", err=True)
    started = time.monotonic()
    shown = started
    lost: str | None = None
    try:
        while duration_s is None or time.monotonic() - started < duration_s:
            try:
                doc = query_sync(path, {"op": "status"})
            except ControlSocketError as exc:
                lost = str(exc)
                break
            status = doc.get("status") if doc.get("ok") else None
            point = feed.update(status.get("gnss") if isinstance(status, dict) else None)
            if point is not None:
                recorder.update(*point)
            if time.monotonic() - shown >= PROGRESS_EVERY_S:
                shown = time.monotonic()
                click.echo(f"  {recorder.points_kept} points kept, {_skipped(feed)}", err=True)
            time.sleep(POLL_S)
    except KeyboardInterrupt:
        pass
    if lost is not None:
        click.echo(f"dbw: the daemon went away ({lost}); keeping what was recorded", err=True)
    try:
        chosen, summary = recorder.finish(
            name,
            frame,
            directions=Directions(directions),
            speed_limit_mps=speed_limit_mps,
            description=description,
            recorded=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
            vehicle=config.name,
        )
    except RecordingError as exc:
        click.echo(f"dbw: nothing stored: {exc} ({_skipped(feed)})", err=True)
        sys.exit(EXIT_REFUSED)
    click.echo(
        f"recorded {name!r}: {summary.length_m:.1f} m in {summary.duration_s:.1f} s, "
        f"{summary.points_kept} points from {summary.fixes_received} epochs "
        f"({summary.points_dropped} closer than {spacing_m:g} m), tightest turn "
        f"{'none' if math.isinf(summary.min_radius_m) else f'{summary.min_radius_m:.1f} m'}"
        f"{', TRUNCATED at the point limit' if summary.truncated else ''}; {_skipped(feed)}"
    )
    report = report_check(chosen, config, name, None)
    if not report.refused:
        try:
            stored = store.save(chosen, overwrite=force)
        except RouteFileError as exc:
            click.echo(f"dbw: cannot store it: {exc}", err=True)
        else:
            click.echo(f"stored route {name!r} as {stored}")
            sys.exit(EXIT_REFUSED if lost is not None else 0)
    _keep(chosen, name)
    sys.exit(EXIT_REFUSED)


def _keep(chosen: Route, name: str) -> None:
    """The route in the current directory under a name no file has; failing that, on
    standard output: a drive is not thrown away because a directory is read-only."""
    kept = Path.cwd() / f"{name}.geojson"
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    if kept.exists():
        kept = kept.with_name(f"{name}-{stamp}.geojson")
    try:
        if kept.exists():
            raise FileExistsError(f"{kept} exists")
        write_route_file(kept, chosen)
    except (OSError, RouteFileError) as exc:
        click.echo(f"dbw: cannot write {kept} ({exc}); the route follows as GeoJSON", err=True)
        click.echo(json.dumps(chosen.to_geojson()))
        return
    click.echo(f"kept in {kept}: edit it, then `dbw route import {kept.name}`", err=True)


def _skipped(feed: EpochFilter) -> str:
    if not feed.skipped:
        return "no epoch skipped"
    return "skipped: " + ", ".join(f"{why} {n}" for why, n in sorted(feed.skipped.items()))
