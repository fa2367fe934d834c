"""The versioned calibration file on disk: the loader and the writer.

The writer replaces the file atomically and reads its own output back before doing so, so
a crash, a full disk or a bug in the writer never leaves a file the daemon cannot load in
place of one it could. ``builtin:simulated`` names the built-in simulated vehicle's
calibration (:mod:`appliance.config.simulated_calibration`), as ``sim`` names a built-in
vehicle profile.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path

from pydantic import BaseModel, ValidationError

from appliance.config.atomic import write_text_atomic
from appliance.config.calibration import (
    SCANNER_NAMES,
    SCHEMA_VERSION,
    Calibration,
    CalibrationFile,
    ScannerCalibrationEntry,
)
from appliance.config.loader import ConfigProblem, explain
from appliance.config.models import VehicleConfig
from appliance.config.simulated_calibration import (
    DEFAULT_SERVO,
    servo_of,
    simulated_calibration,
)

BUILTIN_SIMULATED = "builtin:simulated"

CalibrationProblem = ConfigProblem  # same shape: a TOML field path and one sentence


class CalibrationError(Exception):
    """A calibration that cannot be used; carries every problem found, not just the first."""

    def __init__(self, source: str, problems: list[CalibrationProblem]) -> None:
        self.source = source
        self.problems = problems
        super().__init__(self.render())

    def render(self) -> str:
        lines = [f"{self.source}: {len(self.problems)} problem(s)"]
        lines += [f"  - {problem}" for problem in self.problems]
        return "\n".join(lines)


def load_calibration(
    path: str | Path,
    vehicle_name: str,
    simulation_enabled: bool = False,
    sim_steering_ratio: float = DEFAULT_SERVO.steering_ratio,
) -> Calibration:
    """Load and check the calibration of the vehicle called ``vehicle_name``.

    ``builtin:simulated`` is the built-in simulated vehicle's calibration, accepted only
    when the caller says the simulation is enabled.
    """
    return Calibration.from_file(
        read_calibration_file(path, vehicle_name, simulation_enabled, sim_steering_ratio)
    )


def read_vehicle_calibration(
    config: VehicleConfig, path: str | Path | None = None
) -> CalibrationFile:
    """The calibration file at ``path`` (default: the vehicle's) checked for this vehicle:
    its name, the simulation, and that its steering was measured after the kit's steering
    was installed (``kit.steering_installed_utc``)."""
    path = config.paths.calibration_file if path is None else path
    model = read_calibration_file(
        path, config.name, config.simulation.enabled, config.simulation.steering.steering_ratio
    )
    installed = config.kit.steering_installed_utc
    measured = steering_measured_utc(model)
    if installed is not None and str(path) != BUILTIN_SIMULATED and measured < installed:
        stamp = measured.isoformat().replace("+00:00", "Z")
        raise CalibrationError(
            str(path),
            [
                CalibrationProblem(
                    "created_utc",
                    f"the steering was measured {stamp}, before the kit's steering was "
                    f"installed ({installed.isoformat().replace('+00:00', 'Z')}, "
                    "kit.steering_installed_utc): it describes another installation; run "
                    "`dbw calibrate pot-center` and `dbw calibrate pot-map` again",
                )
            ],
        )
    return model


def steering_measured_utc(model: CalibrationFile) -> datetime:
    """When the steering's numbers were measured: the oldest of the steering maneuvers'
    records, or the file's creation where it has none."""
    items = model.items
    stamps = [
        record.measured_utc
        for record in (
            (items.pot_centre, items.pot_map, items.palm_tree) if items is not None else ()
        )
        if record is not None
    ]
    return min(stamps) if stamps else model.created_utc


def read_calibration_file(
    path: str | Path,
    vehicle_name: str,
    simulation_enabled: bool = False,
    sim_steering_ratio: float = DEFAULT_SERVO.steering_ratio,
) -> CalibrationFile:
    """Like :func:`load_calibration`, but the validated file model (to show or rewrite).
    ``sim_steering_ratio`` is the simulated steering's (``simulation.steering``), which
    the built-in simulated calibration is of."""
    if str(path) == BUILTIN_SIMULATED:
        if not simulation_enabled:
            raise CalibrationError(
                BUILTIN_SIMULATED,
                [
                    CalibrationProblem(
                        "",
                        "a simulated vehicle's calibration on a real vehicle "
                        "(simulation.enabled is false): point paths.calibration_file at "
                        "this vehicle's calibration file",
                    )
                ],
            )
        return simulated_calibration(vehicle_name, servo=servo_of(sim_steering_ratio))
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        message = (
            "calibration file not found: run the calibration maneuvers (README, Calibration) "
            "or point paths.calibration_file at the file"
        )
        raise CalibrationError(str(path), [CalibrationProblem("", message)]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CalibrationError(
            str(path), [CalibrationProblem("", f"cannot read the file: {exc}")]
        ) from None
    return parse_calibration(text, vehicle_name, source=str(path))


def parse_calibration(
    text: str, vehicle_name: str, source: str = "<calibration>"
) -> CalibrationFile:
    model = _parse_model(text, source)
    if model.vehicle_name != vehicle_name:
        raise CalibrationError(
            source,
            [
                CalibrationProblem(
                    "vehicle_name",
                    f"this file calibrates vehicle {model.vehicle_name!r}, but the vehicle "
                    f"config's name is {vehicle_name!r}: use that vehicle's calibration file "
                    "or calibrate this one",
                )
            ],
        )
    return model


def _parse_model(text: str, source: str) -> CalibrationFile:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CalibrationError(source, [CalibrationProblem("", f"not valid TOML: {exc}")]) from None
    version = data.get("schema_version")
    # Only the version is reported for another schema: its other fields mean other things.
    if type(version) is not int or version != SCHEMA_VERSION:
        given = "missing" if version is None else f"unsupported version {version!r}"
        raise CalibrationError(
            source,
            [
                CalibrationProblem(
                    "schema_version",
                    f"{given}; this dbw reads calibration files with "
                    f"schema_version = {SCHEMA_VERSION} only",
                )
            ],
        )
    try:
        return CalibrationFile.model_validate(data)
    except ValidationError as exc:
        raise CalibrationError(source, explain(exc, CalibrationFile)) from None


def dumps_calibration(model: CalibrationFile) -> str:
    """The file's TOML text. Written by hand: the project depends on no TOML writer."""
    header = (
        f"# dbw-applique calibration file, schema version {SCHEMA_VERSION}.\n"
        "# Check it with `dbw calibration check FILE --config VEHICLE`.\n"
    )
    return header + _toml_table(model, prefix="") + "\n"


def write_calibration(path: str | Path, model: CalibrationFile) -> None:
    """Write ``model`` to ``path`` atomically, creating parent directories.

    The text is read back and compared before it replaces anything, so whatever goes wrong
    the old file stays in place, whole.
    """
    path = Path(path)
    text = dumps_calibration(model)
    if _parse_model(text, "<written calibration>").model_dump() != model.model_dump():
        raise ValueError("the written calibration does not read back equal (a writer bug)")
    write_text_atomic(path, text)


def with_scanners(
    model: CalibrationFile, entries: Mapping[str, ScannerCalibrationEntry]
) -> CalibrationFile:
    """``model`` with the named scanners' calibrations replaced and everything else as it
    was (the other scanner's entry included), validated again as a whole."""
    unknown = set(entries) - set(SCANNER_NAMES)
    if unknown:
        raise KeyError(f"no scanner {sorted(unknown)}: the calibration file knows {SCANNER_NAMES}")
    data = model.model_dump()
    scanners = dict(data.get("scanners") or {})
    scanners.update({name: entry.model_dump() for name, entry in entries.items()})
    data["scanners"] = scanners
    return CalibrationFile.model_validate(data)


def merge_scanner_calibration(
    path: str | Path,
    vehicle_name: str,
    entries: Mapping[str, ScannerCalibrationEntry],
    simulation_enabled: bool = False,
) -> CalibrationFile:
    """Read the calibration file at ``path`` (it must exist and be valid for the vehicle),
    replace the named scanners' entries, and write it back atomically; returns what was
    written. Raises `CalibrationError` for a file that cannot be read or used (the
    built-in simulated calibration is no file to write into), OSError if writing fails."""
    if str(path) == BUILTIN_SIMULATED:
        raise CalibrationError(
            BUILTIN_SIMULATED,
            [
                CalibrationProblem(
                    "", "the built-in simulated calibration is not a file to merge into"
                )
            ],
        )
    merged = with_scanners(read_calibration_file(path, vehicle_name, simulation_enabled), entries)
    write_calibration(path, merged)
    return merged


def _toml_table(model: BaseModel, prefix: str) -> str:
    lines = [f"[{prefix}]"] if prefix else []
    tables: list[tuple[str, BaseModel]] = []
    for name in type(model).model_fields:
        value = getattr(model, name)
        if value is None:  # TOML has no null: an absent key reads back as None
            continue
        if isinstance(value, BaseModel):
            tables.append((f"{prefix}.{name}" if prefix else name, value))
        else:
            lines.append(f"{name} = {_toml_value(value)}")
    parts = ["\n".join(lines)] if lines else []
    parts += [_toml_table(table, table_prefix) for table_prefix, table in tables]
    return "\n\n".join(parts)


def _toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"cannot write the non-finite number {value}")
        return float.__repr__(float(value))  # shortest text that reads back to the same float
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, datetime):
        return _toml_string(value.astimezone(UTC).isoformat().replace("+00:00", "Z"))
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, Mapping):  # an inline table, every key quoted
        pairs = ", ".join(f"{_toml_string(str(k))} = {_toml_value(v)}" for k, v in value.items())
        return "{" + (f" {pairs} " if pairs else "") + "}"
    raise TypeError(f"no TOML form for {type(value).__name__}")


_TOML_ESCAPES = {
    '"': '\\"',
    "\\": "\\\\",
    "\b": "\\b",
    "\t": "\\t",
    "\n": "\\n",
    "\f": "\\f",
    "\r": "\\r",
}


def _toml_string(text: str) -> str:
    out = []
    for char in text:
        code = ord(char)
        if char in _TOML_ESCAPES:
            out.append(_TOML_ESCAPES[char])
        elif code < 0x20 or code == 0x7F:
            out.append(f"\\u{code:04X}")
        elif 0xD800 <= code <= 0xDFFF:
            raise ValueError(f"cannot write a lone surrogate (U+{code:04X}) in {text!r}")
        else:
            out.append(char)
    return '"' + "".join(out) + '"'
