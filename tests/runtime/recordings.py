"""LMS111 recordings for CLI tests, made the way `dbw lms111 record` makes them, without a
socket: the twin's device model renders each scan from the simulated site (the vehicle
where ``vehicle_at(t_s)`` puts it, the scanner at its mount, with the given errors), the
protocol core encodes it as the telegram the device sends, and the recording writer
stores those bytes with the scan's time as its receive time. So a command replays them
through the same decoder as a real recording.
"""

from __future__ import annotations

import subprocess
import sys
import traceback
from collections.abc import Callable
from pathlib import Path

import numpy as np
from click.testing import CliRunner

from appliance.cli.main import cli
from appliance.config import load_config
from appliance.sim.scanner_errors import ScannerErrors
from appliance.sim.scanner_model import RayCache, render_scan
from appliance.sim.site import Site
from appliance.sim.site_file import load_site
from drivers.geometry import Pose2D
from drivers.lms111.connection import Lms111Connection
from drivers.lms111.framing import Dialect
from drivers.lms111.mounted import mount_pose
from drivers.lms111.recording import RecordingWriter
from drivers.lms111.replies import ScanConfig
from drivers.lms111.twin_device import DeviceModel

FLATBED = load_config("flatbed")
FLATBED_MOUNTS = {
    "left": mount_pose(FLATBED.geometry.scanner_left_mount),
    "right": mount_pose(FLATBED.geometry.scanner_right_mount),
}
FRONT_END_M = FLATBED.geometry.length_m / 2.0  # the flat-bed's origin is its centre
SERIAL_NUMBERS = {"left": 0x0142_0001, "right": 0x0142_0002}


def centre_at_gap(gap_m: float, y_m: float = 0.0, yaw_rad: float = 0.0) -> Pose2D:
    """The flat-bed's centre in the launcher frame with its front end ``gap_m`` from the
    board (heading along the launcher's axis)."""
    return Pose2D(-(gap_m + FRONT_END_M), y_m, yaw_rad)


def record(
    path: Path,
    mount: Pose2D,
    vehicle_at: Callable[[float], Pose2D],
    errors: ScannerErrors,
    *,
    scans: int,
    start_s: float = 1.0,
    serial_number: int = SERIAL_NUMBERS["left"],
    noise_seed: int = 0,
    site: Site | None = None,
    endpoint: tuple[str, int] = ("127.0.0.1", 2111),
) -> list[float]:
    """``scans`` scans at 25 Hz and 0.25° in CoLa-B (as on the flat-bed), the first at
    ``start_s``, as recorded from ``endpoint``; returns each scan's time (its receive time
    in the file)."""
    site = site if site is not None else load_site("launcher")
    rng = np.random.default_rng(noise_seed)
    cache = RayCache()

    def measure(t_s: float, angles_rad: np.ndarray) -> tuple[np.ndarray, ...]:
        ranges, remission = render_scan(
            site,
            t_s,
            vehicle_at(t_s),
            mount,
            rng=rng,
            errors=errors,
            start_angle_rad=float(angles_rad[0]),
            stop_angle_rad=float(angles_rad[-1]),
            step_rad=float(angles_rad[1] - angles_rad[0]),
            cache=cache,
        )
        return np.resize(ranges, angles_rad.size), np.resize(remission, angles_rad.size)

    device = DeviceModel(
        measure,
        serial_number=serial_number,
        dialect=Dialect.COLA_B,
        config=ScanConfig.from_si(25.0, 0.25),
    )
    connection = Lms111Connection(Dialect.COLA_B)
    metadata = {"host": endpoint[0], "port": endpoint[1], "dialect": Dialect.COLA_B.value}
    times = []
    with RecordingWriter(path, metadata) as writer:
        for k in range(scans):
            t_s = start_s + k * device.period_s
            scan = device.measure(t_s)
            assert scan is not None
            writer.write_chunk(connection.send_scan(device.telegram(scan)), t_s)
            times.append(t_s)
    return times


def dbw(*args: str) -> tuple[int, str, str]:
    """``dbw ARGS`` in a subprocess, as a person runs it: exit status, stdout, stderr."""
    done = subprocess.run(
        [sys.executable, "-m", "appliance", "--log-format", "json", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    return done.returncode, done.stdout, done.stderr


def dbw_here(*args: str) -> tuple[int, str, str]:
    """`dbw` as a subprocess would run it, in this process (click's runner): for the many
    cases of one command, where a subprocess's start would cost seconds each. An exception
    that escaped the command is in stderr as the traceback a process would print."""
    result = CliRunner().invoke(cli, ["--log-format", "json", *args])
    err = result.stderr
    if result.exception is not None and not isinstance(result.exception, SystemExit):
        err += "".join(traceback.format_exception(result.exception))
    return result.exit_code, result.stdout, err


def header_only(path: Path) -> None:
    """A recording with a header and no record: the scanner never sent anything."""
    metadata = {"host": "127.0.0.1", "port": 2111, "dialect": Dialect.COLA_B.value}
    with RecordingWriter(path, metadata):
        pass


PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
