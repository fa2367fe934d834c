"""`dbw localize --left FILE --right FILE`: the launcher localizer replayed on recordings.

The two front scanners' recordings (`dbw lms111 record`, taken at the same time on one
host, so their receive times share one monotonic clock) are merged by receive time and
fed scan by scan to the `LauncherLocalizer` the vehicle runs, each scan at its receive
time (``t_s`` = ``now_s``: a replay has no transport delay). After each scan the estimate
is printed: status and quality, the vehicle centre's pose in the launcher frame with its
σ's, the NIS of the last update of each kind and the counts; at the end a summary (how
long it was lost or degraded, when the first pose came). ``--png`` draws the track as
Qian et al.'s Fig. 9 does, with ±2σ bands.

The launcher's dimensions are the built-in site's unless ``--site`` names another site
file; the poses are in the launcher's own frame (Fig. 7), wherever the site puts it.
This module replays; what is printed and drawn of the track is `appliance.cli.localize_report`.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import click

from appliance.cli.common import CONFIG_OPTION, bad_input, draw_png, load_or_exit
from appliance.cli.localize_report import (
    TrackPoint,
    draw_track,
    point_json,
    point_text,
    recording_json,
    summary_text,
    track_summary,
)
from appliance.cli.recordings import (
    EXIT_TRUNCATED,
    SCANNERS,
    load_calibration_or_exit,
    pose_json,
    read_recording_or_exit,
    scanner_endpoints,
    sensor_angles_rad,
    warn_truncated,
)

if TYPE_CHECKING:
    from appliance.config.models import VehicleConfig
    from appliance.localization.launcher_map import LauncherMap
    from appliance.sim.builders import LauncherSpec
    from drivers.geometry import Pose2D
    from drivers.lms111.recording import RecordedScans
    from drivers.lms111.scan import Scan


@click.command()
@click.option("--left", "left_file", metavar="FILE", help="Recording of the left LMS111.")
@click.option("--right", "right_file", metavar="FILE", help="Recording of the right LMS111.")
@CONFIG_OPTION
@click.option(
    "--calibration",
    "calibration_file",
    metavar="FILE",
    help="The scanners' calibrated mounts and range offsets (`dbw calibrate scanners`).",
)
@click.option(
    "--site",
    metavar="SITE.toml|NAME",
    help="A site file whose [launcher] table gives the launcher's dimensions. "
    "Default: the built-in launcher.",
)
@click.option(
    "--png", "png_file", metavar="OUT.png", help="Draw the track and heading with ±2σ bands."
)
@click.option("--json", "as_json", is_flag=True, help="JSON lines: one per scan, a summary last.")
def localize(
    left_file: str | None,
    right_file: str | None,
    config_name: str | None,
    calibration_file: str | None,
    site: str | None,
    png_file: str | None,
    as_json: bool,
) -> None:
    """Replay two scanners' recordings through the launcher localizer; print the track.

    Poses are the vehicle centre's, in the launcher frame (origin at the front board's
    centre, x into the launcher, y to the left). Exit status 0, 1 when a recording was
    cut off (what was read is used), 2 for bad input.
    """
    from appliance.config.parts import scanner_setups
    from appliance.localization.launcher_localizer import LauncherLocalizer, LocalizerParams

    if not left_file or not right_file:
        bad_input("the localizer needs both front scanners: --left FILE --right FILE")
    config = load_or_exit(config_name)
    calibration = load_calibration_or_exit(calibration_file, config)
    launcher, launcher_pose, site_name = _launcher_or_exit(site)
    files = {"left": left_file, "right": right_file}
    recordings = {name: read_recording_or_exit(path) for name, path in files.items()}
    _check_pair(recordings, config)
    merged = _merged(recordings)
    setups = scanner_setups(config, calibration)
    localizer = LauncherLocalizer(setups, LocalizerParams(launcher=launcher))
    first_s = merged[0][0]
    track: list[TrackPoint] = []
    for t_s, name, scan in merged:
        localizer.update(name, scan.ranges_m, sensor_angles_rad(scan), t_s, t_s)
        point = TrackPoint(t_s, name, scan.scan_counter, localizer.estimate(t_s))
        track.append(point)
        click.echo(
            json.dumps(point_json(point, first_s)) if as_json else point_text(point, first_s)
        )
    png_note = None
    if png_file is not None:
        title = f"{left_file} + {right_file} ({config.name}, {site_name})"
        png_note = draw_png(png_file, lambda plt: draw_track(plt, track, launcher, config, title))
    summary = {
        "kind": "summary",
        "vehicle": config.name,
        "calibration": calibration_file,
        "site": site_name,
        "launcher_in_site": pose_json(launcher_pose),
        "frame": "launcher",
        "recordings": {name: recording_json(r) for name, r in recordings.items()},
        **track_summary(track),
        "stale_scans": localizer.stale_scans,
        "feature_rejections": dict(sorted(localizer.feature_rejections.items())),
        "png": png_file if png_file is not None and png_note is None else None,
    }
    click.echo(json.dumps(summary) if as_json else summary_text(summary))
    if png_note is not None:
        click.echo(f"{png_file}: {png_note}", err=True)
    if warn_truncated(list(recordings.values())):
        sys.exit(EXIT_TRUNCATED)


# ---- inputs --------------------------------------------------------------------------
def _launcher_or_exit(site: str | None) -> tuple[LauncherMap, Pose2D, str]:
    """The launcher's map from a site file's [launcher] table, its pose in the site, and
    the site's name; the built-in launcher without ``--site``."""
    from appliance.localization.launcher_map import LauncherMap
    from drivers.geometry import Pose2D

    if site is None:
        return LauncherMap(), Pose2D(0.0, 0.0, 0.0), "built-in launcher"
    spec = _launcher_spec(site)
    launcher = LauncherMap(
        front_board_width_m=spec.front_board_width_m,
        side_board_length_m=spec.side_board_length_m,
        side_board_sweep_deg=spec.side_board_sweep_deg,
        cylinder_radius_m=spec.cylinder_radius_m,
        cylinder_lateral_m=spec.cylinder_lateral_m,
        cylinder_ahead_m=spec.cylinder_ahead_m,
    )
    return launcher, spec.pose, site


def _launcher_spec(site: str) -> LauncherSpec:
    import tomllib
    from importlib import resources

    from appliance.sim.builders import LauncherSpec
    from appliance.sim.site_file import (
        SITES_FOLDER,
        SITES_PACKAGE,
        SiteError,
        builtin_site_names,
        load_site,
    )

    try:
        load_site(site)  # every table checked, every problem named with its field
    except SiteError as exc:
        bad_input(exc.render().replace("\n", " "))
    if site in builtin_site_names():
        folder = resources.files(SITES_PACKAGE).joinpath(SITES_FOLDER)
        text = folder.joinpath(f"{site}.toml").read_text(encoding="utf-8")
    else:
        text = Path(site).read_text(encoding="utf-8")
    table = tomllib.loads(text).get("launcher")
    if table is None:
        bad_input(f"{site}: the site has no [launcher] table: nothing to localize against")
    return LauncherSpec.model_validate(table)


def _check_pair(recordings: Mapping[str, RecordedScans], config: VehicleConfig) -> None:
    """Two recordings of two scanners, taken at the same time: anything else is bad input."""
    left, right = recordings["left"], recordings["right"]
    shared = {s.serial_number for s in left.scans} & {s.serial_number for s in right.scans}
    if shared:
        bad_input(
            f"the left and right recordings come from the same scanner (serial number "
            f"{min(shared)}): give each scanner's own recording"
        )
    spans = {name: _span(r.scans) for name, r in recordings.items()}
    (l0, l1), (r0, r1) = spans["left"], spans["right"]
    if l1 < r0 or r1 < l0:
        bad_input(
            f"the recordings do not overlap in time (receive times: left {l0:.3f}..{l1:.3f} s, "
            f"right {r0:.3f}..{r1:.3f} s): record both scanners at once on one host"
        )
    endpoints = scanner_endpoints(config)
    if endpoints["left"] == endpoints["right"]:
        return  # the vehicle file cannot tell them apart (a simulated vehicle)
    for name, recording in recordings.items():
        other = "right" if name == "left" else "left"
        if (recording.header.host, recording.header.port) == endpoints[other]:
            click.echo(
                f"warning: {recording.path} was recorded from {recording.header.host}:"
                f"{recording.header.port}, the {other} scanner's endpoint in the vehicle "
                f"file, and is given as --{name}",
                err=True,
            )


def _receive_time_s(scan: Scan) -> float:
    return scan.host_receive_time_s if scan.host_receive_time_s is not None else 0.0


def _span(scans: Sequence[Scan]) -> tuple[float, float]:
    times = [_receive_time_s(scan) for scan in scans]
    return min(times), max(times)


def _merged(recordings: Mapping[str, RecordedScans]) -> list[tuple[float, str, Scan]]:
    """Every scan with ranges, both scanners', in order of receive time (a stable sort:
    a tie keeps left before right)."""
    merged = [
        (_receive_time_s(scan), name, scan)
        for name in SCANNERS
        for scan in recordings[name].scans
        if scan.ranges_m.size
    ]
    merged.sort(key=lambda item: item[0])
    return merged
