"""The maneuvers' raw samples file and the merge into the calibration file.

A samples file reads back what was appended, a torn last line (a crash mid-write) is
dropped and said, any other damage is refused with its line; a merge writes only a whole
valid file, keeps a draft until the steering is complete, and never overwrites a file it
cannot read or one for another vehicle.
"""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest

from appliance.config import load_config
from appliance.config.calibration_file import (
    dumps_calibration,
    read_calibration_file,
    write_calibration,
)
from appliance.config.calibration_items import ItemRecord
from appliance.config.simulated_calibration import simulated_calibration
from appliance.core.maneuver_tap import ManeuverSample
from appliance.maneuvers.merge import MergeError, StepResult, draft_path, merge_result
from appliance.maneuvers.samples_file import (
    SamplesFileError,
    SamplesWriter,
    header,
    read_samples_file,
)

CONFIG = load_config("husky")
WHEN = datetime(2026, 12, 1, 8, 0, tzinfo=UTC)


def sample(seq: int, pot: int = 2100) -> dict[str, object]:
    fields = dict.fromkeys(ManeuverSample.__dataclass_fields__)
    fields.update(seq=seq, t_s=0.02 * seq, mode="ready", engaged=False, stale=[], faults=[])
    fields["pot_counts"] = pot
    return fields


def write_samples(path: Path, count: int) -> None:
    writer = SamplesWriter(path, header("pot-map", "husky", "0.1.0", "2026-12-01T08:00:00Z"))
    writer.mark("started")
    writer.append(sample(i) for i in range(count))
    writer.mark("stopped", reason="complete")
    writer.close()


def test_samples_read_back_and_a_resumed_file_appends(tmp_path: Path) -> None:
    path = tmp_path / "pot-map.jsonl"
    write_samples(path, 5)
    resumed = SamplesWriter(path, None)
    resumed.mark("resumed")
    resumed.append([sample(100)])
    resumed.close()
    read = read_samples_file(path, "husky")
    assert read.step == "pot-map" and not read.torn_last_line
    assert [s["seq"] for s in read.samples] == [0, 1, 2, 3, 4, 100]


def test_a_torn_last_line_is_dropped_and_said(tmp_path: Path) -> None:
    path = tmp_path / "pot-map.jsonl"
    write_samples(path, 3)
    with path.open("a") as file:
        file.write('{"seq": 3, "t_s": 0.0')  # the write a power cut interrupted
    read = read_samples_file(path)
    assert read.torn_last_line and len(read.samples) == 3


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        (lambda text: text.replace('"seq":1,', '"seq":1,,'), ":4: not a JSON line"),
        (lambda text: "", "empty"),
        (lambda text: '{"format": "other"}\n', "no dbw-maneuver-samples header"),
        (lambda text: text.replace('"version":1', '"version":9'), "version 9"),
        (lambda text: text.replace('"t_s":0.02', '"t_s":"soon"'), "t_s must be a number"),
        (lambda text: text.replace('"pot_counts":2100,', "", 1), "lacks pot_counts"),
        (lambda text: text.replace('"vehicle":"husky"', '"vehicle":"flatbed"'), "not 'husky'"),
    ],
)
def test_damaged_files_are_refused_with_the_line(
    tmp_path: Path, damage: object, expected: str
) -> None:
    path = tmp_path / "pot-map.jsonl"
    write_samples(path, 3)
    assert callable(damage)
    path.write_text(damage(path.read_text()))
    with pytest.raises(SamplesFileError, match=r"pot-map\.jsonl") as caught:
        read_samples_file(path, "husky")
    assert expected in str(caught.value)


def record(item: str) -> ItemRecord:
    return ItemRecord(
        method=f"{item} by test",
        measured_utc=WHEN,
        tool_version="0.1.0",
        accepted=True,
        residual_rms=0.01,
        residual_max=0.03,
        residual_unit="deg tyre",
        samples_used=100,
    )


def test_a_first_installation_keeps_a_draft_until_the_steering_is_whole(tmp_path: Path) -> None:
    path = tmp_path / "cal.toml"
    said = merge_result(
        CONFIG,
        path,
        StepResult("pot_centre", {"steering.pot_centre_counts": 2131.4}, record("pot_centre")),
    )
    assert not path.exists() and draft_path(path).exists()
    assert "pot_to_wheel_coeffs (dbw calibrate pot-map)" in said
    truth = simulated_calibration("husky").steering
    values = {
        "steering.pot_to_wheel_coeffs": list(truth.pot_to_wheel_coeffs),
        "steering.pot_valid_min_counts": truth.pot_valid_min_counts,
        "steering.pot_valid_max_counts": truth.pot_valid_max_counts,
        "steering.steering_ratio": 18.0,
    }
    said = merge_result(CONFIG, path, StepResult("pot_map", values, record("pot_map")))
    assert said == f"{path}: pot_map merged" and not draft_path(path).exists()
    written = read_calibration_file(path, "husky")
    assert written.steering.pot_centre_counts == 2131.4
    assert written.items is not None
    assert written.items.pot_centre == record("pot_centre")
    assert written.items.pot_map == record("pot_map")


def test_a_merge_changes_only_its_item_and_refuses_what_it_cannot_read(tmp_path: Path) -> None:
    path = tmp_path / "cal.toml"
    base = simulated_calibration("husky", created_utc=WHEN)
    write_calibration(path, base)
    merge_result(
        CONFIG,
        path,
        StepResult("pot_centre", {"steering.pot_centre_counts": 2130.0}, record("pot_centre")),
    )
    after = read_calibration_file(path, "husky")
    assert after.steering.pot_centre_counts == 2130.0
    assert after.steering.pot_to_wheel_coeffs == base.steering.pot_to_wheel_coeffs
    assert after.created_utc == WHEN

    bad = StepResult("pot_centre", {"steering.pot_centre_counts": 5000.0}, record("pot_centre"))
    before = path.read_text()
    with pytest.raises(MergeError, match="would be invalid"):
        merge_result(CONFIG, path, bad)
    assert path.read_text() == before

    path.write_text(dumps_calibration(simulated_calibration("flatbed")))
    before = path.read_text()
    with pytest.raises(MergeError, match="not overwritten"):
        merge_result(CONFIG, path, bad)
    assert path.read_text() == before
    with pytest.raises(MergeError, match="built-in simulated"):
        merge_result(CONFIG, "builtin:simulated", bad)
