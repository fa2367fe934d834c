"""`dbw calibrate ...`: the calibrations measured on the vehicle.

`scanners` fits each front LMS111's range offset and mount yaw (and its lateral offset,
where the docking leaves it observable) from recordings taken while the vehicle stands
docked at the launcher (`dbw lms111 record HOST:PORT FILE --seconds 2`, one per scanner),
prints the result, and with ``--calibration FILE`` merges accepted results into that
calibration file atomically. The fit is `appliance.localization.scanner_calibration`; this
module only reads the files, wires the vehicle file's mounts and the launcher in, and
reports. Exit status: 0 accepted, 1 refused, 2 bad input (a file that cannot be read, a
wrong vehicle or calibration file), always with a one-line reason and no traceback.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, NoReturn

import click

from appliance.cli.calibrate_maneuvers import add_maneuver_commands
from appliance.cli.common import CONFIG_OPTION, EXIT_CONFIG_ERROR, draw_png, load_or_exit

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from appliance.localization.launcher_map import LauncherMap
    from appliance.localization.scanner_calibration_params import DockedPose
    from appliance.localization.scanner_calibration_verdict import ScannerCalibrationResult
    from drivers.geometry import Pose2D

EXIT_ACCEPTED = 0
EXIT_REFUSED = 1
EXIT_BAD_INPUT = EXIT_CONFIG_ERROR


class BadInput(Exception):
    """A file the command cannot use; its message is the one line the person sees."""


@dataclass(frozen=True)
class Recording:
    path: str
    scans: tuple[tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]], ...]
    serial_numbers: frozenset[int]
    dropped_telegrams: int


def read_recording(path: str) -> Recording:
    """Every scan of an LMS111 recording as (ranges_m, sensor-frame angles_rad), x out of
    the window. Raises BadInput for anything that is not a whole recording with scans."""
    from drivers.lms111.mounted import DEVICE_FORWARD_RAD
    from drivers.lms111.recording import RecordingError, ReplayError, iter_recording

    scans = []
    serials: set[int] = set()
    dropped = 0
    try:
        for event in iter_recording(path):
            if isinstance(event, ReplayError):
                dropped += 1
                continue
            ranges = event.ranges_m
            if ranges.size == 0:
                continue  # a scan without DIST1: nothing to fit
            scans.append((ranges, event.angles_rad - DEVICE_FORWARD_RAD))
            serials.add(event.serial_number)
    except RecordingError as exc:  # RecordingTruncated too: a cut-off file is re-recorded
        raise BadInput(str(exc)) from None
    except OSError as exc:
        raise BadInput(f"{path}: cannot read the recording: {exc.strerror or exc}") from None
    if not scans:
        raise BadInput(f"{path}: the recording holds no scans ({dropped} dropped telegrams)")
    return Recording(path, tuple(scans), frozenset(serials), dropped)


@click.group()
def calibrate() -> None:
    """Measure calibrations on the vehicle: the steering maneuvers, the scanners."""


@calibrate.command("scanners")
@click.option("--left", "left_file", metavar="FILE", help="Recording of the left LMS111.")
@click.option("--right", "right_file", metavar="FILE", help="Recording of the right LMS111.")
@CONFIG_OPTION
@click.option(
    "--calibration",
    "calibration_file",
    metavar="FILE",
    help="Merge accepted results into this calibration file (atomically; the rest stays).",
)
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.option(
    "--png", "png_file", metavar="OUT.png", help="Draw the points as configured and as fitted."
)
@click.option(
    "--standoff-m",
    type=click.FloatRange(min=0.0, max=20.0),
    default=0.0,
    show_default=True,
    help="How far the front end's centre stood in front of the board while recording.",
)
@click.option(
    "--front-end-m",
    type=click.FloatRange(min=0.0, min_open=True, max=40.0),
    default=None,
    help="The front end's centre ahead of the vehicle frame's origin. Default: half the "
    "vehicle's length (the origin at its geometric centre).",
)
@click.option(
    "--lateral-tolerance-m",
    type=click.FloatRange(min=0.0, max=0.1),
    default=0.01,
    show_default=True,
    help="How well the troughs fix the front end sideways (taken as one σ).",
)
@click.option(
    "--heading-tolerance-deg",
    type=click.FloatRange(min=0.0, max=1.0),
    default=0.3,
    show_default=True,
    help="How well the troughs fix the heading (one σ).",
)
@click.option(
    "--longitudinal-tolerance-m",
    type=click.FloatRange(min=0.0, max=0.1),
    default=0.003,
    show_default=True,
    help="How well the touching front end fixes the distance to the board (one σ).",
)
def scanners(
    left_file: str | None,
    right_file: str | None,
    config_name: str | None,
    calibration_file: str | None,
    as_json: bool,
    png_file: str | None,
    standoff_m: float,
    front_end_m: float | None,
    lateral_tolerance_m: float,
    heading_tolerance_deg: float,
    longitudinal_tolerance_m: float,
) -> None:
    """Fit each scanner's range offset and mount yaw from recordings taken docked.

    Record each scanner for a couple of seconds with the vehicle at rest, docked (teeth in
    their troughs, front end touching the board), and nobody near the cylinders:
    `dbw lms111 record HOST:PORT left.lms --seconds 2`. Exit 0 when every given scanner is
    accepted, 1 when one is refused (nothing is merged then), 2 for bad input.
    """
    from appliance.config.calibration_file import CalibrationError, read_calibration_file
    from appliance.localization.launcher_map import LauncherMap
    from appliance.localization.scanner_calibration import calibrate_scanner
    from appliance.localization.scanner_calibration_params import DockedPose
    from drivers.geometry import Pose2D
    from drivers.lms111.mounted import mount_pose

    files = {name: f for name, f in (("left", left_file), ("right", right_file)) if f}
    if not files:
        _bad_input("give at least one recording: --left FILE and/or --right FILE")
    config = load_or_exit(config_name)
    if calibration_file is not None:
        try:  # fail before the fit, not after it
            read_calibration_file(
                calibration_file,
                config.name,
                config.simulation.enabled,
                config.simulation.steering.steering_ratio,
            )
        except CalibrationError as exc:
            _bad_input(exc.render().replace("\n", " "))
    try:
        recordings = {name: read_recording(path) for name, path in files.items()}
    except BadInput as exc:
        _bad_input(str(exc))
    if len(recordings) == 2:
        shared = recordings["left"].serial_numbers & recordings["right"].serial_numbers
        if shared:
            _bad_input(
                f"the left and right recordings come from the same scanner (serial number "
                f"{min(shared)}): record each scanner into its own file"
            )
    geometry = config.geometry
    mounts = {
        "left": mount_pose(geometry.scanner_left_mount),
        "right": mount_pose(geometry.scanner_right_mount),
    }
    front_m = front_end_m if front_end_m is not None else geometry.length_m / 2.0
    docked = DockedPose.at_front_end(
        Pose2D(-standoff_m, 0.0, 0.0),
        front_m,
        longitudinal_tolerance_m,
        lateral_tolerance_m,
        math.radians(heading_tolerance_deg),
    )
    launcher = LauncherMap()
    results = {
        name: calibrate_scanner(recording.scans, mounts[name], docked, launcher)
        for name, recording in recordings.items()
    }
    accepted = all(result.accepted for result in results.values())
    merged_into: str | None = None
    if accepted and calibration_file is not None:
        _merge(calibration_file, config.name, config.simulation.enabled, results, recordings)
        merged_into = calibration_file
    png_note = None
    if png_file is not None:
        png_note = _draw_or_say_why(png_file, recordings, results, mounts, docked, launcher)
    report = {
        "vehicle": config.name,
        "docked": {
            "centre": _pose_json(docked.centre),
            "pivot_forward_m": docked.pivot_forward_m,
            "longitudinal_tolerance_m": docked.longitudinal_tolerance_m,
            "lateral_tolerance_m": docked.lateral_tolerance_m,
            "heading_tolerance_deg": math.degrees(docked.heading_tolerance_rad),
        },
        "scanners": {
            name: _result_json(result, recordings[name], mounts[name])
            for name, result in results.items()
        },
        "accepted": accepted,
        "merged_into": merged_into,
        "png": png_file if png_file is not None and png_note is None else None,
    }
    if as_json:
        click.echo(json.dumps(report, indent=2))
    else:
        click.echo(_summary_text(results, recordings, merged_into, calibration_file))
    if png_note is not None:
        click.echo(f"{png_file}: {png_note}", err=True)
    sys.exit(EXIT_ACCEPTED if accepted else EXIT_REFUSED)


def _bad_input(message: str) -> NoReturn:
    click.echo(f"error: {message}", err=True)
    sys.exit(EXIT_BAD_INPUT)


def _merge(
    path: str,
    vehicle_name: str,
    simulation_enabled: bool,
    results: Mapping[str, ScannerCalibrationResult],
    recordings: Mapping[str, Recording],
) -> None:
    from pydantic import ValidationError

    from appliance.config.calibration import ScannerCalibrationEntry
    from appliance.config.calibration_file import CalibrationError, merge_scanner_calibration
    from appliance.localization.scanner_calibration import METHOD

    now = datetime.now(UTC).replace(microsecond=0)
    entries = {}
    try:
        for name, result in results.items():
            estimate = result.estimate
            assert estimate is not None  # accepted results always carry one
            scans = len(recordings[name].scans)
            entries[name] = ScannerCalibrationEntry(
                range_offset_m=estimate.range_offset_m,
                range_offset_sigma_m=estimate.range_offset_sigma_m,
                mount_yaw_offset_deg=math.degrees(estimate.mount_yaw_offset_rad),
                mount_yaw_offset_sigma_deg=math.degrees(estimate.mount_yaw_offset_sigma_rad),
                lateral_offset_m=estimate.lateral_offset_m,
                lateral_offset_sigma_m=estimate.lateral_offset_sigma_m,
                residual_rms_m=estimate.residual_rms_m,
                method=f"{METHOD}: {scans} scans of {recordings[name].path}",
                measured_utc=now,
            )
        merge_scanner_calibration(path, vehicle_name, entries, simulation_enabled)
    except CalibrationError as exc:
        _bad_input(exc.render().replace("\n", " "))
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(part) for part in first["loc"])
        _bad_input(f"{path}: the result does not fit the calibration file: {where}: {first['msg']}")
    except OSError as exc:
        _bad_input(f"{path}: cannot write the calibration: {exc}")


def _pose_json(pose: Pose2D) -> dict[str, float]:
    return {"x_m": pose.x_m, "y_m": pose.y_m, "yaw_deg": math.degrees(pose.yaw_rad)}


def _result_json(
    result: ScannerCalibrationResult, recording: Recording, mount: Pose2D
) -> dict[str, Any]:
    from appliance.localization.scanner_calibration import calibrated_mount

    data: dict[str, Any] = {
        "file": recording.path,
        "scans": len(recording.scans),
        "dropped_telegrams": recording.dropped_telegrams,
        "scans_used": result.scans_used,
        "accepted": result.accepted,
        "reasons": list(result.reasons),
        "notes": list(result.notes),
        "points_used": dict(result.points_used),
        "configured_mount": _pose_json(mount),
    }
    estimate = result.estimate
    if estimate is None:
        return data
    data |= {
        "range_offset_m": estimate.range_offset_m,
        "range_offset_sigma_m": estimate.range_offset_sigma_m,
        "mount_yaw_offset_deg": math.degrees(estimate.mount_yaw_offset_rad),
        "mount_yaw_offset_sigma_deg": math.degrees(estimate.mount_yaw_offset_sigma_rad),
        "mount_yaw_offset_statistical_sigma_deg": math.degrees(
            estimate.mount_yaw_offset_statistical_sigma_rad
        ),
        "lateral_offset_m": estimate.lateral_offset_m,
        "lateral_offset_sigma_m": estimate.lateral_offset_sigma_m,
        "residual_rms_m": estimate.residual_rms_m,
        "parameters": [
            {
                "name": p.name,
                "value": p.value,
                "sigma": p.sigma,
                "statistical_sigma": p.statistical_sigma,
                "pose_sigma": p.pose_sigma,
                "observable": p.observable,
            }
            for p in estimate.parameters
        ],
        "calibrated_mount": _pose_json(
            calibrated_mount(mount, estimate.mount_yaw_offset_rad, estimate.lateral_offset_m)
        ),
    }
    return data


def _summary_text(
    results: Mapping[str, ScannerCalibrationResult],
    recordings: Mapping[str, Recording],
    merged_into: str | None,
    calibration_file: str | None,
) -> str:
    lines = []
    for name, result in results.items():
        recording = recordings[name]
        verdict = "ACCEPTED" if result.accepted else "REFUSED"
        lines.append(f"{name}: {verdict} ({recording.path}, {len(recording.scans)} scans)")
        estimate = result.estimate
        if estimate is not None:
            lines.append(
                f"  range offset   {estimate.range_offset_m * 1e3:+7.2f} mm "
                f"± {estimate.range_offset_sigma_m * 1e3:.2f} mm"
            )
            lines.append(
                f"  mount yaw      {math.degrees(estimate.mount_yaw_offset_rad):+7.3f}° "
                f"± {math.degrees(estimate.mount_yaw_offset_sigma_rad):.3f}° (the points "
                f"alone ± {math.degrees(estimate.mount_yaw_offset_statistical_sigma_rad):.4f}°)"
            )
            sigma_mm = estimate.lateral_offset_sigma_m * 1e3
            lateral = (
                f"not observable (σ {sigma_mm:.1f} mm): configured y kept"
                if estimate.lateral_offset_m is None
                else f"{estimate.lateral_offset_m * 1e3:+7.2f} mm ± {sigma_mm:.2f} mm"
            )
            lines.append(f"  lateral        {lateral}")
            lines.append(f"  residual rms   {estimate.residual_rms_m * 1e3:7.2f} mm")
        counts = ", ".join(f"{k} {v}" for k, v in result.points_used.items())
        lines.append(f"  points         {counts} (from {result.scans_used} scans)")
        lines += [f"  refused: {reason}" for reason in result.reasons]
        lines += [f"  note: {note}" for note in result.notes]
    if merged_into is not None:
        lines.append(f"merged into {merged_into}")
    elif calibration_file is not None:
        lines.append(f"{calibration_file} left unchanged: not every scanner was accepted")
    return "\n".join(lines)


def _draw_or_say_why(
    path: str,
    recordings: Mapping[str, Recording],
    results: Mapping[str, ScannerCalibrationResult],
    mounts: Mapping[str, Pose2D],
    docked: DockedPose,
    launcher: LauncherMap,
) -> str | None:
    """Draw the PNG, or say why not (None when drawn): a picture is never worth exit 2."""
    return draw_png(path, lambda plt: _draw(plt, recordings, results, mounts, docked, launcher))


def _draw(
    plt: Any,
    recordings: Mapping[str, Recording],
    results: Mapping[str, ScannerCalibrationResult],
    mounts: Mapping[str, Pose2D],
    docked: DockedPose,
    launcher: LauncherMap,
) -> Any:
    """The launcher with each scanner's first scan in the launcher frame, as measured with
    the configured mount (grey) and as fitted (colour); beside it the board's points
    with x stretched, where millimetres show."""
    import numpy as np

    from appliance.perception.points import scan_points
    from drivers.geometry import Pose2D

    figure, (whole, board) = plt.subplots(1, 2, figsize=(13, 6))
    half = launcher.half_width_m
    for axes in (whole, board):
        axes.plot([0.0, 0.0], [-half, half], color="black", linewidth=2)
    for side in (1.0, -1.0):
        far_x, far_y = launcher.side_board_far_end(side)
        whole.plot([0.0, far_x], [side * half, far_y], color="black", linewidth=2)
    for cylinder in launcher.cylinders:
        whole.add_patch(
            plt.Circle((cylinder.x_m, cylinder.y_m), cylinder.radius_m, fill=False, color="black")
        )
    colours = {"left": "tab:blue", "right": "tab:red"}
    for name, recording in recordings.items():
        ranges, angles = recording.scans[0]
        mount = mounts[name]
        estimate = results[name].estimate
        before = scan_points(ranges, angles, docked.centre.compose(mount))
        shown = [(before, "lightgrey", f"{name} as configured")]
        if estimate is not None:
            # All four fitted parameters, the shifts that are not applied included: the
            # picture shows the fit, and the shifts are where the vehicle stood.
            fitted = Pose2D(
                mount.x_m + estimate.parameter("longitudinal").value,
                mount.y_m + estimate.parameter("lateral").value,
                mount.yaw_rad + estimate.mount_yaw_offset_rad,
            )
            after = scan_points(
                ranges,
                angles,
                docked.centre.compose(fitted),
                range_offset_m=estimate.range_offset_m,
            )
            shown.append((after, colours.get(name, "tab:green"), f"{name} fitted"))
        for points, colour, label in shown:
            xy = points.xy_m[points.valid]
            whole.scatter(xy[:, 0], xy[:, 1], s=2, color=colour, label=label)
            on_board = (np.abs(xy[:, 0]) < 0.1) & (np.abs(xy[:, 1]) < half)
            board.scatter(xy[on_board, 0] * 1e3, xy[on_board, 1], s=2, color=colour, label=label)
    whole.set_xlim(-1.5, 1.5)
    whole.set_ylim(-3.5, 3.5)
    whole.set_aspect("equal")
    whole.set_xlabel("x (m), launcher frame")
    whole.set_ylabel("y (m)")
    whole.set_title("docked: the launcher and the first scan of each scanner")
    whole.legend(loc="center right", fontsize="small", markerscale=4)
    board.set_xlim(-40.0, 40.0)
    board.set_xlabel("x (mm): distance from the board's line")
    board.set_ylabel("y (m)")
    board.set_title("front board points")
    board.legend(loc="upper right", fontsize="small", markerscale=4)
    figure.tight_layout()
    return figure


add_maneuver_commands(calibrate)
