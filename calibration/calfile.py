"""The versioned calibration file: its schema, the runtime view, the loader and the writer.

The daemon refuses to leave SELF_CHECK without a valid calibration, because every steering
angle it reports or commands goes through this map: a wrong pot centre steers the vehicle
off its path with every check in the safety layer still green. So the file is checked far
beyond field bounds. The map must be strictly monotonic over the readings it accepts (a map
that folds back gives two wheel angles for one reading and cannot be inverted), it must
imply a steering-wheel travel a real vehicle has, and it must name the vehicle it was
measured on. Readings outside the calibrated range are refused, not extrapolated: outside
it the pot is broken or unplugged, and a guess is worse than a fault.

The writer replaces the file atomically and reads its own output back before doing so, so
a crash, a full disk or a bug in the writer never leaves a file the daemon cannot load in
place of one it could.
"""

from __future__ import annotations

import contextlib
import math
import os
import tempfile
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Annotated, Any, Final, Literal, Self

import numpy as np
import numpy.typing as npt
from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    FiniteFloat,
    ValidationError,
    field_validator,
    model_validator,
)

from appliance.config.loader import ConfigProblem, explain

SCHEMA_VERSION: Final = 1
BUILTIN_SIMULATED = "builtin:simulated"
POT_FULL_SCALE_COUNTS = 4095  # 12-bit ADC
# Up to degree 9: the inverse of a pot map with a cubic term near its lock needs it to
# reach a few mrad of steering-wheel angle (degree 5 cannot do better than ~0.02 rad).
MAX_POT_TO_WHEEL_COEFFS = 9
MONOTONIC_CHECK_POINTS = 512
# A steering wheel turns between half a radian and about five turns from centre to lock.
MIN_WHEEL_TRAVEL_RAD = 0.5
MAX_WHEEL_TRAVEL_RAD = 30.0

CalibrationProblem = ConfigProblem  # same shape: a TOML field path and one sentence

Counts = Annotated[int, Field(ge=0, le=POT_FULL_SCALE_COUNTS)]
FloatArray = npt.NDArray[np.float64]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


def wheel_rad_at(coeffs: Sequence[float], offset_counts: Any) -> Any:
    """``sum(coeffs[i] * d**(i+1))`` for ``d = offset_counts`` (a float or an array)."""
    return np.polynomial.polynomial.polyval(offset_counts, (0.0, *coeffs))


def wheel_slope_rad_per_count(coeffs: Sequence[float], offset_counts: FloatArray) -> FloatArray:
    """Derivative of :func:`wheel_rad_at` with respect to the counts."""
    derivative = [(i + 1) * c for i, c in enumerate(coeffs)]
    return np.asarray(np.polynomial.polynomial.polyval(offset_counts, derivative), np.float64)


class SteeringCalibration(_Model):
    """The steering pot: raw 12-bit counts to steering-wheel angle, and the steering ratio."""

    # Raw reading with the wheels straight ahead: 0 rad by definition.
    pot_centre_counts: float = Field(ge=0.0, le=POT_FULL_SCALE_COUNTS)
    # wheel_rad = sum(coeff[i] * d**(i+1)), d = counts - pot_centre_counts; rad per count^(i+1).
    pot_to_wheel_coeffs: tuple[FiniteFloat, ...] = Field(
        min_length=1, max_length=MAX_POT_TO_WHEEL_COEFFS
    )
    # Readings outside [min, max] are a broken or unplugged pot.
    pot_valid_min_counts: Counts
    pot_valid_max_counts: Counts
    steering_ratio: float = Field(gt=1.0, le=60.0)  # steering-wheel rad per tyre rad

    @model_validator(mode="after")
    def _map_is_usable(self) -> Self:
        low, high = self.pot_valid_min_counts, self.pot_valid_max_counts
        centre = self.pot_centre_counts
        if not low < centre < high:
            raise ValueError(
                "pot_centre_counts must lie strictly between pot_valid_min_counts and "
                f"pot_valid_max_counts (got min {low}, centre {centre}, max {high})"
            )
        with np.errstate(all="ignore"):
            for name, counts in (("pot_valid_min_counts", low), ("pot_valid_max_counts", high)):
                wheel_rad = float(wheel_rad_at(self.pot_to_wheel_coeffs, counts - centre))
                if not MIN_WHEEL_TRAVEL_RAD <= abs(wheel_rad) <= MAX_WHEEL_TRAVEL_RAD:
                    raise ValueError(
                        f"pot_to_wheel_coeffs gives {wheel_rad:.4g} rad of steering-wheel angle "
                        f"at {name} = {counts}; a steering wheel turns "
                        f"{MIN_WHEEL_TRAVEL_RAD}..{MAX_WHEEL_TRAVEL_RAD} rad from centre to "
                        "lock: check the coefficients (rad per count, not per degree) and "
                        "the valid range"
                    )
            offsets = np.linspace(low - centre, high - centre, MONOTONIC_CHECK_POINTS)
            signs = np.sign(wheel_slope_rad_per_count(self.pot_to_wheel_coeffs, offsets))
        # np.sign(nan) is nan, which matches no sign: a non-finite slope counts as a fold.
        bad = np.flatnonzero((signs != signs[0]) | (signs == 0.0))
        if bad.size:
            raise ValueError(
                "pot_to_wheel_coeffs is not strictly monotonic between pot_valid_min_counts "
                f"and pot_valid_max_counts: its slope changes sign near "
                f"{centre + offsets[bad[0]]:.0f} counts, so one reading would mean two wheel "
                "angles (increasing or decreasing are both fine, a fold is not)"
            )
        return self


class CounterSteerCalibration(_Model):
    """Measured rear-to-front steer ratio of proportional counter-steer (a later maneuver)."""

    k_ratio: float | None = Field(None, ge=0.0, le=1.5)


class GuidanceCalibration(_Model):
    """Guidance parameters tuned on the vehicle (a later maneuver)."""

    look_ahead_m: float | None = Field(None, gt=0.0, le=50.0)


class CalibrationFile(_Model):
    """One calibration file, schema version 1, as read from TOML."""

    schema_version: Literal[1] = SCHEMA_VERSION
    vehicle_name: str = Field(min_length=1, max_length=64)  # the vehicle config's `name`
    created_utc: AwareDatetime
    source: str = Field(min_length=1)  # how it was obtained: maneuvers and date, or a fit
    steering: SteeringCalibration
    counter_steer: CounterSteerCalibration | None = None
    guidance: GuidanceCalibration | None = None

    @field_validator("created_utc")
    @classmethod
    def _is_utc(cls, value: datetime) -> datetime:
        if value.utcoffset() != UTC.utcoffset(None):
            raise ValueError(f"created_utc must be in UTC, ending in Z (got {value.isoformat()})")
        return value.replace(tzinfo=UTC)


@dataclass(frozen=True)
class Calibration:
    """The runtime view of a validated calibration file: pure conversions, deny by default."""

    vehicle_name: str
    created_utc: datetime
    source: str
    pot_centre_counts: float
    pot_to_wheel_coeffs: tuple[float, ...]
    pot_valid_min_counts: int
    pot_valid_max_counts: int
    steering_ratio: float
    counter_steer_k_ratio: float | None = None
    guidance_look_ahead_m: float | None = None

    @classmethod
    def from_file(cls, model: CalibrationFile) -> Calibration:
        steering = model.steering
        return cls(
            vehicle_name=model.vehicle_name,
            created_utc=model.created_utc,
            source=model.source,
            pot_centre_counts=steering.pot_centre_counts,
            pot_to_wheel_coeffs=tuple(float(c) for c in steering.pot_to_wheel_coeffs),
            pot_valid_min_counts=steering.pot_valid_min_counts,
            pot_valid_max_counts=steering.pot_valid_max_counts,
            steering_ratio=steering.steering_ratio,
            counter_steer_k_ratio=model.counter_steer.k_ratio if model.counter_steer else None,
            guidance_look_ahead_m=model.guidance.look_ahead_m if model.guidance else None,
        )

    def wheel_rad_from_counts(self, counts: float) -> float | None:
        """Steering-wheel angle, or None for a reading outside the valid range (or NaN)."""
        if not self.pot_valid_min_counts <= counts <= self.pot_valid_max_counts:
            return None
        return float(wheel_rad_at(self.pot_to_wheel_coeffs, counts - self.pot_centre_counts))

    def tyre_rad_from_counts(self, counts: float) -> float | None:
        wheel_rad = self.wheel_rad_from_counts(counts)
        return None if wheel_rad is None else wheel_rad / self.steering_ratio

    @property
    def valid_wheel_range_rad(self) -> tuple[float, float]:
        """Lowest and highest steering-wheel angle the valid reading range maps to."""
        ends = [
            float(wheel_rad_at(self.pot_to_wheel_coeffs, counts - self.pot_centre_counts))
            for counts in (self.pot_valid_min_counts, self.pot_valid_max_counts)
        ]
        return min(ends), max(ends)

    @property
    def valid_tyre_range_rad(self) -> tuple[float, float]:
        low, high = self.valid_wheel_range_rad
        return low / self.steering_ratio, high / self.steering_ratio

    def counts_from_wheel_rad(self, wheel_rad: float) -> float:
        """The reading that means ``wheel_rad``: bisection, which the validated monotonic map
        makes exact to well below a count. Raises ValueError outside the valid range."""
        low_rad, high_rad = self.valid_wheel_range_rad
        if not low_rad <= wheel_rad <= high_rad:
            raise ValueError(
                f"steering-wheel angle {wheel_rad} rad is outside the calibrated range "
                f"{low_rad:.4g}..{high_rad:.4g} rad"
            )
        low, high = float(self.pot_valid_min_counts), float(self.pot_valid_max_counts)
        increasing = self._wheel_rad(high) > self._wheel_rad(low)
        for _ in range(60):  # 4095 / 2**60 counts: far below float resolution of the result
            middle = (low + high) / 2.0
            if (self._wheel_rad(middle) < wheel_rad) == increasing:
                low = middle
            else:
                high = middle
        return (low + high) / 2.0

    def _wheel_rad(self, counts: float) -> float:
        return float(wheel_rad_at(self.pot_to_wheel_coeffs, counts - self.pot_centre_counts))


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
    path: str | Path, vehicle_name: str, simulation_enabled: bool = False
) -> Calibration:
    """Load and check the calibration of the vehicle called ``vehicle_name``.

    ``builtin:simulated`` is the built-in simulated vehicle's calibration, accepted only
    when the caller says the simulation is enabled.
    """
    return Calibration.from_file(read_calibration_file(path, vehicle_name, simulation_enabled))


def read_calibration_file(
    path: str | Path, vehicle_name: str, simulation_enabled: bool = False
) -> CalibrationFile:
    """Like :func:`load_calibration`, but the validated file model (to show or rewrite)."""
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
        # Imported here because calibration.simulated builds its result with this module.
        from calibration.simulated import simulated_calibration

        return simulated_calibration(vehicle_name)
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


def write_text_atomic(path: str | Path, text: str) -> None:
    """Replace ``path`` by ``text`` so that a reader sees the old file or the new one, whole.

    Another process may be waiting for the file to appear (the daemon for `dbw sim
    --write-config`), and the vehicle may lose power mid-write: a partly written file would
    parse as a different, valid-looking configuration with its missing sections defaulted.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as handle:
            handle.write(text)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(tmp_name, 0o644)  # mkstemp makes it 0600; the service user must read it
        os.replace(tmp_name, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise
    _fsync_directory(path.parent)


def _fsync_directory(directory: Path) -> None:
    """Make the rename itself durable: the vehicle may lose power right after a write."""
    try:
        fd = os.open(directory, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


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
