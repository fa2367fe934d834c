"""GNSS epochs to a timed pose, its extrapolation and its verdict, against independent
computations: WGS 84 to ENU written out here (not pymap3d), arcs from their centre, yaw
rates from the headings' own differences, and every refusal's exact wording."""

from __future__ import annotations

import functools
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from appliance.localization.gnss_pose import (
    GnssNoFix,
    GnssPose,
    GnssPoseAssembler,
    GnssPoseParams,
    HeadingSource,
    SigmaSource,
)
from appliance.localization.gnss_quality import (
    FixVerdictParams,
    extrapolate,
    fix_verdict,
)
from appliance.localization.local_frame import LocalFrame
from drivers.gnss import NmeaReceiver, nmea_checksum
from drivers.gnss.sentences import (
    FixQuality,
    GgaFix,
    GstError,
    Heading,
    NmeaEvent,
    RmcFix,
    ThsMode,
    VtgVelocity,
)

ORIGIN_LAT_DEG, ORIGIN_LON_DEG = 42.36, -71.06  # Boston
FRAME = LocalFrame(ORIGIN_LAT_DEG, ORIGIN_LON_DEG)
LATENCY_S = 0.035
PARAMS = GnssPoseParams(receiver_latency_s=LATENCY_S)
KNOT_MPS = 1852.0 / 3600.0
PERIOD_S = 0.1  # a 10 Hz receiver

# --- NMEA lines, the way a receiver sends them -------------------------------------------


def line(body: str) -> bytes:
    return f"${body}*{nmea_checksum(body):02X}\r\n".encode("ascii")


def utc_text(utc_s: float) -> str:
    h, rest = divmod(round(utc_s * 100), 360000)
    m, cs = divmod(rest, 6000)
    return f"{h:02d}{m:02d}{cs // 100:02d}.{cs % 100:02d}"


def nmea_angle(value_deg: float, *, latitude: bool) -> tuple[str, str, float]:
    """(ddmm.mmmmmmm, hemisphere, the exact degrees that text stands for)."""
    whole = int(abs(value_deg))
    minutes = round((abs(value_deg) - whole) * 60.0, 7)
    width = 2 if latitude else 3
    text = f"{whole:0{width}d}{minutes:010.7f}"
    hemisphere = ("N" if value_deg >= 0 else "S") if latitude else ("E" if value_deg >= 0 else "W")
    exact = (whole + minutes / 60.0) * (1 if value_deg >= 0 else -1)
    return text, hemisphere, exact


def gga(
    utc_s: float,
    lat_deg: float = ORIGIN_LAT_DEG,
    lon_deg: float = ORIGIN_LON_DEG,
    *,
    quality: int = 4,
    satellites: int = 14,
    hdop: float = 0.8,
    altitude_m: float = 12.5,
    geoid_m: float = -28.9,
) -> str:
    lat, ns, _ = nmea_angle(lat_deg, latitude=True)
    lon, ew, _ = nmea_angle(lon_deg, latitude=False)
    return (
        f"GPGGA,{utc_text(utc_s)},{lat},{ns},{lon},{ew},{quality},{satellites:02d},{hdop:.1f},"
        f"{altitude_m:.3f},M,{geoid_m:.1f},M,1.0,0000"
    )


def rmc(utc_s: float, *, speed_kn: float = 0.0, course_deg: float = 0.0, status: str = "A") -> str:
    lat, ns, _ = nmea_angle(ORIGIN_LAT_DEG, latitude=True)
    lon, ew, _ = nmea_angle(ORIGIN_LON_DEG, latitude=False)
    return (
        f"GPRMC,{utc_text(utc_s)},{status},{lat},{ns},{lon},{ew},{speed_kn:.2f},"
        f"{course_deg:.2f},230394,,,{'A' if status == 'A' else 'N'}"
    )


def vtg(*, course_deg: float, speed_kmh: float) -> str:
    return f"GPVTG,{course_deg:.2f},T,,M,{speed_kmh / 1.852:.3f},N,{speed_kmh:.3f},K,A"


def hdt(heading_deg: float) -> str:
    return f"GPHDT,{heading_deg:.3f},T"


def ths(heading_deg: float, mode: str = "A") -> str:
    return f"GPTHS,{heading_deg:.3f},{mode}"


def gst(
    utc_s: float, *, sig_lat: float = 0.012, sig_lon: float = 0.009, major: float = 0.015
) -> str:
    return f"GPGST,{utc_text(utc_s)},0.5,{major:.3f},0.008,30.0,{sig_lat:.3f},{sig_lon:.3f},0.02"


def events_of(*bodies: str) -> list[NmeaEvent]:
    """Through the real receiver, so the events are what the daemon will see."""
    receiver = NmeaReceiver()
    receiver.receive_data(b"".join(line(body) for body in bodies))
    events = list(receiver.events())
    assert len(events) == len(bodies), receiver.counts
    return events


@functools.cache
def event_of(body: str) -> NmeaEvent:
    [event] = events_of(body)
    return event


def feed(
    assembler: GnssPoseAssembler, bodies: list[str], start_s: float, step_s: float = 0.004
) -> list[GnssPose | GnssNoFix | None]:
    """Each sentence a few ms after the last, as a burst on a fast serial line."""
    return [
        assembler.update(event, start_s + i * step_s) for i, event in enumerate(events_of(*bodies))
    ]


def burst(utc_s: float, heading_deg: float = 30.0, speed_kn: float = 4.0) -> list[str]:
    course = (heading_deg + 2.0) % 360.0
    return [
        gga(utc_s),
        rmc(utc_s, speed_kn=speed_kn, course_deg=course),
        vtg(course_deg=course, speed_kmh=speed_kn * 1.852),
        hdt(heading_deg),
        gst(utc_s),
    ]


def epoch(assembler: GnssPoseAssembler, bodies: list[str], start_s: float) -> GnssPose | GnssNoFix:
    """The one output of a burst, whether it came out complete or when its window closed."""
    outputs = feed(assembler, bodies, start_s)
    outputs.append(assembler.expire(start_s + PARAMS.epoch_window_s + 1e-3))
    [out] = [out for out in outputs if out is not None]
    return out


def warmed(assembler: GnssPoseAssembler, utc_s: float = 45000.0, start_s: float = 100.0) -> None:
    """Two complete epochs, so the assembler has learned what this receiver sends."""
    for k in range(2):
        feed(assembler, burst(utc_s + k * PERIOD_S), start_s + k * PERIOD_S)


def new() -> GnssPoseAssembler:
    return GnssPoseAssembler(FRAME, PARAMS)


# --- an independent geodesy ---------------------------------------------------------------

WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563


def ecef(lat_deg: float, lon_deg: float, h_m: float) -> np.ndarray:
    e2 = WGS84_F * (2.0 - WGS84_F)
    lat, lon = math.radians(lat_deg), math.radians(lon_deg)
    n = WGS84_A_M / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
    return np.array(
        [
            (n + h_m) * math.cos(lat) * math.cos(lon),
            (n + h_m) * math.cos(lat) * math.sin(lon),
            (n * (1.0 - e2) + h_m) * math.sin(lat),
        ]
    )


def enu(lat_deg: float, lon_deg: float, h_m: float) -> np.ndarray:
    lat0, lon0 = math.radians(ORIGIN_LAT_DEG), math.radians(ORIGIN_LON_DEG)
    d = ecef(lat_deg, lon_deg, h_m) - ecef(ORIGIN_LAT_DEG, ORIGIN_LON_DEG, 0.0)
    east = np.array([-math.sin(lon0), math.cos(lon0), 0.0])
    north = np.array(
        [-math.sin(lat0) * math.cos(lon0), -math.sin(lat0) * math.sin(lon0), math.cos(lat0)]
    )
    up = np.array(
        [math.cos(lat0) * math.cos(lon0), math.cos(lat0) * math.sin(lon0), math.sin(lat0)]
    )
    return np.array([d @ east, d @ north, d @ up])


# --- position and timing ------------------------------------------------------------------


@pytest.mark.parametrize(
    ("d_lat_deg", "d_lon_deg", "altitude_m"),
    [
        (0.0, 0.0, 28.9),
        (6e-4, 0.0, 40.0),
        (0.0, -9e-4, 0.0),
        (-5e-4, 8e-4, 100.0),
        (3e-4, 4e-4, 5.0),
    ],
)
def test_enu_position_matches_an_independent_wgs84_computation_to_a_millimetre(
    d_lat_deg: float, d_lon_deg: float, altitude_m: float
) -> None:
    lat, lon = ORIGIN_LAT_DEG + d_lat_deg, ORIGIN_LON_DEG + d_lon_deg
    geoid_m = -28.9
    [event] = events_of(gga(45000.0, lat, lon, altitude_m=altitude_m, geoid_m=geoid_m))
    assembler = new()
    assert assembler.update(event, 10.0) is None  # the first epoch waits: nothing learned
    pose = assembler.expire(10.0 + PARAMS.epoch_window_s + 1e-3)
    assert isinstance(pose, GnssPose)
    exact_lat = nmea_angle(lat, latitude=True)[2]
    exact_lon = nmea_angle(lon, latitude=False)[2]
    expected = enu(exact_lat, exact_lon, altitude_m + geoid_m)  # GGA: above the geoid
    assert np.hypot(*expected[:2]) < 110.0
    assert pose.east_m == pytest.approx(expected[0], abs=1e-3)
    assert pose.north_m == pytest.approx(expected[1], abs=1e-3)
    assert pose.up_m == pytest.approx(expected[2], abs=1e-3)


def test_a_complete_epoch_carries_every_field_in_si_units_and_the_latency() -> None:
    assembler = new()
    warmed(assembler)
    outputs = feed(assembler, burst(45000.2, heading_deg=30.0, speed_kn=4.0), 100.2)
    assert outputs[:-1] == [None] * 4, "emitted before the epoch was complete"
    pose = outputs[-1]
    assert isinstance(pose, GnssPose)
    assert pose.measurement_time_s == pytest.approx(100.2 - LATENCY_S)  # the GGA's arrival
    assert pose.utc_time_of_day_s == pytest.approx(45000.2)
    assert pose.quality is FixQuality.RTK_FIXED
    assert (pose.satellites, pose.hdop) == (14, 0.8)
    assert pose.heading_source is HeadingSource.TRUE_HEADING
    assert pose.yaw_rad == pytest.approx(math.radians(90.0 - 30.0), abs=1e-6)
    assert pose.course_yaw_rad == pytest.approx(math.radians(90.0 - 32.0), abs=1e-6)
    assert pose.speed_mps == pytest.approx(4.0 * KNOT_MPS, rel=1e-4)
    assert pose.sigma_source is SigmaSource.GST
    assert (pose.sigma_east_m, pose.sigma_north_m, pose.sigma_worst_m) == (0.009, 0.012, 0.015)
    assert pose.yaw_rate_rad_per_s == pytest.approx(0.0, abs=1e-9)


def test_true_north_away_from_the_origin_is_turned_by_the_meridians_convergence() -> None:
    """Due north 8 km east of the origin is not ENU north: measured here through the frame."""
    lat, lon = ORIGIN_LAT_DEG, ORIGIN_LON_DEG + 0.1
    assembler = new()
    feed(assembler, [gga(45000.0, lat, lon), hdt(0.0)], 10.0)
    pose = assembler.expire(11.0)
    assert isinstance(pose, GnssPose) and pose.yaw_rad is not None
    exact_lat = nmea_angle(lat, latitude=True)[2]
    exact_lon = nmea_angle(lon, latitude=False)[2]
    e0, n0, _ = FRAME.to_local(exact_lat, exact_lon)
    e1, n1, _ = FRAME.to_local(exact_lat + 1e-6, exact_lon)
    assert pose.yaw_rad == pytest.approx(math.atan2(n1 - n0, e1 - e0), abs=1e-6)
    assert pose.yaw_rad - math.pi / 2 > 1e-3  # a real effect, not rounding


def test_a_reordered_burst_gives_the_same_pose() -> None:
    canonical, shuffled = new(), new()
    warmed(canonical)
    warmed(shuffled)
    [*_, a] = feed(canonical, burst(45000.2), 100.2)
    b, c, d, e, g = burst(45000.2)
    [*_, b_out] = feed(shuffled, [e, d, b, g, c], 100.2)  # GST, HDT first; VTG last
    assert isinstance(a, GnssPose) and isinstance(b_out, GnssPose)
    assert replace(b_out, measurement_time_s=a.measurement_time_s) == a
    assert b_out.measurement_time_s == pytest.approx(100.2 + 2 * 0.004 - LATENCY_S)


def test_missing_sentences_are_marked_missing_and_the_epoch_still_comes_out() -> None:
    assembler = new()
    warmed(assembler)
    # No HDT, no GST, no RMC/VTG: only the position.
    assert feed(assembler, [gga(45000.2, hdop=0.9)], 100.2) == [None]  # waits for the rest
    pose = assembler.expire(100.2 + PARAMS.epoch_window_s + 1e-3)
    assert isinstance(pose, GnssPose)
    assert (pose.yaw_rad, pose.heading_source) == (None, HeadingSource.MISSING)
    assert (pose.speed_mps, pose.course_yaw_rad, pose.yaw_rate_rad_per_s) == (None, None, None)
    assert pose.sigma_source is SigmaSource.HDOP
    assert pose.sigma_east_m == pose.sigma_north_m == pytest.approx(0.9 * PARAMS.hdop_uere_m)


def test_without_a_heading_sentence_the_course_stands_in_when_moving_and_says_so() -> None:
    assembler = new()
    fast = [gga(45000.0), rmc(45000.0, speed_kn=6.0, course_deg=300.0), gst(45000.0)]
    pose = epoch(assembler, fast, 10.0)
    assert isinstance(pose, GnssPose)
    assert pose.heading_source is HeadingSource.COURSE
    assert pose.yaw_rad == pytest.approx(math.radians(90.0 - 300.0 + 360.0), abs=1e-6)
    slow = [gga(45001.0), rmc(45001.0, speed_kn=1.0, course_deg=300.0), gst(45001.0)]
    pose = epoch(assembler, slow, 12.0)  # 0.51 m/s: below the 1 m/s where course means much
    assert isinstance(pose, GnssPose)
    assert (pose.yaw_rad, pose.heading_source) == (None, HeadingSource.MISSING)
    assert pose.speed_mps == pytest.approx(KNOT_MPS, rel=1e-3)


def test_a_late_sentence_of_the_previous_epoch_is_not_mixed_into_the_next() -> None:
    assembler = new()
    warmed(assembler)
    b = burst(45000.2)
    feed(assembler, b[:4], 100.2)  # GGA RMC VTG HDT: waiting for GST
    # The next epoch begins; then the previous epoch's GST and GGA arrive late.
    out = feed(assembler, [gga(45000.3, ORIGIN_LAT_DEG + 1e-4)], 100.3)
    previous = out[0]
    assert isinstance(previous, GnssPose) and previous.sigma_source is SigmaSource.HDOP
    late = [gst(45000.2, sig_lat=0.9, sig_lon=0.9, major=0.9), gga(45000.2, ORIGIN_LAT_DEG - 1e-3)]
    assert feed(assembler, late, 100.304) == [None, None]
    rest = [rmc(45000.3), vtg(course_deg=0.0, speed_kmh=0.0), hdt(31.0), gst(45000.3)]
    *_, pose = feed(assembler, rest, 100.312)
    assert isinstance(pose, GnssPose)
    assert (pose.sigma_east_m, pose.sigma_north_m) == (0.009, 0.012)  # its own GST
    assert pose.north_m == pytest.approx(enu(ORIGIN_LAT_DEG + 1e-4, ORIGIN_LON_DEG, 0)[1], abs=0.01)
    assert pose.measurement_time_s == pytest.approx(100.3 - LATENCY_S)
    assert assembler.counts["late"] == 2


def test_a_heading_after_its_epoch_went_out_does_not_land_in_the_next_one() -> None:
    assembler = new()
    warmed(assembler)
    feed(assembler, burst(45000.2, heading_deg=30.0), 100.2)  # complete: out already
    feed(assembler, [hdt(99.0)], 100.225)  # a duplicate at the burst's end
    assert assembler.counts["after_emit"] == 1
    next_burst = [b for b in burst(45000.3) if not b.startswith("GPHDT")]
    feed(assembler, next_burst, 100.3)
    pose = assembler.expire(100.3 + PARAMS.epoch_window_s + 1e-3)
    assert isinstance(pose, GnssPose)
    assert pose.heading_source is HeadingSource.COURSE  # not 99°: that was the last epoch's


def test_a_heading_sent_ahead_of_its_burst_belongs_to_it() -> None:
    assembler = new()
    for k in range(3):
        t_s, utc_s = 100.0 + k * PERIOD_S, 45000.0 + k * PERIOD_S
        *_, out = feed(assembler, [ths(10.0 * k), gga(utc_s), rmc(utc_s), gst(utc_s)], t_s)
    assert isinstance(out, GnssPose)
    assert out.yaw_rad == pytest.approx(math.radians(90.0 - 20.0), abs=1e-6)
    assert out.heading_source is HeadingSource.TRUE_HEADING


def test_no_fix_from_gga_quality_0_or_rmc_void() -> None:
    assembler = new()
    feed(assembler, [gga(45000.0, quality=0), gst(45000.0)], 10.0)
    out = assembler.expire(11.0)
    assert isinstance(out, GnssNoFix) and out.reason == "GGA quality 0"
    feed(assembler, [gga(45001.0), rmc(45001.0, status="V")], 12.0)
    out = assembler.expire(13.0)
    assert isinstance(out, GnssNoFix) and out.reason == "RMC void"
    assert out.measurement_time_s == pytest.approx(12.0 - LATENCY_S)
    [empty] = events_of("GPGGA,,,,,,0,00,99.9,,M,,M,,")  # a receiver before its first fix
    assert isinstance(assembler.update(empty, 14.0), GnssNoFix)


def test_midnight_is_a_new_epoch_and_a_utc_jump_back_recovers() -> None:
    assembler = new()
    assert feed(assembler, [gga(86399.9), gst(86399.9)], 10.0) == [None, None]
    before, after = feed(assembler, [gga(0.0), gst(0.0)], 10.1)
    # 23:59:59.9 closed by 00:00:00.0, which is new, not late, and complete at its GST.
    assert isinstance(before, GnssPose) and before.utc_time_of_day_s == 86399.9
    assert isinstance(after, GnssPose) and after.utc_time_of_day_s == 0.0
    assert assembler.counts["late"] == 0
    assert feed(assembler, [gga(86399.9), gst(86399.8)], 10.2) == [None, None]
    assert assembler.counts["late"] == 2
    # Older for longer than utc_jump_reset_s: the receiver's clock was reset, follow it.
    pose = epoch(assembler, [gga(80000.0), gst(80000.0)], 10.1 + PARAMS.utc_jump_reset_s + 0.1)
    assert isinstance(pose, GnssPose) and pose.utc_time_of_day_s == 80000.0
    assert assembler.counts["utc_jump"] == 1


def test_receive_time_going_backwards_is_refused() -> None:
    assembler = new()
    [event] = events_of(gga(45000.0))
    assembler.update(event, 10.0)
    assert assembler.update(event, 9.0) is None
    assert assembler.update(event, math.nan) is None
    assert assembler.counts["bad_receive_time"] == 2


# --- yaw rate -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("start_heading_deg", "step_deg"),
    [(355.0, 1.5), (5.0, -1.5), (275.0, -2.0), (265.0, 2.0)],  # across north; across ±180° ENU
)
def test_yaw_rate_from_headings_across_the_wrap(start_heading_deg: float, step_deg: float) -> None:
    assembler = new()
    rates, yaws, headings = [], [], []
    for k in range(8):
        heading_deg = (start_heading_deg + k * step_deg) % 360.0
        headings.append(heading_deg)
        out = epoch(assembler, burst(45000.0 + k * PERIOD_S, heading_deg), 100.0 + k * PERIOD_S)
        assert isinstance(out, GnssPose)
        rates.append(out.yaw_rate_rad_per_s)
        assert out.yaw_rad is not None
        yaws.append(out.yaw_rad)
    # Heading is clockwise, yaw counter-clockwise: a heading that grows turns right.
    expected = -math.radians(step_deg) / PERIOD_S
    assert rates[0] is None
    assert rates[1:] == pytest.approx([expected] * 7, rel=1e-6)
    # The headings (across north) or the ENU yaws (across west) did cross a cut.
    assert max(headings) - min(headings) > 180.0 or max(yaws) - min(yaws) > math.pi


def test_yaw_rate_is_low_passed() -> None:
    assembler = new()
    headings = [0.0, 0.0, 0.0, 3.0, 6.0]
    rates = []
    for k, heading_deg in enumerate(headings):
        out = epoch(assembler, burst(45000.0 + k * PERIOD_S, heading_deg), 100.0 + k * PERIOD_S)
        assert isinstance(out, GnssPose)
        rates.append(out.yaw_rate_rad_per_s)
    raw = -math.radians(3.0) / PERIOD_S
    alpha = PERIOD_S / (PARAMS.yaw_rate_time_constant_s + PERIOD_S)
    assert rates[3] == pytest.approx(alpha * raw)
    assert rates[4] == pytest.approx(alpha * raw + alpha * (raw - alpha * raw))


# --- extrapolation ------------------------------------------------------------------------


def pose_at(**changes: object) -> GnssPose:
    base = GnssPose(
        measurement_time_s=50.0,
        utc_time_of_day_s=45000.0,
        east_m=3.0,
        north_m=-7.0,
        up_m=0.0,
        quality=FixQuality.RTK_FIXED,
        satellites=14,
        hdop=0.8,
        yaw_rad=0.4,
        heading_source=HeadingSource.TRUE_HEADING,
        course_yaw_rad=None,
        speed_mps=4.47,
        yaw_rate_rad_per_s=0.0,
        sigma_east_m=0.02,
        sigma_north_m=0.03,
        sigma_worst_m=0.04,
        sigma_source=SigmaSource.GST,
    )
    return replace(base, **changes)  # type: ignore[arg-type]


@pytest.mark.parametrize("turn", [1.0, -1.0])
@pytest.mark.parametrize("sideslip_rad", [0.0, 0.05])
def test_extrapolation_follows_an_exact_arc(turn: float, sideslip_rad: float) -> None:
    """A point on a circle of radius R about (cx, cy), moving at v: after dt its angle
    about the centre has grown by ω·dt and its heading with it."""
    radius_m, speed_mps, dt_s, phase_rad = 15.0, 4.47, 0.18, 1.1
    omega = turn * speed_mps / radius_m
    cx, cy = 20.0, 5.0
    travel_rad = phase_rad + turn * math.pi / 2
    pose = pose_at(
        east_m=cx + radius_m * math.cos(phase_rad),
        north_m=cy + radius_m * math.sin(phase_rad),
        yaw_rad=travel_rad - sideslip_rad,
        course_yaw_rad=travel_rad if sideslip_rad else None,
        yaw_rate_rad_per_s=omega,
    )
    out = extrapolate(pose, 50.0 + dt_s, 0.25)
    assert out is not None
    later = phase_rad + omega * dt_s
    assert out.pose.x_m == pytest.approx(cx + radius_m * math.cos(later), abs=1e-9)
    assert out.pose.y_m == pytest.approx(cy + radius_m * math.sin(later), abs=1e-9)
    assert out.pose.yaw_rad == pytest.approx(travel_rad - sideslip_rad + omega * dt_s, abs=1e-12)
    assert out.extrapolation_s == pytest.approx(dt_s)


@pytest.mark.parametrize("yaw_rate", [0.0, 1e-12, -1e-7, None])
def test_extrapolation_at_zero_yaw_rate_is_a_straight_line(yaw_rate: float | None) -> None:
    out = extrapolate(pose_at(yaw_rate_rad_per_s=yaw_rate), 50.2, 0.25)
    assert out is not None
    # 1e-7 rad/s bends 0.9 m of travel by 9 nm: what is checked is that nothing blows up.
    assert out.pose.x_m == pytest.approx(3.0 + 4.47 * 0.2 * math.cos(0.4), abs=1e-7)
    assert out.pose.y_m == pytest.approx(-7.0 + 4.47 * 0.2 * math.sin(0.4), abs=1e-7)


def test_extrapolation_grows_sigma_and_refuses_what_it_cannot_know() -> None:
    out = extrapolate(pose_at(), 50.1, 0.25, sigma_growth_mps=0.5)
    assert out is not None
    assert (out.sigma_east_m, out.sigma_north_m, out.sigma_worst_m) == pytest.approx(
        (0.02 + 0.05, 0.03 + 0.05, 0.04 + 0.05)
    )
    assert extrapolate(pose_at(), 50.26, 0.25) is None  # too far
    assert extrapolate(pose_at(), 49.99, 0.25) is None  # from the future: a broken clock
    assert extrapolate(pose_at(), math.nan, 0.25) is None
    assert extrapolate(pose_at(yaw_rad=None), 50.1, 0.25) is None  # no heading
    assert extrapolate(pose_at(speed_mps=None), 50.1, 0.25) is None  # nothing to move by
    still = extrapolate(pose_at(speed_mps=None), 50.0, 0.25)
    assert still is not None and still.pose == pytest.approx((3.0, -7.0, 0.4))


# --- the verdict --------------------------------------------------------------------------

VERDICT = FixVerdictParams()


@pytest.mark.parametrize(
    ("pose", "now_s", "reason"),
    [
        (None, 50.0, "no fix"),
        (GnssNoFix(50.0, "RMC void"), 50.0, "no fix"),
        (pose_at(), 51.4, "fix lost: last fix 1.4 s ago (limit 0.5 s)"),
        (pose_at(), 50.52, "fix lost: last fix 0.52 s ago (limit 0.5 s)"),
        (pose_at(), 49.7, "fix lost: fix time 0.30 s ahead of now"),
        (pose_at(sigma_worst_m=0.8), 50.1, "fix degraded: σ 0.80 m (limit 0.15 m)"),
        (
            pose_at(sigma_worst_m=4.0, sigma_source=SigmaSource.HDOP),
            50.1,
            "fix degraded: σ 4.00 m estimated from HDOP (limit 0.15 m)",
        ),
        (
            pose_at(sigma_worst_m=None, sigma_source=SigmaSource.MISSING),
            50.1,
            "fix degraded: σ unknown (limit 0.15 m)",
        ),
        (
            pose_at(quality=FixQuality.GPS),
            50.1,
            "fix degraded: quality GPS (need RTK fixed or float)",
        ),
        (pose_at(yaw_rad=None, heading_source=HeadingSource.MISSING), 50.1, "no heading"),
        (
            pose_at(heading_source=HeadingSource.COURSE),
            50.1,
            "no heading: course over ground only",
        ),
        (pose_at(satellites=4), 50.1, "too few satellites: 4 (need 6)"),
        (pose_at(satellites=None), 50.1, "too few satellites: unknown (need 6)"),
    ],
)
def test_each_refusal_is_stated(
    pose: GnssPose | GnssNoFix | None, now_s: float, reason: str
) -> None:
    verdict = fix_verdict(pose, now_s, VERDICT)
    assert not verdict.ok
    assert verdict.reasons == (reason,)
    assert verdict.reason == reason


def test_a_good_fix_passes_and_the_params_decide_what_is_good() -> None:
    assert fix_verdict(pose_at(), 50.1, VERDICT).ok
    gps = pose_at(quality=FixQuality.GPS, sigma_worst_m=0.8, heading_source=HeadingSource.COURSE)
    lenient = FixVerdictParams(
        accepted_qualities=(FixQuality.GPS, FixQuality.DGPS),
        max_sigma_m=1.0,
        accept_course_as_heading=True,
    )
    assert fix_verdict(gps, 50.1, lenient).ok
    strict = replace(
        lenient, accepted_qualities=(FixQuality.DGPS, FixQuality.PPS, FixQuality.RTK_FIXED)
    )
    assert fix_verdict(gps, 50.1, strict).reason == (
        "fix degraded: quality GPS (need DGPS, PPS or RTK fixed)"
    )
    everything_wrong = pose_at(quality=FixQuality.GPS, satellites=3, sigma_worst_m=2.0)
    assert [r.split(":")[0] for r in fix_verdict(everything_wrong, 52.0, VERDICT).reasons] == [
        "fix lost",
        "fix degraded",
        "too few satellites",
        "fix degraded",
    ]
    with pytest.raises(ValueError, match="accepted_qualities"):
        FixVerdictParams(accepted_qualities=())
    with pytest.raises(ValueError, match="receiver_latency_s"):
        GnssPoseParams(receiver_latency_s=-0.01)


def test_a_verdict_end_to_end_from_nmea_lines() -> None:
    assembler = new()
    warmed(assembler)
    *_, pose = feed(assembler, burst(45000.2), 100.2)
    assert fix_verdict(pose, 100.25, VERDICT).ok
    assert fix_verdict(pose, 100.2 - LATENCY_S + 1.4, VERDICT).reason == (
        "fix lost: last fix 1.4 s ago (limit 0.5 s)"
    )


# --- properties ---------------------------------------------------------------------------

anything = st.floats(allow_nan=True, allow_infinity=True)
maybe = st.none() | anything
utc = st.none() | st.sampled_from([45000.0, 45000.1, 45000.2, 44999.9, 0.0, 86399.9]) | anything
events = st.one_of(
    st.builds(
        GgaFix,
        st.just("GP"),
        utc,
        maybe,
        maybe,
        st.none() | st.sampled_from(FixQuality),
        st.none() | st.integers(-5, 40),
        maybe,
        maybe,
        maybe,
        maybe,
    ),
    st.builds(RmcFix, st.just("GP"), st.booleans(), utc, st.none(), maybe, maybe, maybe, maybe),
    st.builds(VtgVelocity, st.just("GP"), st.booleans(), maybe, maybe),
    st.builds(
        Heading,
        st.just("GP"),
        st.sampled_from(["HDT", "THS", "GGA", "XXX"]),
        maybe,
        st.booleans(),
        st.none() | st.sampled_from(ThsMode),
    ),
    st.builds(GstError, st.just("GP"), utc, maybe, maybe, maybe, maybe, maybe, maybe, maybe),
)
# Plausible values too, so that poses do come out and get checked.
plausible = st.sampled_from(
    [e for k in range(3) for e in events_of(*burst(45000.0 + k * PERIOD_S, 100.0 * k))]
)
steps = st.one_of(
    st.floats(0.0, 0.01),  # within a burst
    st.floats(0.0, 0.3),
    st.sampled_from([-1.0, math.nan, math.inf, 5.0, 1e-9]),
)


def assert_finite(pose: GnssPose) -> None:
    for name, value in vars(pose).items():
        if isinstance(value, float):
            assert math.isfinite(value), (name, value)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 3), events, plausible, steps), min_size=5, max_size=60))
def test_any_event_sequence_never_raises_nor_yields_a_non_finite_pose(
    sequence: list[tuple[int, NmeaEvent, NmeaEvent, float]],
) -> None:
    assembler = new()
    now_s = 100.0
    outputs = []
    for choice, anything_event, plausible_event, step_s in sequence:
        event = anything_event if choice == 0 else plausible_event
        now_s = now_s + step_s if math.isfinite(now_s + step_s) else now_s
        outputs.append(assembler.update(event, now_s + (step_s if step_s < 0 else 0.0)))
        outputs.append(assembler.expire(now_s))
    for out in outputs:
        verdict = fix_verdict(out, now_s, VERDICT)
        assert verdict.ok == (verdict.reason == "") == (verdict.reasons == ())
        if isinstance(out, GnssPose):
            assert_finite(out)
            moved = extrapolate(out, out.measurement_time_s + 0.1, 0.25)
            if moved is not None:
                assert all(math.isfinite(v) for v in moved.pose)


def signature_burst(k: int) -> dict[str, str]:
    """Epoch k's sentences, every value unique to k, so a pose shows where each came from."""
    utc_s, heading_deg = 45000.0 + k * PERIOD_S, (20.0 * k + 5.0) % 360.0
    return {
        "GGA": gga(utc_s, ORIGIN_LAT_DEG + 1e-5 * k),
        "RMC": rmc(utc_s, speed_kn=2.0 + k, course_deg=heading_deg),
        "VTG": vtg(course_deg=heading_deg, speed_kmh=(2.0 + k) * 1.852),
        "HDT": hdt(heading_deg),
        "GST": gst(utc_s, sig_lat=0.01 + 0.001 * k, sig_lon=0.02 + 0.001 * k, major=0.05),
    }


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_dropped_reordered_and_late_sentences_are_never_mixed_across_epochs(
    data: st.DataObject,
) -> None:
    """Any drops, any order within a burst, timed sentences arriving a burst late: every
    field of every pose is its own epoch's, and each epoch whose GGA came on time comes out
    exactly once (or is counted as superseded by a newer one in the same call)."""
    epochs = data.draw(st.integers(2, 8))
    delayed: list[str] = []
    schedule: list[tuple[float, str]] = []  # (receive time, body)
    gga_times: dict[int, float] = {}
    for k in range(epochs):
        sentences = signature_burst(k)
        kept = data.draw(st.lists(st.sampled_from(sorted(sentences)), unique=True))
        timed = [kind for kind in kept if kind in ("GGA", "RMC", "GST")]
        # A timed sentence may come late only if another of its epoch came on time: a whole
        # epoch a period late cannot be told from an on-time one by receive times.
        late = data.draw(st.lists(st.sampled_from(timed), unique=True)) if len(timed) > 1 else []
        late = late[: len(timed) - 1]
        order = data.draw(st.permutations([kind for kind in kept if kind not in late]))
        bodies = [sentences[kind] for kind in order] + delayed
        delayed = [sentences[kind] for kind in late]
        start_s = 100.0 + k * PERIOD_S
        for i, body in enumerate(bodies):
            schedule.append((start_s + i * 0.004, body))
            if body is sentences["GGA"]:
                gga_times[k] = start_s + i * 0.004
    assembler = new()
    poses: list[GnssPose] = []
    for t_s, body in schedule:
        out = assembler.update(event_of(body), t_s)
        assert not isinstance(out, GnssNoFix)
        poses += [out] if out is not None else []
    last = assembler.expire(schedule[-1][0] + 1.0) if schedule else None
    poses += [last] if isinstance(last, GnssPose) else []

    assert len(poses) + assembler.counts["superseded"] == len(gga_times)
    for pose in poses:
        k = round((pose.utc_time_of_day_s - 45000.0) / PERIOD_S)
        heading_rad = math.radians((20.0 * k + 5.0) % 360.0)
        yaw_rad = math.pi / 2 - heading_rad
        assert pose.measurement_time_s == pytest.approx(gga_times[k] - LATENCY_S)
        expected_north = enu(
            nmea_angle(ORIGIN_LAT_DEG + 1e-5 * k, latitude=True)[2], ORIGIN_LON_DEG, 0
        )
        assert pose.north_m == pytest.approx(expected_north[1], abs=1e-3)
        if pose.yaw_rad is not None:  # from HDT or, moving at ≥ 1 m/s, the course: the same
            assert math.remainder(pose.yaw_rad - yaw_rad, math.tau) == pytest.approx(0, abs=1e-6)
        if pose.speed_mps is not None:
            assert pose.speed_mps == pytest.approx((2.0 + k) * KNOT_MPS, rel=1e-3)
        if pose.yaw_rate_rad_per_s is not None:
            # 20° more heading per epoch; the GGA's place in its burst moves the stamps by
            # up to 28 ms, so every raw rate (and any mean of them) lies in this band.
            fastest, slowest = math.radians(20.0) / 0.072, math.radians(20.0) / 0.128
            assert -fastest - 1e-9 <= pose.yaw_rate_rad_per_s <= -slowest + 1e-9
        if pose.sigma_source is SigmaSource.GST:
            assert (pose.sigma_north_m, pose.sigma_east_m) == pytest.approx(
                (0.01 + 0.001 * k, 0.02 + 0.001 * k)
            )
