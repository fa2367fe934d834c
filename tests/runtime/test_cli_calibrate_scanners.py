"""`dbw calibrate scanners` on LMS111 recordings, as a person runs it after docking.

The recordings are made the way `dbw lms111 record` makes them, without a socket: the
twin's device model renders each scan from the simulated site (from the scanner's true
mount, with its drawn errors), the protocol core encodes it as the telegram the device
sends, and the recording writer stores those bytes. So the command replays them through
the same decoder as a real recording.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from appliance.config import load_config
from appliance.config.calibration_file import read_calibration_file, write_calibration
from appliance.config.simulated_calibration import simulated_calibration
from appliance.sim.scanner_errors import ScannerErrors, draw_scanner_errors
from drivers.geometry import Pose2D
from drivers.lms111.mounted import mount_pose
from tests.runtime import recordings as shared_recordings
from tests.runtime.recordings import dbw, dbw_here

# Files and faster-than-real-time runs, no daemon on the clock: run with the unit tests,
# on every core (see tests/conftest.py).
pytestmark = pytest.mark.cpu_bound

FLATBED = load_config("flatbed")
MOUNTS = {
    "left": mount_pose(FLATBED.geometry.scanner_left_mount),
    "right": mount_pose(FLATBED.geometry.scanner_right_mount),
}
DOCKED_CENTRE = Pose2D(-FLATBED.geometry.length_m / 2.0, 0.0, 0.0)
SEED = 7


def record(
    path: Path,
    mount: Pose2D,
    errors: ScannerErrors,
    *,
    scans: int = 12,
    serial_number: int = 0x0142_0001,
    noise_seed: int = 0,
) -> None:
    """A recording of ``scans`` scans at 25 Hz and 0.25°, in CoLa-B, taken docked."""
    shared_recordings.record(
        path,
        mount,
        lambda _t_s: DOCKED_CENTRE,
        errors,
        scans=scans,
        serial_number=serial_number,
        noise_seed=noise_seed,
    )


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("recordings")
    files = {}
    for index, (name, mount) in enumerate(MOUNTS.items()):
        files[name] = folder / f"{name}.lms"
        record(
            files[name],
            mount,
            draw_scanner_errors(SEED, index, True),
            serial_number=0x0142_0001 + index,
            noise_seed=index,
        )
    return files


def test_accepted_scanners_print_their_offsets_as_json(recordings: dict[str, Path]) -> None:
    code, out, err = dbw(
        "calibrate", "scanners", "--config", "flatbed",
        "--left", str(recordings["left"]), "--right", str(recordings["right"]), "--json",
    )  # fmt: skip
    assert code == 0, err
    report = json.loads(out)
    assert report["accepted"] is True
    assert report["merged_into"] is None
    for index, name in enumerate(("left", "right")):
        truth = draw_scanner_errors(SEED, index, True)
        result = report["scanners"][name]
        assert result["accepted"] is True
        assert result["reasons"] == []
        assert result["scans"] == 12
        assert abs(result["range_offset_m"] - truth.range_offset_m) < 0.004
        assert abs(result["mount_yaw_offset_deg"] - math.degrees(truth.mount_error.yaw_rad)) < 0.05
        assert result["lateral_offset_m"] is None  # the troughs' ±1 cm hide it
        assert result["residual_rms_m"] < 0.015
        assert result["points_used"]["front_board"] > 100
        mount = result["calibrated_mount"]
        expected_yaw = math.degrees(MOUNTS[name].yaw_rad) + result["mount_yaw_offset_deg"]
        assert mount["yaw_deg"] == pytest.approx(expected_yaw)


def test_the_summary_text_says_what_was_found(recordings: dict[str, Path]) -> None:
    code, out, err = dbw(
        "calibrate", "scanners", "--config", "flatbed", "--left", str(recordings["left"])
    )
    assert code == 0, err
    assert "left: ACCEPTED" in out
    assert "range offset" in out
    assert "not observable" in out
    assert "right:" not in out  # only the scanner given


def test_accepted_results_merge_into_the_calibration_file(
    recordings: dict[str, Path], tmp_path: Path
) -> None:
    calfile = tmp_path / "calibration.toml"
    before = simulated_calibration("flatbed")
    write_calibration(calfile, before)
    code, out, err = dbw(
        "calibrate", "scanners", "--config", "flatbed",
        "--left", str(recordings["left"]), "--right", str(recordings["right"]),
        "--calibration", str(calfile), "--json",
    )  # fmt: skip
    assert code == 0, err
    assert json.loads(out)["merged_into"] == str(calfile)
    after = read_calibration_file(calfile, "flatbed")
    assert after.model_dump(exclude={"scanners"}) == before.model_dump(exclude={"scanners"})
    assert after.scanners is not None
    for index, entry in enumerate((after.scanners.left, after.scanners.right)):
        assert entry is not None
        truth = draw_scanner_errors(SEED, index, True)
        assert abs(entry.range_offset_m - truth.range_offset_m) < 0.004
        assert entry.lateral_offset_m is None
        assert entry.method.startswith("docked-pose point fit")


def test_a_refused_scanner_exits_1_and_merges_nothing(tmp_path: Path) -> None:
    # The right scanner's recording given as the left one: no board where the left
    # scanner would see it, no left cylinder.
    swapped = tmp_path / "swapped.lms"
    record(swapped, MOUNTS["right"], draw_scanner_errors(SEED, 1, True), scans=3)
    calfile = tmp_path / "calibration.toml"
    write_calibration(calfile, simulated_calibration("flatbed"))
    text_before = calfile.read_text()
    code, out, err = dbw(
        "calibrate", "scanners", "--config", "flatbed", "--left", str(swapped),
        "--calibration", str(calfile), "--json",
    )  # fmt: skip
    assert code == 1, err
    report = json.loads(out)
    assert report["accepted"] is False
    assert report["scanners"]["left"]["reasons"]
    assert calfile.read_text() == text_before


def test_bad_input_exits_2_with_one_line_and_no_traceback(
    recordings: dict[str, Path], tmp_path: Path
) -> None:
    corrupt = tmp_path / "corrupt.lms"
    corrupt.write_bytes(recordings["left"].read_bytes()[:-100])  # cut off inside a record
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"not a recording at all\n")
    cases = [
        ["--left", str(corrupt)],
        ["--left", str(junk)],
        ["--left", str(tmp_path / "missing.lms")],
        [],
        ["--left", str(recordings["left"]), "--right", str(recordings["left"])],
        ["--left", str(recordings["left"]), "--calibration", str(tmp_path / "none.toml")],
    ]
    # One as a person runs it, in a process of its own; the others in this one.
    code, _, err = dbw("calibrate", "scanners", "--config", "flatbed", *cases[1])
    assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    for args in cases:
        code, out, err = dbw_here("calibrate", "scanners", "--config", "flatbed", *args)
        assert code == 2, (args, out, err)
        assert "Traceback" not in err
        assert err.strip(), args
        assert len(err.strip().splitlines()) == 1, err
    code, _, err = dbw_here(
        "calibrate", "scanners", "--config", "no-such-vehicle", "--left", str(recordings["left"])
    )
    assert code == 2
    assert "Traceback" not in err


def test_png_draws_the_points(recordings: dict[str, Path], tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    png = tmp_path / "calibration.png"
    code, _, err = dbw(
        "calibrate", "scanners", "--config", "flatbed",
        "--left", str(recordings["left"]), "--png", str(png),
    )  # fmt: skip
    assert code == 0, err
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
