"""What each sentence type reads as: values, SI units, empty fields, range and format checks."""

from __future__ import annotations

import datetime as dt
import math
from decimal import Decimal

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from drivers.gnss import (
    FixQuality,
    GgaFix,
    GstError,
    Heading,
    NmeaEvent,
    RmcFix,
    ThsMode,
    VtgVelocity,
)
from tests.unit.gnss.lines import parse_one, reject_reason, xor_checksum

# Published examples (gpsd's NMEA reference, NovAtel and Trimble manuals) with their checksums.
GGA = "GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"
RMC = "GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W"
VTG = "GPVTG,054.7,T,034.4,M,005.5,N,010.2,K"
GST = "GPGST,172814.0,0.006,0.023,0.020,273.6,0.023,0.020,0.031"
HDT = "HEHDT,274.07,T"
THS = "INTHS,123.4,A"

KNOT = 1852 / 3600


def test_test_checksum_matches_published_examples() -> None:
    assert [xor_checksum(b) for b in (GGA, RMC, VTG, GST)] == [0x47, 0x6A, 0x48, 0x6A]


def test_gga() -> None:
    fix = parse_one(GGA)
    assert isinstance(fix, GgaFix)
    assert vars(fix) == pytest.approx(
        {
            "talker": "GP",
            "utc_time_of_day_s": 12 * 3600 + 35 * 60 + 19,
            "lat_deg": 48 + 7.038 / 60,
            "lon_deg": 11 + 31.0 / 60,
            "quality": FixQuality.GPS,
            "satellites": 8,
            "hdop": 0.9,
            "altitude_m": 545.4,
            "geoid_separation_m": 46.9,
            "differential_age_s": None,
        }
    )


def test_rmc() -> None:
    fix = parse_one(RMC)
    assert isinstance(fix, RmcFix)
    assert fix.valid
    assert fix.speed_mps == pytest.approx(22.4 * KNOT)
    assert fix.course_rad == pytest.approx(math.radians(84.4))
    assert fix.utc_date == dt.date(1994, 3, 23)
    assert fix.utc_datetime == dt.datetime(1994, 3, 23, 12, 35, 19, tzinfo=dt.UTC)
    assert fix.lat_deg == pytest.approx(48.1173)
    assert fix.lon_deg == pytest.approx(11.51666667)


def test_rmc_status_v_and_mode_n_are_not_valid_and_two_digit_years_pivot_at_80() -> None:
    body = "GNRMC,083559.00,V,4717.11437,N,00833.91522,E,0.004,77.52,091202,,,A"
    fix = parse_one(body)
    assert isinstance(fix, RmcFix)
    assert not fix.valid
    assert fix.utc_date == dt.date(2002, 12, 9)
    mode_n = parse_one(body.replace(",V,", ",A,").removesuffix("A") + "N")
    assert isinstance(mode_n, RmcFix)
    assert not mode_n.valid


def test_vtg_prefers_km_h_and_falls_back_to_knots() -> None:
    vtg = parse_one(VTG)
    assert isinstance(vtg, VtgVelocity)
    assert (vtg.talker, vtg.valid, vtg.course_rad) == ("GP", True, math.radians(54.7))
    assert vtg.speed_mps == pytest.approx(10.2 / 3.6)
    knots_only = parse_one("GPVTG,054.7,T,034.4,M,005.5,N,,K")
    assert isinstance(knots_only, VtgVelocity)
    assert knots_only.speed_mps == pytest.approx(5.5 * KNOT)
    no_fix = parse_one("GPVTG,,T,,M,,N,,K,N")
    assert no_fix == VtgVelocity("GP", valid=False, speed_mps=None, course_rad=None)


def test_hdt() -> None:
    assert parse_one(HDT) == Heading("HE", "HDT", math.radians(274.07), valid=True, mode=None)
    assert parse_one("GPHDT,,T") == Heading("GP", "HDT", None, valid=False, mode=None)


@pytest.mark.parametrize(
    ("letter", "valid"), [("A", True), ("E", True), ("M", False), ("S", False), ("V", False)]
)
def test_ths_mode_decides_validity(letter: str, valid: bool) -> None:
    heading = parse_one(f"INTHS,123.4,{letter}")
    assert heading == Heading("IN", "THS", math.radians(123.4), valid=valid, mode=ThsMode(letter))


def test_gst() -> None:
    assert parse_one(GST) == GstError(
        talker="GP",
        utc_time_of_day_s=17 * 3600 + 28 * 60 + 14.0,
        rms_m=0.006,
        ellipse_major_m=0.023,
        ellipse_minor_m=0.020,
        ellipse_orientation_rad=math.radians(273.6),
        sigma_lat_m=0.023,
        sigma_lon_m=0.020,
        sigma_alt_m=0.031,
    )


@pytest.mark.parametrize("talker", ["GP", "GN", "GL", "IN"])
@pytest.mark.parametrize(
    ("body", "kind"),
    [
        (GGA, GgaFix),
        (RMC, RmcFix),
        (VTG, VtgVelocity),
        (GST, GstError),
        (HDT, Heading),
        (THS, Heading),
    ],
)
def test_every_type_from_every_talker(talker: str, body: str, kind: type[NmeaEvent]) -> None:
    event = parse_one(talker + body[2:])
    assert isinstance(event, kind)
    assert event.talker == talker


@pytest.mark.parametrize(
    "body",
    [
        "GPGGA,,,,,,0,00,99.99,,,,,,",  # u-blox before the first fix
        "GPRMC,,V,,,,,,,,,,N",
        "GPVTG,,,,,,,,,N",
        "GPGST,,,,,,,,",
        "GPHDT,,",
        "INTHS,,V",
    ],
)
def test_empty_fields_are_none_never_zero(body: str) -> None:
    event = parse_one(body)
    sent = {"talker", "sentence", "valid"}  # never empty
    if isinstance(event, GgaFix):  # quality 0, 0 satellites and hdop 99.99 are sent, not empty
        assert (event.quality, event.satellites, event.hdop) == (FixQuality.INVALID, 0, 99.99)
        sent |= {"quality", "satellites", "hdop"}
    if isinstance(event, Heading):
        assert event.mode in (None, ThsMode.NOT_VALID)
        sent.add("mode")
    empty = {name: value for name, value in vars(event).items() if name not in sent}
    assert len(empty) >= 1
    assert all(value is None for value in empty.values()), empty
    if isinstance(event, RmcFix | VtgVelocity | Heading):
        assert not event.valid


def test_missing_trailing_fields_of_older_versions_are_empty() -> None:
    """NMEA 2.0 RMC (the example) has no mode indicator: valid from the status alone. Fewer
    fields than 2.0 had is not an older version but a damaged sentence."""
    fix = parse_one(RMC)
    assert isinstance(fix, RmcFix)
    assert fix.valid
    assert reject_reason(RMC.removesuffix(",W")) == "malformed"


@pytest.mark.parametrize(
    ("lat", "lon", "lat_deg", "lon_deg"),
    [
        ("4807.038", "01131.000", 48.1173, 11.516666666666667),
        ("0000.000", "00000.000", 0.0, 0.0),
        ("9000.000", "18000.000", 90.0, 180.0),
        ("3351.9876", "15112.5432", 33.86646, 151.20905333333334),
    ],
)
@pytest.mark.parametrize(("ns", "ew"), [("N", "E"), ("S", "W"), ("N", "W"), ("S", "E")])
def test_lat_lon_hemispheres(
    lat: str, lon: str, lat_deg: float, lon_deg: float, ns: str, ew: str
) -> None:
    fix = parse_one(f"GNGGA,000000.00,{lat},{ns},{lon},{ew},4,12,0.6,10.0,M,0.0,M,1.0,0000")
    assert isinstance(fix, GgaFix)
    assert fix.lat_deg == pytest.approx(lat_deg * (-1 if ns == "S" else 1), abs=1e-9)
    assert fix.lon_deg == pytest.approx(lon_deg * (-1 if ew == "W" else 1), abs=1e-9)


def _encode_dm(value_deg: float, degree_digits: int) -> str | None:
    """Decimal degrees to (d)ddmm.mmmmmm via Decimal, the way a receiver formats it."""
    magnitude = Decimal(repr(abs(value_deg)))
    whole = int(magnitude)
    minutes = ((magnitude - whole) * 60).quantize(Decimal("0.000001"))
    if minutes >= 60:
        return None
    return f"{whole:0{degree_digits}d}{minutes:09.6f}"


@given(
    lat=st.floats(-90, 90, allow_nan=False),
    lon=st.floats(-180, 180, allow_nan=False),
)
def test_lat_lon_round_trip_against_an_independent_encoding(lat: float, lon: float) -> None:
    lat_dm, lon_dm = _encode_dm(lat, 2), _encode_dm(lon, 3)
    assume(lat_dm is not None and lon_dm is not None)
    ns, ew = ("S" if lat < 0 else "N"), ("W" if lon < 0 else "E")
    fix = parse_one(f"GPGGA,120000,{lat_dm},{ns},{lon_dm},{ew},1,08,0.9,545.4,M,46.9,M,,")
    assert isinstance(fix, GgaFix)
    # six decimals of a minute: 1e-6 / 60 degrees
    assert fix.lat_deg == pytest.approx(lat, abs=2e-8)
    assert fix.lon_deg == pytest.approx(lon, abs=2e-8)


@pytest.mark.parametrize(
    ("body", "reason"),
    [
        ("GPGGA,123519,9100.000,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", "out_of_range"),
        ("GPGGA,123519,4807.038,N,18100.000,E,1,08,0.9,545.4,M,46.9,M,,", "out_of_range"),
        ("GPGGA,123519,4860.500,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", "out_of_range"),
        ("GPGGA,123519,4807.038,N,01131.000,E,9,08,0.9,545.4,M,46.9,M,,", "out_of_range"),
        ("GPGGA,253519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", "out_of_range"),
        ("GPGGA,123519,4807.038,X,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,48o7.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,nan,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,inf,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,5_45,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,F,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,N,01131.000,E,1,-8,0.9,545.4,M,46.9,M,,", "malformed"),
        ("GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9", "malformed"),
        ("GPRMC,123519,A,4807.038,N,01131.000,E,-22.4,084.4,230394,003.1,W", "out_of_range"),
        ("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,400.0,230394,003.1,W", "out_of_range"),
        ("GPRMC,123519,A,4807.038,N,01131.000,E,022.4,084.4,310294,003.1,W", "out_of_range"),
        ("GPRMC,123519,X,4807.038,N,01131.000,E,022.4,084.4,230394,003.1,W", "malformed"),
        ("GPVTG,054.7,M,034.4,M,005.5,N,010.2,K", "malformed"),
        ("GPGST,172814.0,-0.006,0.023,0.020,273.6,0.023,0.020,0.031", "out_of_range"),
        ("INTHS,123.4,X", "malformed"),
        ("INTHS,361.0,A", "out_of_range"),
        ("HEHDT,274.07,M", "malformed"),
    ],
)
def test_unusable_fields_reject_the_sentence(body: str, reason: str) -> None:
    assert reject_reason(body) == reason
