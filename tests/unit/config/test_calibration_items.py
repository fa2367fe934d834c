"""The calibration file's per-item records and the kit's installation date.

A record written is read back equal (the TOML writer's inline tables included, with any
reason text); a record with a bad field is refused with its path; a calibration whose
steering was measured before the kit's steering was installed is refused with a line
that says what to run.
"""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.config import load_config
from appliance.config.calibration import CalibrationFile
from appliance.config.calibration_file import (
    CalibrationError,
    dumps_calibration,
    parse_calibration,
    read_vehicle_calibration,
    steering_measured_utc,
    write_calibration,
)
from appliance.config.calibration_items import ItemRecord
from appliance.config.simulated_calibration import simulated_calibration

WHEN = datetime(2026, 11, 2, 9, 30, tzinfo=UTC)


def record(measured_utc: datetime = WHEN, **changes: object) -> ItemRecord:
    fields: dict[str, object] = {
        "method": "mean pot over straight segments",
        "measured_utc": measured_utc,
        "tool_version": "0.1.0",
        "accepted": True,
        "residual_rms": 0.02,
        "residual_max": 0.05,
        "residual_unit": "deg tyre",
        "samples_used": 1200,
        "rejected": {"turning": 40, "too slow": 7},
        "summary": "4 segments",
        "raw_data": "/var/lib/dbw/calibration/pot-center.jsonl",
    }
    return ItemRecord.model_validate(fields | changes)


def with_items(vehicle: str, **items: ItemRecord) -> CalibrationFile:
    data = simulated_calibration(vehicle, created_utc=WHEN).model_dump()
    data["source"] = "dbw calibrate"  # not the simulated truth: a measured file
    data["tool_version"] = "0.1.0"
    data["items"] = {name: item.model_dump() for name, item in items.items()}
    return CalibrationFile.model_validate(data)


@settings(max_examples=60, deadline=None)
@given(
    reasons=st.dictionaries(st.text(min_size=1, max_size=80), st.integers(0, 10**9), max_size=5),
    summary=st.text(max_size=400).filter(lambda t: not any(0xD800 <= ord(c) <= 0xDFFF for c in t)),
)
def test_records_read_back_equal_whatever_their_text(reasons: dict[str, int], summary: str) -> None:
    model = with_items("sim", pot_map=record(rejected=reasons, summary=summary))
    assert parse_calibration(dumps_calibration(model), "sim") == model


def test_a_record_with_a_bad_field_is_refused_by_name() -> None:
    text = dumps_calibration(with_items("sim", pot_centre=record()))
    assert "residual_rms = 0.02" in text
    with pytest.raises(CalibrationError) as caught:
        parse_calibration(text.replace("residual_rms = 0.02", "residual_rms = -1.0"), "sim")
    assert "items.pot_centre.residual_rms" in caught.value.render()


def test_steering_measured_before_the_kit_was_installed_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "cal.toml"
    config = load_config("husky")
    config = config.model_copy(
        update={
            "paths": config.paths.model_copy(update={"calibration_file": str(path)}),
            "kit": config.kit.model_copy(update={"steering_installed_utc": WHEN}),
        }
    )
    older = WHEN - timedelta(days=3)
    write_calibration(path, with_items("husky", pot_map=record(older), pot_centre=record()))
    with pytest.raises(CalibrationError) as caught:
        read_vehicle_calibration(config)
    text = caught.value.render()
    assert "before the kit's steering was installed" in text and "dbw calibrate pot-map" in text

    newer = with_items("husky", pot_map=record(WHEN + timedelta(hours=1)), pot_centre=record())
    write_calibration(path, newer)
    assert read_vehicle_calibration(config) == newer
    assert steering_measured_utc(newer) == WHEN


def test_a_file_without_records_is_dated_by_its_creation() -> None:
    model = simulated_calibration("sim", created_utc=WHEN)
    assert model.items is None and steering_measured_utc(model) == WHEN
