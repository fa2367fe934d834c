"""The calibration of one vehicle: the file's schema and the daemon's view of it.

The daemon refuses to leave SELF_CHECK without a valid calibration, because every steering
angle it reports or commands goes through this map: a wrong pot centre steers the vehicle
off its path with every check in the safety layer still green. So the file is checked far
beyond field bounds. The map must be strictly monotonic over the readings it accepts (a map
that folds back gives two wheel angles for one reading and cannot be inverted), it must
imply a steering-wheel travel a real vehicle has, and it must name the vehicle it was
measured on. Readings outside the calibrated range are refused, not extrapolated: outside
it the pot is broken or unplugged, and a guess is worse than a fault.

The optional ``[scanners.left]`` / ``[scanners.right]`` tables hold what ``dbw calibrate
scanners`` measured of each LMS111 at the docked pose: a range offset and a mount yaw
offset (and a lateral offset where the docking left it observable), with their σ. They
came after version 1 without a version bump, like ``counter_steer`` and ``guidance``
before them: the version says what the fields *mean*, and an optional table adds meaning
without changing any other field's, so every version-1 file still loads unchanged.

``steering.wheel_to_tyre_coeffs`` (optional, added the same way) is the palm tree's
wheel-to-tyre map; without it the constant ``steering_ratio`` converts, with it the map
does and ``steering_ratio`` must be its slope at straight ahead, so a reader that knows
only the ratio still reads the right one near the centre.

``[items.<step>]`` records how each maneuver's result was obtained (method, date, tool
version, residuals, verdict, raw data): :mod:`appliance.config.calibration_items`.
The optional ``[pedals.throttle]`` and ``[pedals.brake]`` are the pedal sweep's maps:
:mod:`appliance.config.calibration_pedals`.

Reading and writing the file is :mod:`appliance.config.calibration_file`; the map's
polynomial and its fit are :mod:`calibration.pot_map`; the scanner fit is
:mod:`appliance.localization.scanner_calibration`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Annotated, Final, Literal, Self

import numpy as np
from pydantic import (
    AwareDatetime,
    BaseModel,
    ConfigDict,
    Field,
    FiniteFloat,
    field_validator,
    model_validator,
)

from appliance.config.calibration_items import CalibrationItems
from appliance.config.calibration_pedals import PedalsCalibration
from appliance.guidance.pure_pursuit import LookaheadSchedule
from calibration.pot_map import (
    MAX_POT_TO_WHEEL_COEFFS,
    wheel_rad_at,
    wheel_slope_rad_per_count,
)
from calibration.servo_torque import TorqueStats

SCHEMA_VERSION: Final = 1
POT_FULL_SCALE_COUNTS = 4095  # 12-bit ADC
MONOTONIC_CHECK_POINTS = 512
MAX_WHEEL_TO_TYRE_COEFFS = 7
# A steering wheel turns between half a radian and about five turns from centre to lock.
MIN_WHEEL_TRAVEL_RAD = 0.5
MAX_WHEEL_TRAVEL_RAD = 30.0

Counts = Annotated[int, Field(ge=0, le=POT_FULL_SCALE_COUNTS)]

# Bounds of a scanner's calibration, the same as the fit's acceptance thresholds: a
# larger offset is a wrong mount or a broken unit, not something to calibrate away.
MAX_SCANNER_RANGE_OFFSET_M = 0.1  # the data sheet's systematic error is ±30 mm
MAX_SCANNER_YAW_OFFSET_DEG = 2.0  # a bracket is off by tenths of a degree
MAX_SCANNER_LATERAL_OFFSET_M = 0.05  # a bracket is off by millimetres
MAX_SCANNER_RESIDUAL_RMS_M = 0.05
SCANNER_NAMES: Final = ("left", "right")


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


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
    # The palm tree's map (Stanley et al., Fig. 19): tyre_rad = sum(c[i] * wheel**(i+1)).
    # Absent: the constant ratio above. Present: it rules, and steering_ratio is its slope
    # at straight ahead (1 / c[0]), kept for what reads only the ratio.
    wheel_to_tyre_coeffs: tuple[FiniteFloat, ...] | None = Field(
        None, min_length=1, max_length=MAX_WHEEL_TO_TYRE_COEFFS
    )

    @model_validator(mode="after")
    def _tyre_map_is_usable(self) -> Self:
        coeffs = self.wheel_to_tyre_coeffs
        if coeffs is None:
            return self
        if not coeffs[0] > 0.0 or abs(self.steering_ratio * coeffs[0] - 1.0) > 1e-3:
            raise ValueError(
                f"wheel_to_tyre_coeffs[0] ({coeffs[0]:.6g} tyre rad per wheel rad) must be "
                f"1 / steering_ratio ({1.0 / self.steering_ratio:.6g}): the ratio is the "
                "map's slope at straight ahead"
            )
        with np.errstate(all="ignore"):
            ends = [
                float(wheel_rad_at(self.pot_to_wheel_coeffs, c - self.pot_centre_counts))
                for c in (self.pot_valid_min_counts, self.pot_valid_max_counts)
            ]
            wheel = np.linspace(min(ends), max(ends), MONOTONIC_CHECK_POINTS)
            slope = wheel_slope_rad_per_count(coeffs, wheel)  # same polynomial form
        if not np.all(slope > 0.0):
            raise ValueError(
                "wheel_to_tyre_coeffs is not strictly increasing over the pot's valid range "
                f"({min(ends):.2f}..{max(ends):.2f} rad of wheel): one tyre angle would need "
                "two wheel angles"
            )
        return self

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


class LookaheadScheduleCalibration(_Model):
    """The tracker's look-ahead ``L(v) = clamp(offset + gain v, min, max)`` as tuned on the
    vehicle (`dbw calibrate lookahead`, Stanley et al. Fig. 20)."""

    offset_m: float = Field(ge=-20.0, le=50.0)
    gain_s: float = Field(ge=0.0, le=10.0)
    min_m: float = Field(gt=0.0, le=50.0)
    max_m: float = Field(gt=0.0, le=100.0)

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.max_m < self.min_m:
            raise ValueError(f"max_m ({self.max_m}) must not be below min_m ({self.min_m})")
        return self

    def schedule(self) -> LookaheadSchedule:
        return LookaheadSchedule(self.offset_m, self.gain_s, self.min_m, self.max_m)


class ServoTorqueBaseline(_Model):
    """The steering servo's load at tuning time (``calibration.servo_torque``): the
    look-ahead holds for this servo; a later comparison flags re-tuning (Fig. 21)."""

    c0_nm: float = Field(ge=-1e3, le=1e3)
    c_wheel_nm_per_rad: float = Field(ge=-1e3, le=1e3)
    c_rate_nm_s_per_rad: float = Field(ge=-1e3, le=1e3)
    hard_wheel_rad: float = Field(ge=0.0, le=100.0)
    hard_rate_rad_per_s: float = Field(ge=0.0, le=100.0)
    stall_fraction: float = Field(ge=0.0, le=1.0)
    residual_rms_nm: float = Field(ge=0.0, le=1e3)
    moving_samples: int = Field(ge=1)

    def stats(self) -> TorqueStats:
        """As ``calibration.servo_torque`` compares it."""
        return TorqueStats(
            coeffs=(self.c0_nm, self.c_wheel_nm_per_rad, self.c_rate_nm_s_per_rad),
            residual_rms_nm=self.residual_rms_nm,
            hard_wheel_rad=self.hard_wheel_rad,
            hard_rate_rad_per_s=self.hard_rate_rad_per_s,
            moving=self.moving_samples,
            stalls=0,
            stall_fraction=self.stall_fraction,
            rejected={},
        )

    @classmethod
    def of(cls, stats: TorqueStats) -> ServoTorqueBaseline:
        c0, c_wheel, c_rate = stats.coeffs
        return cls(
            c0_nm=c0,
            c_wheel_nm_per_rad=c_wheel,
            c_rate_nm_s_per_rad=c_rate,
            hard_wheel_rad=stats.hard_wheel_rad,
            hard_rate_rad_per_s=stats.hard_rate_rad_per_s,
            stall_fraction=stats.stall_fraction,
            residual_rms_nm=stats.residual_rms_nm,
            moving_samples=stats.moving,
        )


class GuidanceCalibration(_Model):
    """Guidance parameters tuned on the vehicle. ``look_ahead_m`` (older files): a
    constant look-ahead; ``look_ahead`` (the tuning's schedule) wins where both are."""

    look_ahead_m: float | None = Field(None, gt=0.0, le=50.0)
    look_ahead: LookaheadScheduleCalibration | None = None
    servo_torque: ServoTorqueBaseline | None = None

    def schedule(self) -> LookaheadSchedule | None:
        if self.look_ahead is not None:
            return self.look_ahead.schedule()
        if self.look_ahead_m is not None:
            return LookaheadSchedule(self.look_ahead_m, 0.0, self.look_ahead_m, self.look_ahead_m)
        return None


def _is_utc(value: datetime, name: str) -> datetime:
    if value.utcoffset() != UTC.utcoffset(None):
        raise ValueError(f"{name} must be in UTC, ending in Z (got {value.isoformat()})")
    return value.replace(tzinfo=UTC)


class ScannerCalibrationEntry(_Model):
    """One LMS111's calibration at the docked pose (``dbw calibrate scanners``).

    ``range_offset_m`` is subtracted from every range; the calibrated mount is the
    configured one turned by ``mount_yaw_offset_deg`` and moved by ``lateral_offset_m``
    along the vehicle's y (absent: not observable, the configured y stands). Each σ
    includes the docked pose's tolerance (``lateral_offset_sigma_m`` is there even when
    the offset is not: it is the number that said so).
    """

    range_offset_m: float = Field(ge=-MAX_SCANNER_RANGE_OFFSET_M, le=MAX_SCANNER_RANGE_OFFSET_M)
    range_offset_sigma_m: float = Field(ge=0.0, le=MAX_SCANNER_RANGE_OFFSET_M)
    mount_yaw_offset_deg: float = Field(
        ge=-MAX_SCANNER_YAW_OFFSET_DEG, le=MAX_SCANNER_YAW_OFFSET_DEG
    )
    mount_yaw_offset_sigma_deg: float = Field(ge=0.0, le=MAX_SCANNER_YAW_OFFSET_DEG)
    lateral_offset_m: float | None = Field(
        None, ge=-MAX_SCANNER_LATERAL_OFFSET_M, le=MAX_SCANNER_LATERAL_OFFSET_M
    )
    lateral_offset_sigma_m: float = Field(ge=0.0, le=1.0)
    residual_rms_m: float = Field(ge=0.0, le=MAX_SCANNER_RESIDUAL_RMS_M)
    method: str = Field(min_length=1)  # how it was measured (the fit, the pose, the files)
    measured_utc: AwareDatetime

    @field_validator("measured_utc")
    @classmethod
    def _measured_in_utc(cls, value: datetime) -> datetime:
        return _is_utc(value, "measured_utc")

    @property
    def mount_yaw_offset_rad(self) -> float:
        return math.radians(self.mount_yaw_offset_deg)


class ScannersCalibration(_Model):
    """Both front scanners' calibrations; either may be absent (not calibrated yet)."""

    left: ScannerCalibrationEntry | None = None
    right: ScannerCalibrationEntry | None = None


class CalibrationFile(_Model):
    """One calibration file, schema version 1, as read from TOML."""

    schema_version: Literal[1] = SCHEMA_VERSION
    vehicle_name: str = Field(min_length=1, max_length=64)  # the vehicle config's `name`
    created_utc: AwareDatetime
    source: str = Field(min_length=1)  # how it was obtained: maneuvers and date, or a fit
    steering: SteeringCalibration
    counter_steer: CounterSteerCalibration | None = None
    guidance: GuidanceCalibration | None = None
    scanners: ScannersCalibration | None = None
    pedals: PedalsCalibration | None = None  # the pedal maps (calibration_pedals)
    # Which dbw wrote the file, and how each maneuver's result was obtained (optional:
    # hand-written and older files have neither).
    tool_version: str | None = Field(None, min_length=1, max_length=40)
    items: CalibrationItems | None = None

    @field_validator("created_utc")
    @classmethod
    def _created_in_utc(cls, value: datetime) -> datetime:
        return _is_utc(value, "created_utc")


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
    wheel_to_tyre_coeffs: tuple[float, ...] | None = None
    counter_steer_k_ratio: float | None = None
    guidance: GuidanceCalibration | None = None
    scanners: ScannersCalibration | None = None
    pedals: PedalsCalibration | None = None

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
            wheel_to_tyre_coeffs=(
                None
                if steering.wheel_to_tyre_coeffs is None
                else tuple(float(c) for c in steering.wheel_to_tyre_coeffs)
            ),
            counter_steer_k_ratio=model.counter_steer.k_ratio if model.counter_steer else None,
            guidance=model.guidance,
            scanners=model.scanners,
            pedals=model.pedals,
        )

    @property
    def guidance_schedule(self) -> LookaheadSchedule | None:
        """The look-ahead tuned on the vehicle (None: the tracker's defaults)."""
        return None if self.guidance is None else self.guidance.schedule()

    def scanner(self, name: str) -> ScannerCalibrationEntry | None:
        """The calibration of the ``left`` or ``right`` scanner, or None if it has none.

        Any other name raises KeyError: a misspelt scanner must not read as uncalibrated.
        """
        if name not in SCANNER_NAMES:
            raise KeyError(f"no scanner {name!r}: the calibration file knows {SCANNER_NAMES}")
        if self.scanners is None:
            return None
        entry: ScannerCalibrationEntry | None = getattr(self.scanners, name)
        return entry

    def wheel_rad_from_counts(self, counts: float) -> float | None:
        """Steering-wheel angle, or None for a reading outside the valid range (or NaN)."""
        if not self.pot_valid_min_counts <= counts <= self.pot_valid_max_counts:
            return None
        return float(wheel_rad_at(self.pot_to_wheel_coeffs, counts - self.pot_centre_counts))

    def tyre_rad_from_counts(self, counts: float) -> float | None:
        wheel_rad = self.wheel_rad_from_counts(counts)
        return None if wheel_rad is None else self.tyre_rad_from_wheel(wheel_rad)

    def tyre_rad_from_wheel(self, wheel_rad: float) -> float:
        """Front tyre angle: the palm tree's map where there is one, else the ratio."""
        if self.wheel_to_tyre_coeffs is None:
            return wheel_rad / self.steering_ratio
        return float(wheel_rad_at(self.wheel_to_tyre_coeffs, wheel_rad))

    def wheel_rad_from_tyre(self, tyre_rad: float) -> float:
        """The wheel angle that gives ``tyre_rad``: what the servo is aimed at.

        With a map: bisection over the valid wheel range (the file's validation makes the
        map increasing there), and beyond it the map's end slope, so a wish past the lock
        still points the right way and the servo's own limits stop it.
        """
        coeffs = self.wheel_to_tyre_coeffs
        if coeffs is None or not math.isfinite(tyre_rad):
            return tyre_rad * self.steering_ratio  # NaN stays NaN: never a made-up angle
        low, high = self.valid_wheel_range_rad
        tyre_low, tyre_high = self.tyre_rad_from_wheel(low), self.tyre_rad_from_wheel(high)
        if tyre_rad <= tyre_low:
            slope = float(wheel_slope_rad_per_count(coeffs, np.array([low]))[0])
            return low + (tyre_rad - tyre_low) / slope
        if tyre_rad >= tyre_high:
            slope = float(wheel_slope_rad_per_count(coeffs, np.array([high]))[0])
            return high + (tyre_rad - tyre_high) / slope
        for _ in range(50):  # 30 rad / 2**50: far below a servo tick
            middle = 0.5 * (low + high)
            if self.tyre_rad_from_wheel(middle) < tyre_rad:
                low = middle
            else:
                high = middle
        return 0.5 * (low + high)

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
        return self.tyre_rad_from_wheel(low), self.tyre_rad_from_wheel(high)

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
