"""An accepted maneuver's result into the calibration file: all of it, or nothing.

Why the care: the daemon refuses to leave SELF_CHECK without a valid file, and a wrong
pot centre steers the vehicle off its line with every check green. So a result is merged
only when its fit was accepted, into a file that is read and validated first (a damaged
or foreign file is refused, never overwritten), the merged whole is validated again, and
the write is atomic and read back (:func:`appliance.config.calibration_file.
write_calibration`). A refused fit, an abort or a crash leaves the old file as it was.

A first installation has no file yet, and the steering table needs the pot centre, the
map and the steering ratio together. An accepted step whose values cannot make a whole
file yet is kept in a draft beside it (``<file>.draft.json``); the pot map, measured
second, finds the centre there, and the file is written once it can be valid.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from appliance import __version__
from appliance.config.atomic import write_text_atomic
from appliance.config.calibration import CalibrationFile
from appliance.config.calibration_file import (
    BUILTIN_SIMULATED,
    CalibrationError,
    read_calibration_file,
    write_calibration,
)
from appliance.config.calibration_items import ItemRecord
from appliance.config.loader import explain
from appliance.config.models import VehicleConfig


class MergeError(Exception):
    """The result cannot go into the file; the message says why and what to do."""


@dataclass(frozen=True)
class StepResult:
    """What an accepted step contributes: values by dotted path, and its record."""

    item: str  # the [items.<item>] key
    values: Mapping[str, Any]  # e.g. {"steering.pot_centre_counts": 2131.2}
    record: ItemRecord


def draft_path(calibration_path: str | Path) -> Path:
    return Path(f"{calibration_path}.draft.json")


def merge_result(config: VehicleConfig, path: str | Path, result: StepResult) -> str:
    """Merge ``result`` into the calibration file at ``path``; say what was written."""
    if str(path) == BUILTIN_SIMULATED:
        raise MergeError(
            "the built-in simulated calibration is no file to merge into: give "
            "--calibration FILE (a file of its own for this vehicle)"
        )
    path = Path(path)
    if path.exists():
        try:
            base = read_calibration_file(
                path,
                config.name,
                config.simulation.enabled,
                config.simulation.steering.steering_ratio,
            )
        except CalibrationError as exc:
            raise MergeError(
                f"{exc.render()}\nthe existing file is not overwritten: fix it, or move it "
                "away to start a new one"
            ) from None
        data = base.model_dump()
    else:
        data = _draft_data(config, path)
    _apply(data, result)
    data["tool_version"] = __version__
    try:
        merged = CalibrationFile.model_validate(data)
    except ValidationError as exc:
        if path.exists():
            problems = "; ".join(str(p) for p in explain(exc, CalibrationFile))
            raise MergeError(f"the merged calibration would be invalid: {problems}") from None
        _save_draft(path, data)
        return (
            f"{draft_path(path)}: {result.item} kept in the draft; {path} is written once "
            f"the steering is complete ({_missing(data)})"
        )
    write_calibration(path, merged)
    draft = draft_path(path)
    if draft.exists():
        draft.unlink()
    return f"{path}: {result.item} merged"


def _apply(data: dict[str, Any], result: StepResult) -> None:
    for dotted, value in result.values.items():
        table = data
        *parents, leaf = dotted.split(".")
        for name in parents:
            child = table.get(name)
            if not isinstance(child, dict):
                child = table[name] = {}
            table = child
        table[leaf] = value
    items = data.get("items") if isinstance(data.get("items"), dict) else None
    data["items"] = {**(items or {}), result.item: result.record.model_dump()}


def draft_values(config: VehicleConfig, path: str | Path) -> dict[str, Any]:
    """What the draft beside ``path`` holds so far ({} without a draft)."""
    return _draft_data(config, Path(path)) if draft_path(path).exists() else {}


def _draft_data(config: VehicleConfig, path: Path) -> dict[str, Any]:
    draft = draft_path(path)
    if not draft.exists():
        return {
            "vehicle_name": config.name,
            "created_utc": datetime.now(UTC),
            "source": "dbw calibrate (maneuvers)",
        }
    try:
        data = json.loads(draft.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise MergeError(f"{draft}: cannot read the draft ({exc}): move it away") from None
    if not isinstance(data, dict) or data.get("vehicle_name") != config.name:
        raise MergeError(f"{draft}: not a draft for vehicle {config.name!r}: move it away")
    return data


def _save_draft(path: Path, data: Mapping[str, Any]) -> None:
    text = json.dumps(data, default=_json_default, indent=2, allow_nan=False)
    write_text_atomic(draft_path(path), text + "\n")


def _json_default(value: object) -> object:
    if isinstance(value, datetime):
        return value.astimezone(UTC).isoformat().replace("+00:00", "Z")
    raise TypeError(f"no JSON form for {type(value).__name__}")


def _missing(data: Mapping[str, Any]) -> str:
    steering = data.get("steering") or {}
    needed = {
        "pot_centre_counts": "dbw calibrate pot-center",
        "pot_to_wheel_coeffs": "dbw calibrate pot-map",
        "steering_ratio": "dbw calibrate pot-map --steering-ratio, or palm-tree",
    }
    missing = [f"{key} ({how})" for key, how in needed.items() if key not in steering]
    return "missing " + ", ".join(missing) if missing else "see the problems above"
