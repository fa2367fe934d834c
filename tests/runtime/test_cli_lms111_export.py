"""`dbw lms111 decode FILE --export jsonl|csv`: the scans themselves, beam by beam.

What is exported must be what the recording holds: the ranges equal the replayed scan's
(exactly: floats are written so they parse back to the same number), the sensor-frame
angle is the device angle less 90°, and the CSV parses back with its header.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from appliance.cli.lms111 import decode
from appliance.sim.scanner_errors import ScannerErrors
from drivers.lms111.recording import EXPORT_CSV_COLUMNS, read_scans
from tests.runtime.recordings import FLATBED_MOUNTS, centre_at_gap, dbw, record

# Files and faster-than-real-time runs, no daemon on the clock: run with the unit tests,
# on every core (see tests/conftest.py).
pytestmark = pytest.mark.cpu_bound

SCANS = 3


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("export") / "left.lms"
    record(
        path, FLATBED_MOUNTS["left"], lambda _t: centre_at_gap(8.0), ScannerErrors(), scans=SCANS
    )
    return path


def invoke(*args: str | Path) -> tuple[int, str, str]:
    result = CliRunner().invoke(decode, [str(arg) for arg in args])
    return result.exit_code, result.stdout, result.stderr


def test_jsonl_export_round_trips_every_beam(recording: Path) -> None:
    code, out, err = invoke(recording, "--export", "jsonl")
    assert code == 0, err
    exported = [json.loads(line) for line in out.splitlines()]
    scans = read_scans(recording).scans
    assert len(exported) == len(scans) == SCANS
    for index, (row, scan) in enumerate(zip(exported, scans, strict=True)):
        assert row["scan_index"] == index
        assert row["host_receive_time_s"] == scan.host_receive_time_s
        assert row["device_time_us"] == scan.device_time_us
        assert row["scan_counter"] == scan.scan_counter
        assert row["telegram_counter"] == scan.telegram_counter
        assert row["beams"] == len(scan.ranges_m) == 1081
        assert np.array_equal(np.array(row["range_m"]), scan.ranges_m)
        assert np.array_equal(np.array(row["intensity"]), scan.intensities)
        device_deg = np.array(row["device_angle_deg"])
        assert device_deg[0] == -45.0 and device_deg[-1] == 225.0
        assert np.allclose(np.radians(device_deg), scan.angles_rad, atol=1e-12)
        sensor = np.array(row["sensor_angle_rad"])
        assert np.array_equal(sensor, scan.angles_rad - math.pi / 2.0)
        assert (np.array(row["range_m"]) > 0).sum() > 100
    # The report goes to stderr, out of the data's way.
    assert f"{SCANS} scans, 0 dropped telegrams" in err


def test_csv_export_to_a_file_parses_back(recording: Path, tmp_path: Path) -> None:
    out_file = tmp_path / "left.csv"
    code, out, err = invoke(recording, "--export", "csv", "--out", out_file)
    assert code == 0, err
    assert f"{SCANS} scans" in out  # with --out, the report stays on stdout
    with out_file.open(newline="") as file:
        reader = csv.DictReader(file)
        assert tuple(reader.fieldnames or ()) == EXPORT_CSV_COLUMNS
        rows = list(reader)
    scans = read_scans(recording).scans
    assert len(rows) == sum(len(scan.ranges_m) for scan in scans)
    for index, scan in enumerate(scans):
        mine = [row for row in rows if int(row["scan_index"]) == index]
        assert [int(row["beam_index"]) for row in mine] == list(range(len(scan.ranges_m)))
        assert np.array_equal([float(row["range_m"]) for row in mine], scan.ranges_m)
        assert np.array_equal([float(row["intensity"]) for row in mine], scan.intensities)
        assert np.array_equal(
            [float(row["sensor_angle_rad"]) for row in mine], scan.angles_rad - math.pi / 2.0
        )
        assert float(mine[0]["device_angle_deg"]) == -45.0
        assert {float(row["host_receive_time_s"]) for row in mine} == {scan.host_receive_time_s}
        assert {int(row["scan_counter"]) for row in mine} == {scan.scan_counter}


def test_csv_export_to_stdout_has_only_the_table(recording: Path) -> None:
    code, out, err = invoke(recording, "--export", "csv", "--json")
    assert code == 0, err
    rows = list(csv.reader(io.StringIO(out)))
    assert tuple(rows[0]) == EXPORT_CSV_COLUMNS
    assert len(rows) == 1 + SCANS * 1081
    assert json.loads(err.strip().splitlines()[-1])["scans"] == SCANS


def test_without_export_decode_is_unchanged(recording: Path) -> None:
    code, out, err = invoke(recording)
    assert code == 0, err
    lines = out.splitlines()
    assert len(lines) == SCANS + 1
    assert lines[0].startswith("t=1.000 scan #1")
    assert lines[-1].startswith(f"{SCANS} scans, 0 dropped telegrams")


def test_a_cut_off_recording_exports_what_was_read_and_says_so(
    recording: Path, tmp_path: Path
) -> None:
    cut = tmp_path / "cut.lms"
    cut.write_bytes(recording.read_bytes()[:-100])  # inside the last record
    code, out, err = invoke(cut, "--export", "jsonl")
    assert code == 1
    assert len(out.splitlines()) == SCANS - 1
    assert "truncated" in err
    assert "Traceback" not in err


def test_bad_use_and_bad_input_exit_2(recording: Path, tmp_path: Path) -> None:
    code, _, err = invoke(recording, "--out", tmp_path / "x.csv")
    assert code == 2
    assert "--export" in err
    junk = tmp_path / "junk.lms"
    junk.write_bytes(b"not a recording at all\n")
    out_file = tmp_path / "junk.csv"
    code, _, err = invoke(junk, "--export", "csv", "--out", out_file)
    assert code == 2
    assert "not an LMS111 recording" in err
    assert not out_file.exists()
    code, _, err = invoke(recording, "--export", "csv", "--out", tmp_path / "no" / "such" / "x")
    assert code == 2
    assert "cannot write" in err


def test_the_installed_command_exports(recording: Path, tmp_path: Path) -> None:
    out_file = tmp_path / "left.jsonl"
    code, _, err = dbw(
        "lms111", "decode", str(recording), "--export", "jsonl", "--out", str(out_file)
    )
    assert code == 0, err
    assert len(out_file.read_text().splitlines()) == SCANS
    assert "Traceback" not in err
