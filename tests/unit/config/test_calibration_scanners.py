"""The calibration file's optional ``[scanners.left]``/``[scanners.right]`` tables: old
files still load, the bounds refuse what they should with the field's path, the writer
round-trips them, and a merge replaces one scanner and leaves everything else alone."""

from __future__ import annotations

import math
from datetime import UTC, datetime
from pathlib import Path

import pytest

from appliance.config.calibration import (
    Calibration,
    ScannerCalibrationEntry,
    ScannersCalibration,
)
from appliance.config.calibration_file import (
    BUILTIN_SIMULATED,
    CalibrationError,
    dumps_calibration,
    merge_scanner_calibration,
    parse_calibration,
    read_calibration_file,
    with_scanners,
    write_calibration,
)
from appliance.config.simulated_calibration import simulated_calibration

OLD_FILE = """\
schema_version = 1
vehicle_name = "flatbed"
created_utc = "2026-12-01T15:00:00Z"
source = "maneuver pot_centre + pot_map on 2026-12-01"

[steering]
pot_centre_counts = 2131.0
pot_to_wheel_coeffs = [0.0055, 0.0, 1.2e-10]
pot_valid_min_counts = 400
pot_valid_max_counts = 3860
steering_ratio = 18.0
"""

LEFT = """
[scanners.left]
range_offset_m = -0.0089
range_offset_sigma_m = 0.0007
mount_yaw_offset_deg = -0.207
mount_yaw_offset_sigma_deg = 0.3
lateral_offset_sigma_m = 0.0101
residual_rms_m = 0.0074
method = "docked-pose point fit: 50 scans of left.lms"
measured_utc = "2026-12-02T09:30:00Z"
"""


def entry(**changes: object) -> ScannerCalibrationEntry:
    values: dict[str, object] = {
        "range_offset_m": 0.012,
        "range_offset_sigma_m": 0.0007,
        "mount_yaw_offset_deg": 0.15,
        "mount_yaw_offset_sigma_deg": 0.3,
        "lateral_offset_m": None,
        "lateral_offset_sigma_m": 0.0101,
        "residual_rms_m": 0.0073,
        "method": "test",
        "measured_utc": datetime(2026, 12, 2, 9, 30, tzinfo=UTC),
    }
    values.update(changes)
    return ScannerCalibrationEntry.model_validate(values)


def problems_of(text: str) -> dict[str, str]:
    with pytest.raises(CalibrationError) as caught:
        parse_calibration(text, "flatbed", "test.toml")
    return {problem.field: problem.message for problem in caught.value.problems}


def test_a_file_without_scanners_loads_as_before() -> None:
    model = parse_calibration(OLD_FILE, "flatbed")
    assert model.scanners is None
    calibration = Calibration.from_file(model)
    assert calibration.scanner("left") is None
    assert calibration.scanner("right") is None
    assert "scanners" not in dumps_calibration(model)


def test_a_file_with_one_scanner_loads() -> None:
    model = parse_calibration(OLD_FILE + LEFT, "flatbed")
    calibration = Calibration.from_file(model)
    left = calibration.scanner("left")
    assert left is not None
    assert left.range_offset_m == -0.0089
    assert left.lateral_offset_m is None  # absent: not observable, configured y stands
    assert left.mount_yaw_offset_rad == pytest.approx(math.radians(-0.207))
    assert left.measured_utc == datetime(2026, 12, 2, 9, 30, tzinfo=UTC)
    assert calibration.scanner("right") is None


def test_a_misspelt_scanner_is_an_error_not_uncalibrated() -> None:
    calibration = Calibration.from_file(parse_calibration(OLD_FILE + LEFT, "flatbed"))
    with pytest.raises(KeyError, match="middle"):
        calibration.scanner("middle")
    assert problems_of(OLD_FILE + LEFT.replace("scanners.left", "scanners.middle")) == {
        "scanners.middle": "unknown field; known fields here: left, right"
    }


@pytest.mark.parametrize(
    ("line", "replacement", "field"),
    [
        ("range_offset_m = -0.0089", "range_offset_m = 0.2", "range_offset_m"),
        ("range_offset_m = -0.0089", "range_offset_m = nan", "range_offset_m"),
        ("range_offset_sigma_m = 0.0007", "range_offset_sigma_m = -0.001", "range_offset_sigma_m"),
        ("mount_yaw_offset_deg = -0.207", "mount_yaw_offset_deg = 2.5", "mount_yaw_offset_deg"),
        (
            "mount_yaw_offset_sigma_deg = 0.3",
            "mount_yaw_offset_sigma_deg = inf",
            "mount_yaw_offset_sigma_deg",
        ),
        (
            "lateral_offset_sigma_m = 0.0101",
            "lateral_offset_sigma_m = 0.0101\nlateral_offset_m = 0.06",
            "lateral_offset_m",
        ),
        ("residual_rms_m = 0.0074", "residual_rms_m = 0.2", "residual_rms_m"),
        ('method = "docked-pose point fit: 50 scans of left.lms"', 'method = ""', "method"),
        (
            'measured_utc = "2026-12-02T09:30:00Z"',
            'measured_utc = "2026-12-02T09:30:00+01:00"',
            "measured_utc",
        ),
        ("residual_rms_m = 0.0074", "", "residual_rms_m"),
        ("residual_rms_m = 0.0074", "residual_rms_m = 0.0074\nrange_scale = 0.0", "range_scale"),
    ],
)
def test_each_bound_names_its_field(line: str, replacement: str, field: str) -> None:
    assert line in LEFT
    problems = problems_of(OLD_FILE + LEFT.replace(line, replacement))
    assert list(problems) == [f"scanners.left.{field}"], problems


def test_the_writer_round_trips_the_scanners() -> None:
    model = with_scanners(
        simulated_calibration("flatbed", created_utc=datetime(2026, 12, 1, tzinfo=UTC)),
        {"left": entry(), "right": entry(lateral_offset_m=-0.003, range_offset_m=-0.02)},
    )
    text = dumps_calibration(model)
    assert "[scanners.left]" in text and "[scanners.right]" in text
    assert text.count("lateral_offset_m =") == 1  # None is written as absent
    assert parse_calibration(text, "flatbed") == model


def test_with_scanners_replaces_one_and_keeps_the_rest() -> None:
    base = with_scanners(simulated_calibration("flatbed"), {"left": entry()})
    updated = with_scanners(base, {"right": entry(range_offset_m=0.001)})
    assert updated.scanners == ScannersCalibration(left=entry(), right=entry(range_offset_m=0.001))
    assert updated.model_dump(exclude={"scanners"}) == base.model_dump(exclude={"scanners"})
    again = with_scanners(updated, {"left": entry(range_offset_m=-0.004)})
    assert again.scanners is not None and again.scanners.right == entry(range_offset_m=0.001)
    assert again.scanners.left == entry(range_offset_m=-0.004)
    with pytest.raises(KeyError):
        with_scanners(base, {"middle": entry()})


def test_merge_writes_the_file_atomically_and_leaves_the_rest(tmp_path: Path) -> None:
    path = tmp_path / "calibration.toml"
    path.write_text(OLD_FILE + LEFT)
    written = merge_scanner_calibration(path, "flatbed", {"right": entry()})
    read_back = read_calibration_file(path, "flatbed")
    assert read_back == written
    old = parse_calibration(OLD_FILE + LEFT, "flatbed")
    assert read_back.model_dump(exclude={"scanners"}) == old.model_dump(exclude={"scanners"})
    assert read_back.scanners is not None and old.scanners is not None
    assert read_back.scanners.left == old.scanners.left
    assert read_back.scanners.right == entry()
    assert [p.name for p in tmp_path.iterdir()] == ["calibration.toml"]  # no temporary left


def test_merge_refuses_what_it_cannot_merge_into(tmp_path: Path) -> None:
    with pytest.raises(CalibrationError, match="not found"):
        merge_scanner_calibration(tmp_path / "missing.toml", "flatbed", {"left": entry()})
    with pytest.raises(CalibrationError, match="simulated"):
        merge_scanner_calibration(BUILTIN_SIMULATED, "flatbed", {"left": entry()}, True)
    other = tmp_path / "other.toml"
    write_calibration(other, simulated_calibration("husky"))
    before = other.read_text()
    with pytest.raises(CalibrationError, match="husky"):
        merge_scanner_calibration(other, "flatbed", {"left": entry()})
    assert other.read_text() == before
