"""What the commands that replay LMS111 recordings share (`dbw features`, `dbw localize`).

Reading a recording (`dbw lms111 record`), which front scanner it is of and its beams'
angles, the vehicle's calibration, and a pose as their output prints it. Bad input ends
the command with exit status 2 and one line, no traceback; a recording cut off inside a
record is used up to the cut, with a warning and exit status 1, as `dbw lms111 decode`
does.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import click

from appliance.cli.common import bad_input

if TYPE_CHECKING:
    import numpy as np
    import numpy.typing as npt

    from appliance.config.calibration import Calibration
    from appliance.config.models import VehicleConfig
    from drivers.geometry import Pose2D
    from drivers.lms111.recording import RecordedScans, RecordingHeader
    from drivers.lms111.scan import Scan

    FloatArray = npt.NDArray[np.float64]

EXIT_TRUNCATED = 1  # as `dbw lms111 decode`: the output is what was read before the cut
SCANNERS = ("left", "right")


def read_recording_or_exit(path: str) -> RecordedScans:
    """Every scan of the recording at ``path``; exit 2 unless it is a recording with scans.
    A cut-off file is returned with what was read (``truncated`` says where it ends)."""
    from drivers.lms111.recording import RecordingError, read_scans

    try:
        recording = read_scans(path)
    except RecordingError as exc:
        bad_input(str(exc))
    except OSError as exc:
        bad_input(f"{path}: cannot read the recording: {exc.strerror or exc}")
    if not any(scan.ranges_m.size for scan in recording.scans):
        cut = " before it was cut off" if recording.truncated else ""
        bad_input(
            f"{path}: the recording holds no scans with ranges{cut} "
            f"({len(recording.scans)} scans, {recording.dropped_telegrams} dropped telegrams)"
        )
    return recording


def warn_truncated(recordings: Sequence[RecordedScans]) -> bool:
    """Say on stderr which recordings were cut off (their scans were used up to the cut)."""
    cut = [r for r in recordings if r.truncated]
    for recording in cut:
        click.echo(
            f"warning: {recording.truncated}; used the {len(recording.scans)} scans before it",
            err=True,
        )
    return bool(cut)


def load_calibration_or_exit(path: str | None, config: VehicleConfig) -> Calibration | None:
    """The calibration file at ``path`` for this vehicle, None without one; exit 2 unless
    it can be used."""
    if path is None:
        return None
    from appliance.config.calibration_file import CalibrationError, load_calibration

    try:
        return load_calibration(
            path, config.name, config.simulation.enabled, config.simulation.steering.steering_ratio
        )
    except CalibrationError as exc:
        bad_input(exc.render().replace("\n", " "))
    except OSError as exc:
        bad_input(f"{path}: cannot read the calibration: {exc.strerror or exc}")


def scanner_endpoints(config: VehicleConfig) -> dict[str, tuple[str, int]]:
    """Each front scanner's (host, port) in the vehicle file: what a recording's header
    is matched against."""
    return {
        "left": (config.devices.lms111_left.host, config.devices.lms111_left.port),
        "right": (config.devices.lms111_right.host, config.devices.lms111_right.port),
    }


def scanner_of(header: RecordingHeader, config: VehicleConfig, path: str) -> str:
    """Which front scanner a recording is of, from the endpoint it was recorded from."""
    endpoints = scanner_endpoints(config)
    matches = [
        name for name, endpoint in endpoints.items() if endpoint == (header.host, header.port)
    ]
    if len(matches) == 1:
        return matches[0]
    whose = "both scanners'" if matches else "neither scanner's"
    bad_input(
        f"{path}: recorded from {header.host}:{header.port}, which is {whose} endpoint in "
        f"the vehicle file {config.name!r}: say which scanner it is with --scanner left|right"
    )


def sensor_angles_rad(scan: Scan) -> FloatArray:
    """The scan's beam angles in its sensor frame (x out of the window)."""
    from drivers.lms111.mounted import DEVICE_FORWARD_RAD

    angles: FloatArray = scan.angles_rad - DEVICE_FORWARD_RAD
    return angles


def pose_json(pose: Pose2D) -> dict[str, float]:
    return {
        "x_m": round(pose.x_m, 5),
        "y_m": round(pose.y_m, 5),
        "yaw_deg": round(math.degrees(pose.yaw_rad), 5),
    }
