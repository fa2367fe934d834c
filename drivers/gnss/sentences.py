"""What the fields of the NMEA 0183 position sentences mean: typed events in SI units.

This module knows nothing of bytes, lines or checksums (`drivers.gnss.nmea` does); it turns the
comma-separated fields of one already-verified sentence into a frozen event, converting once at
the edge: knots and km/h to m/s, degrees to radians, ``ddmm.mmmm`` + hemisphere to signed
decimal degrees, ``hhmmss.ss`` to seconds since UTC midnight.

Two rules hold for every field:

* **An empty field is None, never 0.** NMEA leaves a field empty when the receiver has no value
  (no fix yet, no differential age, no course while standing still). A 0 would be a plausible
  measurement: latitude 0 is the equator, speed 0 is "stopped", and a consumer cannot tell it
  from a real one. None forces the consumer to decide what "unknown" means.
* **A field that is present but unreadable rejects the whole sentence.** pynmea2's typed
  attributes quietly hand back the raw string when a conversion fails (and ``float`` accepts
  ``nan``, ``inf`` and ``1_0``), so the raw fields are read here with strict patterns instead.
  `FieldError.reason` says whether the text was unreadable (``malformed``) or a readable value
  is impossible (``out_of_range``: latitude beyond ±90°, minutes ≥ 60, a negative speed).

Trailing fields that an older NMEA version does not send (RMC's mode indicator before 2.3) are
treated as empty; fewer fields than the oldest version of a sentence has is ``malformed``.
"""

from __future__ import annotations

import datetime as dt
import enum
import math
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Final

KNOT_MPS: Final = 1852.0 / 3600.0
KMH_MPS: Final = 1000.0 / 3600.0

MALFORMED: Final = "malformed"
OUT_OF_RANGE: Final = "out_of_range"


class FieldError(ValueError):
    """A field of a verified sentence that cannot be used; `reason` is the counter key."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


class FixQuality(enum.IntEnum):
    """GGA field 6, with its NMEA 0183 codes (4 and 5 since NMEA 2.3, for RTK)."""

    INVALID = 0
    GPS = 1
    DGPS = 2
    PPS = 3
    RTK_FIXED = 4
    RTK_FLOAT = 5
    DEAD_RECKONING = 6
    MANUAL = 7
    SIMULATION = 8


class ThsMode(enum.Enum):
    """THS mode indicator: where the heading came from."""

    AUTONOMOUS = "A"
    ESTIMATED = "E"
    MANUAL = "M"
    SIMULATOR = "S"
    NOT_VALID = "V"


# A heading the vehicle may steer by: measured (A) or propagated by the INS through a short GNSS
# outage (E). Manual input and simulator output describe no real motion of this vehicle.
THS_VALID_MODES: Final = frozenset({ThsMode.AUTONOMOUS, ThsMode.ESTIMATED})


@dataclass(frozen=True)
class GgaFix:
    """GGA: position fix. Altitude is above mean sea level; add the geoid separation for the
    height above the WGS 84 ellipsoid."""

    talker: str
    utc_time_of_day_s: float | None
    lat_deg: float | None
    lon_deg: float | None
    quality: FixQuality | None
    satellites: int | None
    hdop: float | None
    altitude_m: float | None
    geoid_separation_m: float | None
    differential_age_s: float | None


@dataclass(frozen=True)
class RmcFix:
    """RMC: recommended minimum. `valid` is status A and, from NMEA 2.3, mode indicator not N."""

    talker: str
    valid: bool
    utc_time_of_day_s: float | None
    utc_date: dt.date | None
    lat_deg: float | None
    lon_deg: float | None
    speed_mps: float | None
    course_rad: float | None

    @property
    def utc_datetime(self) -> dt.datetime | None:
        """Date and time of the fix when the sentence carries both."""
        if self.utc_date is None or self.utc_time_of_day_s is None:
            return None
        midnight = dt.datetime.combine(self.utc_date, dt.time(), tzinfo=dt.UTC)
        return midnight + dt.timedelta(seconds=self.utc_time_of_day_s)


@dataclass(frozen=True)
class VtgVelocity:
    """VTG: course (true) and speed over ground. `valid` is False only for mode indicator N."""

    talker: str
    valid: bool
    speed_mps: float | None
    course_rad: float | None


@dataclass(frozen=True)
class Heading:
    """True heading from HDT (a value is valid) or THS (its mode decides, see `ThsMode`)."""

    talker: str
    sentence: str
    heading_rad: float | None
    valid: bool
    mode: ThsMode | None


@dataclass(frozen=True)
class GstError:
    """GST: 1-sigma position error estimates, metres; ellipse orientation from true north."""

    talker: str
    utc_time_of_day_s: float | None
    rms_m: float | None
    ellipse_major_m: float | None
    ellipse_minor_m: float | None
    ellipse_orientation_rad: float | None
    sigma_lat_m: float | None
    sigma_lon_m: float | None
    sigma_alt_m: float | None


NmeaEvent = GgaFix | RmcFix | VtgVelocity | Heading | GstError

_NUMBER = re.compile(r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)")
_UNSIGNED_INT = re.compile(r"\d+")
_TIME = re.compile(r"(\d\d)(\d\d)(\d\d(?:\.\d+)?)")
_DATE = re.compile(r"(\d\d)(\d\d)(\d\d)")
# Degrees take the digits before the last two ahead of the point; NMEA pads them to 2 (lat) or
# 3 (lon), but a receiver that drops leading zeros is still read right.
_DEGREES_MINUTES = re.compile(r"(\d{1,3})(\d\d(?:\.\d+)?)")


def _malformed(message: str) -> FieldError:
    return FieldError(MALFORMED, message)


def _out_of_range(message: str) -> FieldError:
    return FieldError(OUT_OF_RANGE, message)


def _field(fields: Sequence[str], index: int) -> str:
    return fields[index] if index < len(fields) else ""


def _require(fields: Sequence[str], count: int, sentence: str) -> None:
    if len(fields) < count:
        raise _malformed(f"{sentence} has {len(fields)} fields, needs {count}")


def _float(text: str, what: str) -> float | None:
    if not text:
        return None
    if not _NUMBER.fullmatch(text):
        raise _malformed(f"{what} is not a number: {text!r}")
    return float(text)


def _non_negative(text: str, what: str) -> float | None:
    value = _float(text, what)
    if value is not None and value < 0:
        raise _out_of_range(f"{what} is negative: {value}")
    return value


def _int(text: str, what: str) -> int | None:
    if not text:
        return None
    if not _UNSIGNED_INT.fullmatch(text):
        raise _malformed(f"{what} is not an unsigned integer: {text!r}")
    return int(text)


def _angle_rad(text: str, what: str) -> float | None:
    """A direction in degrees from true north, 0..360 inclusive (some receivers send 360.0)."""
    value = _float(text, what)
    if value is None:
        return None
    if not 0.0 <= value <= 360.0:
        raise _out_of_range(f"{what} outside 0..360 degrees: {value}")
    return math.radians(value)


def _symbol(text: str, expected: str, what: str) -> None:
    """A unit or reference letter (M for metres, T for true): empty or exactly the one expected."""
    if text not in ("", expected):
        raise _malformed(f"{what} is {text!r}, expected {expected!r}")


def utc_time_of_day_s(text: str) -> float | None:
    """``hhmmss[.ss]`` as seconds since UTC midnight (second 60 allowed: a leap second)."""
    if not text:
        return None
    match = _TIME.fullmatch(text)
    if match is None:
        raise _malformed(f"time is not hhmmss.ss: {text!r}")
    hours, minutes, seconds = int(match[1]), int(match[2]), float(match[3])
    if hours > 23 or minutes > 59 or seconds >= 61.0:
        raise _out_of_range(f"time out of range: {text!r}")
    return hours * 3600.0 + minutes * 60.0 + seconds


def utc_date(text: str) -> dt.date | None:
    """``ddmmyy``. Two-digit years from 80 are 19xx (GPS began in 1980), the rest 20xx."""
    if not text:
        return None
    match = _DATE.fullmatch(text)
    if match is None:
        raise _malformed(f"date is not ddmmyy: {text!r}")
    day, month, year = int(match[1]), int(match[2]), int(match[3])
    try:
        return dt.date(year + (1900 if year >= 80 else 2000), month, day)
    except ValueError:
        raise _out_of_range(f"no such date: {text!r}") from None


def degrees(value: str, hemisphere: str, *, latitude: bool) -> float | None:
    """``ddmm.mmmm`` (or ``dddmm.mmmm``) and N/S (or E/W) as signed decimal degrees.

    Both fields empty is None (no fix); one without the other is malformed. The result is
    range-checked: |lat| ≤ 90, |lon| ≤ 180, and minutes below 60.
    """
    if not value and not hemisphere:
        return None
    positive, negative, limit = ("N", "S", 90.0) if latitude else ("E", "W", 180.0)
    what = "latitude" if latitude else "longitude"
    match = _DEGREES_MINUTES.fullmatch(value)
    if match is None:
        raise _malformed(f"{what} is not (d)ddmm.mmmm: {value!r}")
    if hemisphere not in (positive, negative):
        raise _malformed(f"{what} hemisphere is {hemisphere!r}")
    whole, minutes = int(match[1]), float(match[2])
    if minutes >= 60.0:
        raise _out_of_range(f"{what} minutes ≥ 60: {value!r}")
    result = whole + minutes / 60.0
    if result > limit:
        raise _out_of_range(f"{what} beyond {limit}: {value!r}")
    return -result if hemisphere == negative else result


def parse_gga(talker: str, fields: Sequence[str]) -> GgaFix:
    _require(fields, 14, "GGA")
    quality_code = _int(fields[5], "fix quality")
    try:
        quality = None if quality_code is None else FixQuality(quality_code)
    except ValueError:
        raise _out_of_range(f"unknown GGA fix quality {quality_code}") from None
    _symbol(fields[9], "M", "altitude unit")
    _symbol(fields[11], "M", "geoid separation unit")
    return GgaFix(
        talker=talker,
        utc_time_of_day_s=utc_time_of_day_s(fields[0]),
        lat_deg=degrees(fields[1], fields[2], latitude=True),
        lon_deg=degrees(fields[3], fields[4], latitude=False),
        quality=quality,
        satellites=_int(fields[6], "satellites"),
        hdop=_non_negative(fields[7], "HDOP"),
        altitude_m=_float(fields[8], "altitude"),
        geoid_separation_m=_float(fields[10], "geoid separation"),
        differential_age_s=_non_negative(fields[12], "differential age"),
    )


def parse_rmc(talker: str, fields: Sequence[str]) -> RmcFix:
    _require(fields, 11, "RMC")
    status = fields[1]
    if status not in ("A", "V"):
        raise _malformed(f"RMC status is {status!r}, expected A or V")
    mode = _field(fields, 11)
    speed_knots = _non_negative(fields[6], "RMC speed")
    return RmcFix(
        talker=talker,
        valid=status == "A" and mode != "N",
        utc_time_of_day_s=utc_time_of_day_s(fields[0]),
        utc_date=utc_date(fields[8]),
        lat_deg=degrees(fields[2], fields[3], latitude=True),
        lon_deg=degrees(fields[4], fields[5], latitude=False),
        speed_mps=None if speed_knots is None else speed_knots * KNOT_MPS,
        course_rad=_angle_rad(fields[7], "RMC course"),
    )


def parse_vtg(talker: str, fields: Sequence[str]) -> VtgVelocity:
    """Speed from the km/h field when present: it carries more resolution than knots."""
    _require(fields, 8, "VTG")
    for index, expected in ((1, "T"), (3, "M"), (5, "N"), (7, "K")):
        _symbol(fields[index], expected, f"VTG field {index + 1}")
    speed_kmh = _non_negative(fields[6], "VTG speed km/h")
    speed_knots = _non_negative(fields[4], "VTG speed knots")
    if speed_kmh is not None:
        speed_mps: float | None = speed_kmh * KMH_MPS
    else:
        speed_mps = None if speed_knots is None else speed_knots * KNOT_MPS
    return VtgVelocity(
        talker=talker,
        valid=_field(fields, 8) != "N",
        speed_mps=speed_mps,
        course_rad=_angle_rad(fields[0], "VTG true course"),
    )


def parse_hdt(talker: str, fields: Sequence[str]) -> Heading:
    _require(fields, 2, "HDT")
    _symbol(fields[1], "T", "HDT reference")
    heading_rad = _angle_rad(fields[0], "HDT heading")
    return Heading(talker, "HDT", heading_rad, valid=heading_rad is not None, mode=None)


def parse_ths(talker: str, fields: Sequence[str]) -> Heading:
    _require(fields, 2, "THS")
    try:
        mode = ThsMode(fields[1]) if fields[1] else None
    except ValueError:
        raise _malformed(f"THS mode is {fields[1]!r}") from None
    heading_rad = _angle_rad(fields[0], "THS heading")
    valid = heading_rad is not None and mode in THS_VALID_MODES
    return Heading(talker, "THS", heading_rad, valid=valid, mode=mode)


def parse_gst(talker: str, fields: Sequence[str]) -> GstError:
    _require(fields, 8, "GST")
    return GstError(
        talker=talker,
        utc_time_of_day_s=utc_time_of_day_s(fields[0]),
        rms_m=_non_negative(fields[1], "GST rms"),
        ellipse_major_m=_non_negative(fields[2], "GST ellipse major"),
        ellipse_minor_m=_non_negative(fields[3], "GST ellipse minor"),
        ellipse_orientation_rad=_angle_rad(fields[4], "GST ellipse orientation"),
        sigma_lat_m=_non_negative(fields[5], "GST sigma lat"),
        sigma_lon_m=_non_negative(fields[6], "GST sigma lon"),
        sigma_alt_m=_non_negative(fields[7], "GST sigma alt"),
    )


SENTENCE_PARSERS: Final[Mapping[str, Callable[[str, Sequence[str]], NmeaEvent]]] = {
    "GGA": parse_gga,
    "RMC": parse_rmc,
    "VTG": parse_vtg,
    "HDT": parse_hdt,
    "THS": parse_ths,
    "GST": parse_gst,
}
"""Sentence type (talker stripped: GPGGA, GNGGA and INGGA all read alike) to field reader."""
