"""`dbw features FILE`: what the feature extraction makes of each scan of a recording.

The same extraction the localizer runs (Qian et al. 3.2.3, Fig. 5: clusters by
adjacent-point distance, isolated and dispersed points dropped, lines by split-and-merge,
cylinders by arc fitting), on the whole scan, in the vehicle frame through the scanner's
mount (the calibrated one with ``--calibration``). Per scan: the segments, the lines
(Hessian r and α, length, ends and whether each end is occluded, σ's), the cylinders
(centre, σ, points) and what was rejected and why. ``--png`` draws one scan as the
paper's Fig. 5 does. A recording cut off inside a record is used up to the cut, with a
warning and exit status 1, as `dbw lms111 decode` does (the reading is shared with
`dbw localize`: `appliance.cli.recordings`).
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import click

from appliance.cli.common import CONFIG_OPTION, bad_input, draw_png, load_or_exit
from appliance.cli.recordings import (
    EXIT_TRUNCATED,
    SCANNERS,
    load_calibration_or_exit,
    pose_json,
    read_recording_or_exit,
    scanner_of,
    sensor_angles_rad,
    warn_truncated,
)

if TYPE_CHECKING:
    from appliance.perception.types import CircleFeature, LineFeature, ScanFeatures
    from drivers.geometry import Pose2D
    from drivers.lms111.scan import Scan

# The drawing shows what lies within this distance of the scanner: the launcher's
# approach zone is about 10 m (Qian et al. 4.1); a yard's far walls would shrink it away.
CLOSE_UP_M = 15.0


@click.command()
@click.argument("file", type=click.Path(dir_okay=False))
@CONFIG_OPTION
@click.option(
    "--scanner",
    type=click.Choice(SCANNERS),
    default=None,
    help="Which front scanner recorded FILE (its mount places the features). Default: "
    "the one whose endpoint in the vehicle file is the recording's.",
)
@click.option(
    "--calibration",
    "calibration_file",
    metavar="FILE",
    help="Use the scanner's calibrated mount and range offset from this calibration file.",
)
@click.option(
    "--scan",
    "scan_index",
    type=click.IntRange(min=0),
    default=None,
    help="Only this scan (0 = the first of the recording). Default: every scan.",
)
@click.option(
    "--png",
    "png_file",
    metavar="OUT.png",
    help="Draw one scan (--scan, default the first): points by segment, lines, cylinders.",
)
@click.option("--json", "as_json", is_flag=True, help="JSON lines: one per scan, a summary last.")
def features(
    file: str,
    config_name: str | None,
    scanner: str | None,
    calibration_file: str | None,
    scan_index: int | None,
    png_file: str | None,
    as_json: bool,
) -> None:
    """The segments, lines and cylinders in each scan of an LMS111 recording.

    Features are in the vehicle frame (x forward, y left), placed through the scanner's
    mount; a line is x cos α + y sin α = r. Exit status 0, 1 when the recording was cut
    off (what was read is used), 2 for bad input.
    """
    from appliance.config.parts import scanner_setups
    from appliance.perception.features import extract_features

    config = load_or_exit(config_name)
    calibration = load_calibration_or_exit(calibration_file, config)
    recording = read_recording_or_exit(file)
    name = scanner or scanner_of(recording.header, config, file)
    setup = scanner_setups(config, calibration)[name]
    scans = recording.scans
    if scan_index is not None and scan_index >= len(scans):
        bad_input(f"{file}: no scan {scan_index}: the recording holds {len(scans)} scans")
    chosen = range(len(scans)) if scan_index is None else (scan_index,)
    counts: dict[str, list[int]] = {"lines": [], "cylinders": []}
    drawn: tuple[Scan, ScanFeatures] | None = None
    for index in chosen:
        scan = scans[index]
        found = extract_features(
            scan.ranges_m, sensor_angles_rad(scan), setup.mount,
            range_offset_m=setup.range_offset_m,
        )  # fmt: skip
        counts["lines"].append(len(found.lines))
        counts["cylinders"].append(len(found.circles))
        if drawn is None:
            drawn = (scan, found)
        click.echo(
            json.dumps(_scan_json(index, scan, found))
            if as_json
            else _scan_text(index, scan, found)
        )
    png_note = None
    if png_file is not None and drawn is not None:
        shown_scan, shown_features = drawn
        title = f"{file}: scan {chosen[0]} of the {name} scanner, vehicle frame"
        png_note = draw_png(
            png_file,
            lambda plt: _draw(
                plt, shown_scan, shown_features, setup.mount, setup.range_offset_m, title
            ),
        )
    summary = {
        "kind": "summary",
        "file": file,
        "vehicle": config.name,
        "scanner": name,
        "frame": "vehicle",
        "mount": pose_json(setup.mount),
        "range_offset_m": setup.range_offset_m,
        "scans": len(scans),
        "scans_shown": len(chosen),
        "dropped_telegrams": recording.dropped_telegrams,
        "truncated": recording.truncated,
        "lines_per_scan": _spread(counts["lines"]),
        "cylinders_per_scan": _spread(counts["cylinders"]),
        "png": png_file if png_file is not None and png_note is None else None,
    }
    click.echo(json.dumps(summary) if as_json else _summary_text(summary))
    if png_note is not None:
        click.echo(f"{png_file}: {png_note}", err=True)
    if warn_truncated([recording]):
        sys.exit(EXIT_TRUNCATED)


def _spread(values: Sequence[int]) -> dict[str, float]:
    return {
        "min": min(values),
        "mean": round(sum(values) / len(values), 3),
        "max": max(values),
    }


def _sigmas(covariance: Any) -> tuple[float, float]:
    return (
        math.sqrt(max(float(covariance[0][0]), 0.0)),
        math.sqrt(max(float(covariance[1][1]), 0.0)),
    )


def line_json(line: LineFeature) -> dict[str, Any]:
    sigma_r, sigma_alpha = _sigmas(line.covariance)
    return {
        "r_m": round(line.r_m, 5),
        "alpha_deg": round(math.degrees(line.alpha_rad), 5),
        "sigma_r_m": round(sigma_r, 6),
        "sigma_alpha_deg": round(math.degrees(sigma_alpha), 6),
        "length_m": round(line.length_m, 5),
        "start_xy_m": [round(v, 5) for v in line.start_xy_m],
        "end_xy_m": [round(v, 5) for v in line.end_xy_m],
        "start_occluded": line.start_occluded,
        "end_occluded": line.end_occluded,
        "n_points": line.n_points,
        "rms_m": round(line.rms_m, 6),
        "first_index": line.first_index,
        "last_index": line.last_index,
    }


def cylinder_json(circle: CircleFeature) -> dict[str, Any]:
    sigma_x, sigma_y = _sigmas(circle.covariance)
    return {
        "cx_m": round(circle.cx_m, 5),
        "cy_m": round(circle.cy_m, 5),
        "radius_m": circle.radius_m,
        "sigma_x_m": round(sigma_x, 6),
        "sigma_y_m": round(sigma_y, 6),
        "n_points": circle.n_points,
        "rms_m": round(circle.rms_m, 6),
        "first_index": circle.first_index,
        "last_index": circle.last_index,
    }


def _scan_json(index: int, scan: Scan, found: ScanFeatures) -> dict[str, Any]:
    return {
        "kind": "scan",
        "scan_index": index,
        "host_receive_time_s": scan.host_receive_time_s,
        "scan_counter": scan.scan_counter,
        "serial_number": scan.serial_number,
        "beams": int(scan.ranges_m.size),
        "echoes": int((scan.ranges_m > 0).sum()),
        "segments": [list(segment) for segment in found.segments],  # half-open beam ranges
        "lines": [line_json(line) for line in found.lines],
        "cylinders": [cylinder_json(circle) for circle in found.circles],
        "rejections": dict(sorted(found.rejections.items())),
    }


def _end(occluded: bool) -> str:
    return "occluded" if occluded else "true"


def _scan_text(index: int, scan: Scan, found: ScanFeatures) -> str:
    rejected = ", ".join(f"{k} {v}" for k, v in sorted(found.rejections.items())) or "none"
    time_s = scan.host_receive_time_s if scan.host_receive_time_s is not None else math.nan
    lines = [
        f"scan {index} t={time_s:.3f} s #{scan.scan_counter}: {scan.ranges_m.size} beams, "
        f"{int((scan.ranges_m > 0).sum())} echoes, {len(found.segments)} segments, "
        f"{len(found.lines)} lines, {len(found.circles)} cylinders (rejected: {rejected})"
    ]
    for line in found.lines:
        sigma_r, sigma_alpha = _sigmas(line.covariance)
        (x0, y0), (x1, y1) = line.start_xy_m, line.end_xy_m
        lines.append(
            f"  line      r {line.r_m:7.3f} m  α {math.degrees(line.alpha_rad):+8.2f}°  "
            f"length {line.length_m:6.2f} m  ({x0:+.2f}, {y0:+.2f}) to ({x1:+.2f}, {y1:+.2f}) "
            f"ends {_end(line.start_occluded)}/{_end(line.end_occluded)}  "
            f"σ r {sigma_r * 1e3:.1f} mm α {math.degrees(sigma_alpha):.3f}°  "
            f"n {line.n_points} rms {line.rms_m * 1e3:.1f} mm"
        )
    for circle in found.circles:
        sigma_x, sigma_y = _sigmas(circle.covariance)
        lines.append(
            f"  cylinder  centre ({circle.cx_m:+.3f}, {circle.cy_m:+.3f}) m  "
            f"σ {sigma_x * 1e3:.1f}/{sigma_y * 1e3:.1f} mm  "
            f"n {circle.n_points} rms {circle.rms_m * 1e3:.1f} mm"
        )
    return "\n".join(lines)


def _summary_text(summary: dict[str, Any]) -> str:
    mount = summary["mount"]
    lines, cylinders = summary["lines_per_scan"], summary["cylinders_per_scan"]
    png = f"; drew {summary['png']}" if summary["png"] else ""
    return (
        f"{summary['scans_shown']} of {summary['scans']} scans of the {summary['scanner']} "
        f"scanner ({summary['vehicle']}: mount x {mount['x_m']:.2f} y {mount['y_m']:.2f} m "
        f"yaw {mount['yaw_deg']:.2f}°, range offset {summary['range_offset_m'] * 1e3:+.1f} mm): "
        f"lines per scan {lines['min']}..{lines['max']} (mean {lines['mean']}), cylinders "
        f"{cylinders['min']}..{cylinders['max']} (mean {cylinders['mean']}); "
        f"{summary['dropped_telegrams']} dropped telegrams{png}"
    )


# ---- drawing -------------------------------------------------------------------------
def _draw(
    plt: Any,
    scan: Scan,
    found: ScanFeatures,
    mount: Pose2D,
    range_offset_m: float,
    title: str,
) -> Any:
    """Qian et al.'s Fig. 5: the points coloured by segment (grey: in none), the fitted
    lines with their ends (a hollow ring where the end is occluded), the fitted circles."""
    import numpy as np
    from matplotlib.lines import Line2D

    from appliance.perception.points import scan_points

    points = scan_points(
        scan.ranges_m, sensor_angles_rad(scan), mount, range_offset_m=range_offset_m
    )
    xy, valid = points.xy_m, points.valid
    figure, axes = plt.subplots(figsize=(10, 8))
    in_segment = np.zeros(len(valid), dtype=bool)
    tab10 = plt.get_cmap("tab10")
    palette = [tab10(i) for i in (0, 2, 4, 5, 6, 7, 8, 9)]  # red and orange mark features
    for k, (start, stop) in enumerate(found.segments):
        beams = np.arange(start, stop)
        beams = beams[valid[beams]]
        in_segment[beams] = True
        axes.scatter(xy[beams, 0], xy[beams, 1], s=4, color=palette[k % len(palette)], zorder=2)
    rest = valid & ~in_segment
    axes.scatter(xy[rest, 0], xy[rest, 1], s=3, color="lightgrey", zorder=1)
    for line in found.lines:
        (x0, y0), (x1, y1) = line.start_xy_m, line.end_xy_m
        axes.plot([x0, x1], [y0, y1], color="black", linewidth=1.5, zorder=3)
        for (x, y), occluded in (
            (line.start_xy_m, line.start_occluded),
            (line.end_xy_m, line.end_occluded),
        ):
            axes.plot(
                x, y, marker="o", markersize=7, zorder=4, linestyle="none",
                color="tab:orange" if occluded else "black",
                markerfacecolor="none" if occluded else "black",
            )  # fmt: skip
    for circle in found.circles:
        axes.add_patch(
            plt.Circle(
                (circle.cx_m, circle.cy_m), circle.radius_m,
                fill=False, color="tab:red", linewidth=1.5, zorder=3,
            )
        )  # fmt: skip
        axes.plot(circle.cx_m, circle.cy_m, marker="+", color="tab:red", markersize=8, zorder=4)
    axes.plot(mount.x_m, mount.y_m, marker="^", color="tab:blue", markersize=9, zorder=5)
    arrow_m = 0.8
    axes.annotate(
        "",
        xy=(
            mount.x_m + arrow_m * math.cos(mount.yaw_rad),
            mount.y_m + arrow_m * math.sin(mount.yaw_rad),
        ),
        xytext=(mount.x_m, mount.y_m),
        arrowprops={"arrowstyle": "->", "color": "tab:blue"},
    )
    axes.plot(0.0, 0.0, marker="+", color="black", markersize=10)
    near = valid & (points.ranges_m <= CLOSE_UP_M)
    shown = xy[near] if near.any() else xy[valid]
    if len(shown):
        x_lo = min(float(shown[:, 0].min()), mount.x_m, 0.0) - 0.5
        x_hi = max(float(shown[:, 0].max()), mount.x_m, 0.0) + 0.5
        y_lo = min(float(shown[:, 1].min()), mount.y_m, 0.0) - 0.5
        y_hi = max(float(shown[:, 1].max()), mount.y_m, 0.0) + 0.5
        axes.set_xlim(x_lo, x_hi)
        axes.set_ylim(y_lo, y_hi)
    axes.set_aspect("equal", adjustable="box")
    legend = [
        Line2D([], [], marker="o", linestyle="none", color="tab:blue", markersize=4,
               label="points (colour: segment)"),
        Line2D([], [], marker="o", linestyle="none", color="lightgrey", markersize=4,
               label="points in no segment"),
        Line2D([], [], color="black", linewidth=1.5, label="fitted line"),
        Line2D([], [], marker="o", linestyle="none", color="black", label="true end"),
        Line2D([], [], marker="o", linestyle="none", color="tab:orange",
               markerfacecolor="none", label="occluded end"),
        Line2D([], [], color="tab:red", linewidth=1.5, label="fitted circle"),
        Line2D([], [], marker="^", linestyle="none", color="tab:blue", label="scanner"),
    ]  # fmt: skip
    axes.legend(handles=legend, loc="best", fontsize="small")
    hidden = int((valid & ~near).sum()) if near.any() else 0
    axes.set_title(
        f"{title}\n{len(found.segments)} segments, {len(found.lines)} lines, "
        f"{len(found.circles)} cylinders"
        + (f" ({hidden} points beyond {CLOSE_UP_M:.0f} m not shown)" if hidden else "")
    )
    axes.set_xlabel("x (m), vehicle frame")
    axes.set_ylabel("y (m)")
    axes.grid(True, linewidth=0.3)
    figure.tight_layout()
    return figure
